"""Typed readers for the fields of a decoded msgpack map (PROTOCOL.md §3).

Each reader checks one field's type and range and raises ProtocolError; none does I/O
or knows which message it is reading beyond the name used in its error text.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.limits import Limits

MAX_UINT64: Final = (1 << 64) - 1


class _Missing:
    def __repr__(self) -> str:
        return "<required>"


REQUIRED: Final = _Missing()


def _type_name(value: Any) -> str:
    return {
        type(None): "nil",
        bool: "bool",
        int: "int",
        float: "float",
        str: "str",
        bytes: "bin",
        list: "array",
        dict: "map",
    }.get(type(value), type(value).__name__)


def invalid(where: str, expected: str, value: Any) -> ProtocolError:
    """The INVALID_FIELD error for field ``where`` holding ``value`` instead of ``expected``."""
    return ProtocolError(
        ErrorCode.INVALID_FIELD, f"{where} must be {expected}, got {_type_name(value)}"
    )


def _get(obj: Mapping[str, Any], key: str, where: str, default: Any) -> Any:
    # nil and absence mean the same thing, so clients in languages without "absent" can
    # send every key.
    value = obj.get(key)
    if value is None:
        if default is REQUIRED:
            raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where} is required")
        return default
    return value


def read_uint(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
    """An integer in [0, 2**64 - 1]; bool is not an integer here."""
    value = _get(obj, key, where, default)
    if value is default:
        return value
    if type(value) is not int or not 0 <= value <= MAX_UINT64:
        raise invalid(where, "an integer in [0, 2**64-1]", value)
    return value


def read_int(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
    """Any msgpack integer; bool is not an integer here."""
    value = _get(obj, key, where, default)
    if value is default:
        return value
    if type(value) is not int:
        raise invalid(where, "an integer", value)
    return value


def read_float(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
    """A finite number (msgpack int or float), returned as float; NaN/Inf -> NON_FINITE."""
    value = _get(obj, key, where, default)
    if value is default:
        return value
    return check_float(value, where)


def check_float(value: Any, where: str) -> float:
    """``value`` as a finite float, or the ProtocolError a peer should see."""
    if type(value) is int:
        if abs(value) > 1 << 1023:
            raise invalid(where, "a finite number", value)
        return float(value)
    if type(value) is not float:
        raise invalid(where, "a number", value)
    if not math.isfinite(value):
        raise ProtocolError(ErrorCode.NON_FINITE, f"{where} must be finite, got {value!r}")
    return value


def read_bool(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
    value = _get(obj, key, where, default)
    if value is default:
        return value
    if type(value) is not bool:
        raise invalid(where, "a bool", value)
    return value


def read_str(
    obj: Mapping[str, Any],
    key: str,
    where: str,
    limits: Limits,
    default: Any = REQUIRED,
    *,
    choices: tuple[str, ...] | None = None,
) -> Any:
    """A non-empty string of at most ``limits.max_string`` characters, or one of ``choices``."""
    value = _get(obj, key, where, default)
    if value is default:
        return value
    return check_str(value, where, limits, choices=choices)


def check_str(
    value: Any, where: str, limits: Limits | None, *, choices: tuple[str, ...] | None = None
) -> str:
    """``value`` as a non-empty string within ``limits`` (length unchecked when None)."""
    if type(value) is not str:
        raise invalid(where, "a string", value)
    if choices is not None:
        if value not in choices:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, f"{where} must be one of {list(choices)}, got {value!r}"
            )
        return value
    if limits is not None:
        check_str_length(value, where, limits)
    if not value:
        raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where} must not be empty")
    return value


def check_str_length(value: str, where: str, limits: Limits) -> None:
    if len(value) > limits.max_string:
        raise ProtocolError(
            ErrorCode.MESSAGE_TOO_LARGE,
            f"{where} has {len(value)} characters, more than the limit {limits.max_string}",
        )


def read_map(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
    value = _get(obj, key, where, default)
    if value is default:
        return value
    if type(value) is not dict:
        raise invalid(where, "a map", value)
    return value

"""Typed readers for the fields of a decoded msgpack map (PROTOCOL.md §3).

Each reader checks one field's type and range and raises ProtocolError; none does I/O
or knows which message it is reading beyond the name used in its error text.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, Final, Protocol

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


def _absent(where: str, default: Any) -> Any:
    # nil and absence mean the same thing, so clients in languages without "absent" can
    # send every key.
    if default is REQUIRED:
        raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where} is required")
    return default


def check_uint(value: Any, where: str) -> int:
    """``value`` as an integer in [0, 2**64 - 1]; bool is not an integer here."""
    if type(value) is not int or not 0 <= value <= MAX_UINT64:
        raise invalid(where, "an integer in [0, 2**64-1]", value)
    return value


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


def _exactly(kind: type, expected: str) -> Callable[[Any, str], Any]:
    """The check that a value's type is ``kind`` itself (so a bool is not an int)."""

    def check(value: Any, where: str) -> Any:
        if type(value) is not kind:
            raise invalid(where, expected, value)
        return value

    return check


check_int: Final = _exactly(int, "an integer")
check_bool: Final = _exactly(bool, "a bool")
check_map: Final = _exactly(dict, "a map")


class FieldReader(Protocol):
    """``read_*(obj, key, where, default)``: field ``key`` of ``obj``, checked."""

    def __call__(
        self, obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED
    ) -> Any: ...


def _reader(name: str, check: Callable[[Any, str], Any], doc: str) -> FieldReader:
    """A reader returning ``check(value, where)``, or ``default`` when the field is nil/absent.

    Built once per type rather than written out per type; a closure keeps the decode path
    at one Python call per field plus the check.
    """

    def read(obj: Mapping[str, Any], key: str, where: str, default: Any = REQUIRED) -> Any:
        value = obj.get(key)
        if value is None:
            return _absent(where, default)
        return check(value, where)

    read.__name__ = read.__qualname__ = name
    read.__doc__ = doc
    return read


read_uint: Final = _reader(
    "read_uint", check_uint, "An integer in [0, 2**64 - 1]; bool is not an integer here."
)
read_int: Final = _reader(
    "read_int", check_int, "Any msgpack integer; bool is not an integer here."
)
read_float: Final = _reader(
    "read_float",
    check_float,
    "A finite number (msgpack int or float), returned as float; NaN/Inf -> NON_FINITE.",
)
read_bool: Final = _reader("read_bool", check_bool, "A bool.")
read_map: Final = _reader("read_map", check_map, "A map.")


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
    value = obj.get(key)
    if value is None:
        return _absent(where, default)
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

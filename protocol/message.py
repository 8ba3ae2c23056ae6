"""The base of every protocol message and the field checks the message families share.

`Message` and its array-comparing subclass, the header, and the checks that raise
`ProtocolError`; the messages themselves live in handshake, frames, calibration, control.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any, ClassVar, Final, Self, TypeVar

import numpy as np

from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import (
    invalid,
)
from facecast.protocol.head import Head
from facecast.protocol.limits import Limits
from facecast.protocol.stamps import Stamps

PROTOCOL_VERSION: Final = 1

_DEFAULT_LIMITS: Final = Limits()


def _fail(where: str, expected: str, value: Any) -> ProtocolError:
    return invalid(where, expected, value)


def _check_choice(value: Any, where: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD, f"{where} must be one of {list(choices)}, got {value!r}"
        )


def _check_array(value: Any, where: str, trailing: tuple[int, ...]) -> None:
    if (
        not isinstance(value, np.ndarray)
        or value.ndim != 1 + len(trailing)
        or value.shape[1:] != trailing
        or value.shape[0] == 0
        or value.dtype.kind != "f"
        or value.dtype.itemsize not in (2, 4, 8)
    ):
        shape = f"(N, {', '.join(map(str, trailing))})" if trailing else "(N,)"
        got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value)
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY, f"{where} must be a non-empty float {shape} array, got {got}"
        )


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, Mapping) and isinstance(b, Mapping):  # of arrays (calibrate.blinks)
        return a.keys() == b.keys() and all(_same(a[key], b[key]) for key in a)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and bool(np.array_equal(a, b))
        )
    return bool(a == b)


class Message:
    """Base of all messages: ``TYPE`` is the wire ``type``; ``serialize`` gives the map."""

    TYPE: ClassVar[str]

    def serialize(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        raise NotImplementedError


class _ArrayMessage(Message):
    """Equality for messages holding arrays: same dtype, shape and values."""

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))  # type: ignore[arg-type]

    __hash__ = None  # type: ignore[assignment]


_M = TypeVar("_M", bound=Message)


def _checked(cls: type[_M], **values: Any) -> _M:
    """A message of ``cls`` from field values its ``parse`` has already validated.

    Skips ``__post_init__``, which would check the same fields again (a third of a frame's
    decode). Every field must be given, each exactly as ``__post_init__`` would store it.
    """
    message = object.__new__(cls)
    message.__dict__.update(values)
    return message


def _header(kind: str) -> dict[str, Any]:
    return {"v": PROTOCOL_VERSION, "type": kind}


def _check_head(value: Any, where: str) -> None:
    if value is not None and not isinstance(value, Head):
        raise _fail(where, "nil or a Head", value)


def _read_head(obj: Mapping[str, Any], where: str) -> Head | None:
    value = obj.get("head")
    return None if value is None else Head.parse(value, where)


def _check_stamps(value: Any, where: str) -> None:
    if value is not None and not isinstance(value, Stamps):
        raise _fail(where, "nil or Stamps", value)


def _read_stamps(obj: Mapping[str, Any], where: str) -> Stamps | None:
    value = obj.get("stamps")
    return None if value is None else Stamps.parse(value, where)

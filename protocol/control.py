"""The control messages: `Ping`/`Pong` (§5.1.4, §5.2.4), `Error` (§5.2.3), channel events.

`ChannelIdle`, `ChannelLive` (§5.2.6) and `FaceLost` (§5.2.7): what the peers say besides
frames, results and calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final, Self

from facecast.protocol.errors import ErrorCode, ProtocolError, error_code
from facecast.protocol.fields import (
    check_bool,
    check_float,
    check_str,
    check_str_length,
    check_uint,
    read_bool,
    read_float,
    read_int,
    read_str,
    read_uint,
)
from facecast.protocol.limits import Limits
from facecast.protocol.message import (
    _DEFAULT_LIMITS,
    Message,
    _fail,
    _header,
)

#: Longest error message a server sends; longer ones are cut, so they always decode.
MAX_ERROR_MESSAGE: Final = 256


@dataclass(frozen=True, kw_only=True)
class _Probe(Message):
    """Fields shared by `Ping` and `Pong`."""

    id: int
    ts: float

    def __post_init__(self) -> None:
        check_uint(self.id, f"{self.TYPE}.id")
        object.__setattr__(self, "ts", check_float(self.ts, f"{self.TYPE}.ts"))

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "id": self.id, "ts": self.ts}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        return cls(
            id=read_uint(obj, "id", f"{cls.TYPE}.id"), ts=read_float(obj, "ts", f"{cls.TYPE}.ts")
        )


@dataclass(frozen=True, kw_only=True)
class Ping(_Probe):
    """Liveness and round-trip probe (§5.1.4); answered by a `Pong` with the same fields.

    Attributes
    ----------
    id : int
        Sender-chosen probe id.
    ts : float
        Sender's clock when sent, seconds.
    """

    TYPE: ClassVar[str] = "ping"


@dataclass(frozen=True, kw_only=True)
class Error(Message):
    """Something went wrong (§5.2.3, codes in §6).

    ``code`` is an `ErrorCode`, or a bare int for a code newer than this library.
    ``message`` is cut to `MAX_ERROR_MESSAGE` characters. ``dropped``: on RATE_LIMITED,
    the session's total of discarded frames so far, like ``result.dropped`` (§8); None
    (not sent) on other errors.
    """

    TYPE: ClassVar[str] = "error"
    code: ErrorCode | int
    message: str
    seq: int | None = None
    fatal: bool = False
    dropped: int | None = None

    def __post_init__(self) -> None:
        if type(self.code) is not int and not isinstance(self.code, ErrorCode):
            raise _fail("error.code", "an integer", self.code)
        object.__setattr__(self, "code", error_code(int(self.code)))
        if type(self.message) is not str:
            raise _fail("error.message", "a string", self.message)
        if len(self.message) > MAX_ERROR_MESSAGE:
            object.__setattr__(self, "message", self.message[: MAX_ERROR_MESSAGE - 1] + "…")
        if self.seq is not None:
            check_uint(self.seq, "error.seq")
        check_bool(self.fatal, "error.fatal")
        if self.dropped is not None:
            check_uint(self.dropped, "error.dropped")

    def serialize(self) -> dict[str, Any]:
        fields = {
            **_header(self.TYPE),
            "code": int(self.code),
            "message": self.message,
            "seq": self.seq,
            "fatal": self.fatal,
        }
        if self.dropped is not None:
            fields["dropped"] = self.dropped
        return fields

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Error:
        message = obj.get("message")
        if type(message) is not str:
            raise _fail("error.message", "a string", message)
        check_str_length(message, "error.message", limits)
        return cls(
            code=read_int(obj, "code", "error.code"),
            message=message,
            seq=read_uint(obj, "seq", "error.seq", None),
            fatal=read_bool(obj, "fatal", "error.fatal", False),
            dropped=read_uint(obj, "dropped", "error.dropped", None),
        )

    def to_exception(self) -> ProtocolError:
        """This error as a `ProtocolError` a client can raise."""
        return ProtocolError(self.code, self.message, seq=self.seq, fatal=self.fatal)

    @classmethod
    def of(cls, error: ProtocolError) -> Error:
        """The `Error` message that reports ``error`` to the peer."""
        return cls(code=error.code, message=error.message, seq=error.seq, fatal=error.fatal)


@dataclass(frozen=True, kw_only=True)
class Pong(_Probe):
    """Answer to a `Ping` (§5.2.4): ``id`` and ``ts`` echoed unchanged.

    Attributes
    ----------
    server_ts : float or None
        The server's wall clock when it answered, seconds since the Unix epoch: with the
        round trip, a client's estimate of its clock's offset to the server's (§5.4).
        None: not sent (servers before it; the bytes are then as before).
    """

    TYPE: ClassVar[str] = "pong"
    server_ts: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.server_ts is not None:
            object.__setattr__(self, "server_ts", check_float(self.server_ts, "pong.server_ts"))

    def serialize(self) -> dict[str, Any]:
        out = super().serialize()
        if self.server_ts is not None:
            out["server_ts"] = self.server_ts
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        return cls(
            id=read_uint(obj, "id", "pong.id"),
            ts=read_float(obj, "ts", "pong.ts"),
            server_ts=read_float(obj, "server_ts", "pong.server_ts", None),
        )


@dataclass(frozen=True, kw_only=True)
class _ChannelEvent(Message):
    """Fields shared by `ChannelIdle` and `ChannelLive`."""

    channel: str

    def __post_init__(self) -> None:
        check_str(self.channel, f"{self.TYPE}.channel", None)

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "channel": self.channel}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        return cls(channel=read_str(obj, "channel", f"{cls.TYPE}.channel", limits))


@dataclass(frozen=True, kw_only=True)
class ChannelIdle(_ChannelEvent):
    """The watched channel has no publisher (§5.2.6)."""

    TYPE: ClassVar[str] = "channel_idle"


@dataclass(frozen=True, kw_only=True)
class ChannelLive(_ChannelEvent):
    """The watched channel has a publisher again (§5.2.6)."""

    TYPE: ClassVar[str] = "channel_live"


@dataclass(frozen=True, kw_only=True)
class FaceLost(Message):
    """The publisher's tracker lost the face (§5.2.7); ``since`` is the last frame's ``ts``."""

    TYPE: ClassVar[str] = "face_lost"
    since: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "since", check_float(self.since, "face_lost.since"))

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "since": self.since}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> FaceLost:
        return cls(since=read_float(obj, "since", "face_lost.since"))

"""The protocol's one exception type and its stable numeric error codes (PROTOCOL.md §6).

Only codes and the exception live here; no decoding, no I/O. The tree::

    facecast.errors.FacecastError, ValueError
    └── ProtocolError(code, message, *, seq=None, fatal=False)
            code: ErrorCode   1xxx malformed or unacceptable message (client's fault)
                              2xxx refused by the service (rig, auth, rate, capacity)
                              3000 INTERNAL (server's fault)

Unlike the other FacecastErrors, whose ``code`` is a string per class, a ProtocolError's
``code`` is the number the wire carries: one class, every code of §6.
"""

from __future__ import annotations

from enum import IntEnum, unique

from facecast.errors import FacecastError


@unique
class ErrorCode(IntEnum):
    """Stable numeric error codes; a number, once published, never changes meaning."""

    MALFORMED = 1001
    INVALID_MESSAGE = 1002
    UNKNOWN_TYPE = 1003
    UNSUPPORTED_VERSION = 1004
    INVALID_FIELD = 1005
    MESSAGE_TOO_LARGE = 1006
    INVALID_ARRAY = 1007
    NON_FINITE = 1008
    WRONG_STATE = 1009
    TEXT_NOT_SUPPORTED = 1010
    UNKNOWN_RIG = 2001
    WRONG_POINT_COUNT = 2002
    RATE_LIMITED = 2003
    IDLE_TIMEOUT = 2004
    UNAUTHORIZED = 2005
    FORBIDDEN = 2006
    OVERLOADED = 2007
    CHANNEL_BUSY = 2008
    CALIBRATION_FAILED = 2009
    POINTS_OUT_OF_RANGE = 2010
    RESULT_NOT_FINITE = 2011
    INTERNAL = 3000


def error_code(value: int) -> ErrorCode | int:
    """Return the `ErrorCode` for ``value``, or the bare int for a code this version lacks.

    A client must survive a server newer than itself, so unknown codes are kept, not refused.
    """
    try:
        return ErrorCode(value)
    except ValueError:
        return value


class ProtocolError(FacecastError, ValueError):
    """A message that cannot be accepted, or a refusal, with a stable code.

    Parameters
    ----------
    code : ErrorCode or int
        Stable numeric code (§6 of PROTOCOL.md).
    message : str
        Human-readable explanation; not for machines to parse.
    seq : int or None
        Sequence number of the frame the error concerns, when there is one.
    fatal : bool
        True when the connection is closed after the error is sent.
    """

    def __init__(
        self, code: ErrorCode | int, message: str, *, seq: int | None = None, fatal: bool = False
    ) -> None:
        super().__init__(message)
        self.code: ErrorCode | int = error_code(int(code))
        self.message = message
        self.seq = seq
        self.fatal = fatal

    @property
    def code_name(self) -> str:
        """The code by name (metrics labels, close reasons, counts); its number if unnamed."""
        return self.code.name if isinstance(self.code, ErrorCode) else str(int(self.code))

    def __str__(self) -> str:
        name = self.code.name if isinstance(self.code, ErrorCode) else "UNKNOWN"
        return f"[{int(self.code)} {name}] {self.message}"

    def __repr__(self) -> str:
        return (
            f"ProtocolError({self.code!r}, {self.message!r}, seq={self.seq!r}, "
            f"fatal={self.fatal!r})"
        )

    def evolve(self, *, seq: int | None = None, fatal: bool | None = None) -> ProtocolError:
        """Return a copy with ``seq`` filled in (if not already set) and/or ``fatal`` changed."""
        return ProtocolError(
            self.code,
            self.message,
            seq=self.seq if self.seq is not None else seq,
            fatal=self.fatal if fatal is None else fatal,
        )

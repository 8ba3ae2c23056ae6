"""How a connection ends: the `Closing` that carries its close code and last error.

Raised by the core's rules (a fatal error, the idle timeout) and by the driver (a bug,
a shutdown); the driver sends the error, then the close, each within ``CLOSE_GRACE``.
"""

from __future__ import annotations

from facecast.protocol import ErrorCode, ProtocolError, close_code

__all__ = ["CLOSE_GRACE", "Closing"]

#: How long a closing connection waits to hand its last error, then its close frame, to
#: the socket (each).
CLOSE_GRACE = 1.0


class Closing(Exception):
    """Ends a connection with a close code (and maybe a fatal error sent first)."""

    def __init__(self, code: int, reason: str, error: ProtocolError | None = None) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.error = error

    @classmethod
    def for_error(cls, error: ProtocolError) -> Closing:
        """The close a fatal ``error`` calls for (PROTOCOL.md §7: its code's close code)."""
        return cls(close_code(error), error.code_name.lower(), error)

    @classmethod
    def internal(cls) -> Closing:
        """The close of a connection whose server side failed (a bug): 1011, INTERNAL."""
        error = ProtocolError(ErrorCode.INTERNAL, "internal server error", fatal=True)
        return cls(1011, "internal error", error)

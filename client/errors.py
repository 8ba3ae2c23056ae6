"""The client library's exceptions: what connecting to and talking with a server raises.

No I/O here. The tree::

    ConnectionError
    └── ConnectionFailed(message, *, attempts=1, last_error=None)
            no session could be opened, or a lost one could not be re-opened
"""

from __future__ import annotations

__all__ = ["ConnectionFailed"]


class ConnectionFailed(ConnectionError):
    """No session could be opened, or a lost one could not be re-opened.

    Attributes
    ----------
    attempts : int
        Connection attempts made before giving up.
    last_error : BaseException or None
        Why the last attempt failed.
    """

    def __init__(
        self, message: str, *, attempts: int = 1, last_error: BaseException | None = None
    ) -> None:
        super().__init__(message)
        self.attempts = attempts
        self.last_error = last_error

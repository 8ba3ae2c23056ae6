"""The client library's exceptions: what connecting to and asking a server can raise.

No I/O here. The tree (the root is ``facecast.errors.FacecastError``)::

    ClientError                                   "client_error"
    ├── ConnectionFailed(ClientError, ConnectionError)     "connection_failed"
    │       no session could be opened, or a lost one not re-opened (also: closed)
    └── ServerRequestError(ClientError, ConnectionError)   "server_request_failed"
        │   a REST request failed; an instance's ``code`` is the server's problem
        │   code (``rig_not_found``...) or ``unreachable``, ``too_large``
        └── RigNotFound(ServerRequestError, LookupError)   "rig_not_on_server"
                the server has no rig with that id (HTTP 404 ``rig_not_found``)

What the server refuses over WebSocket (unknown rig, bad token, rate limit) arrives as
`facecast.protocol.ProtocolError` with the wire's numeric code, re-exported here.
"""

from __future__ import annotations

from facecast.errors import FacecastError
from facecast.protocol.errors import ProtocolError

__all__ = [
    "ClientError",
    "ConnectionFailed",
    "ProtocolError",
    "RigNotFound",
    "ServerRequestError",
]


class ClientError(FacecastError):
    """Base of the client library's own errors."""

    code: str = "client_error"


class ConnectionFailed(ClientError, ConnectionError):
    """No session could be opened, or a lost one could not be re-opened.

    Attributes
    ----------
    attempts : int
        Connection attempts made before giving up.
    last_error : BaseException or None
        Why the last attempt failed.
    """

    code: str = "connection_failed"

    def __init__(
        self, message: str, *, attempts: int = 1, last_error: BaseException | None = None
    ) -> None:
        super().__init__(message)
        self.attempts = attempts
        self.last_error = last_error


class ServerRequestError(ClientError, ConnectionError):
    """A REST request failed: unreachable server, or an HTTP problem response.

    Attributes
    ----------
    status : int or None
        HTTP status, None when no response arrived.
    code : str
        The problem's stable ``code`` (e.g. ``rig_not_found``), or ``unreachable``.
    """

    code: str = "server_request_failed"

    def __init__(self, message: str, *, status: int | None, code: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code


class RigNotFound(ServerRequestError, LookupError):
    """The server has no rig with the id asked for (HTTP 404, problem ``rig_not_found``)."""

    code: str = "rig_not_on_server"

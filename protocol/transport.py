"""WebSocket transport conventions: URL paths, subprotocols, tokens, close codes (PROTOCOL.md §2).

Pure helpers a server or client calls with values it already has (headers, query
parameters); they never open sockets or look tokens up.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Final

from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import check_str
from facecast.protocol.limits import Limits
from facecast.protocol.messages import CHANNEL_OUTPUTS, RESULT_DTYPES, Hello

STREAM_PATH: Final = "/v1/stream"
PUBLISH_PATH: Final = "/v1/channels/{name}/publish"
WATCH_PATH: Final = "/v1/channels/{name}/watch"

#: The subprotocol a client offers and the server selects.
SUBPROTOCOL: Final = "facecast.v1"
#: Prefix of the subprotocol that carries a bearer token, for clients (browsers) that
#: cannot set an Authorization header on a WebSocket.
BEARER_SUBPROTOCOL_PREFIX: Final = "facecast.bearer."

_CLOSE_CODES: Final[dict[ErrorCode | int, int]] = {
    ErrorCode.TEXT_NOT_SUPPORTED: 1003,
    ErrorCode.MESSAGE_TOO_LARGE: 1009,
    ErrorCode.INTERNAL: 1011,
    ErrorCode.OVERLOADED: 1013,
}


def bearer_token(
    *,
    authorization: str | None = None,
    subprotocols: Iterable[str] = (),
    query_token: str | None = None,
) -> str | None:
    """The bearer token a connecting client presented, or None when it presented none.

    Looked for, in this order: the ``Authorization: Bearer TOKEN`` header, an offered
    ``facecast.bearer.TOKEN`` subprotocol, the ``token`` query parameter (§2.2). The
    first place that has one wins.

    Raises
    ------
    ProtocolError
        UNAUTHORIZED when an Authorization header is present but not a non-empty Bearer
        credential.
    """
    if authorization is not None:
        scheme, _, credential = authorization.strip().partition(" ")
        credential = credential.strip()
        if scheme.lower() != "bearer" or not credential:
            raise ProtocolError(
                ErrorCode.UNAUTHORIZED,
                "the Authorization header must be 'Bearer <token>'",
                fatal=True,
            )
        return credential
    for offered in subprotocols:
        if offered.startswith(BEARER_SUBPROTOCOL_PREFIX):
            token = offered[len(BEARER_SUBPROTOCOL_PREFIX) :]
            if token:
                return token
    if query_token:
        return query_token
    return None


def select_subprotocol(offered: Iterable[str]) -> str | None:
    """The subprotocol to accept: ``facecast.v1`` when offered, else None.

    Never the bearer subprotocol: echoing it would put the token in a response header.
    """
    return SUBPROTOCOL if SUBPROTOCOL in offered else None


_DEFAULT_LIMITS: Final = Limits()


def watch_hello(query: Mapping[str, str], limits: Limits = _DEFAULT_LIMITS) -> Hello:
    """The session parameters a channel watcher gives in its query string (§2.3).

    ``rig`` is required; ``output`` defaults to "weights", ``dtype`` to "f32".

    Raises
    ------
    ProtocolError
        INVALID_FIELD (or MESSAGE_TOO_LARGE) for a missing or bad parameter; fatal.
    """
    try:
        rig = query.get("rig")
        if rig is None:
            raise ProtocolError(ErrorCode.INVALID_FIELD, "the query parameter rig is required")
        return Hello(
            rig=check_str(rig, "query rig", limits),
            output=check_str(
                query.get("output", "weights"), "query output", limits, choices=CHANNEL_OUTPUTS
            ),
            dtype=check_str(
                query.get("dtype", "f32"), "query dtype", limits, choices=RESULT_DTYPES
            ),
        )
    except ProtocolError as exc:
        raise exc.evolve(fatal=True) from None


def close_code(error: ProtocolError) -> int:
    """WebSocket close code to use after sending a fatal ``error`` (§6.3).

    1003 text not supported, 1009 too large, 1011 internal, 1013 overloaded, 1008 (policy
    violation) for everything else.
    """
    return _CLOSE_CODES.get(error.code, 1008)

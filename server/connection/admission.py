"""Admitting a WebSocket connection: who is calling, whether there is room, then serving it.

One rule for ``/v1/stream`` and the channel endpoints: a caller's token checked for a
role, the registry's limits and quotas, the refusal (``refusal``) when either says no,
and the accept-run-unregister around the connection (``driver``). No protocol here.
"""

from __future__ import annotations

from fastapi import WebSocket

from facecast.protocol import ErrorCode, ProtocolError, bearer_token

from ..errors import ApiError
from ..guards.auth import Principal, authorize
from ..settings import Settings
from .driver import Driver
from .refusal import refuse
from .registry import Owner, Quotas

__all__ = ["authorize_websocket", "serve"]


def authorize_websocket(websocket: WebSocket, settings: Settings, role: str) -> Principal:
    """The caller holding ``role`` (PROTOCOL.md §2.2), or a fatal ProtocolError.

    UNAUTHORIZED (no or unknown token) or FORBIDDEN (wrong role); a token given in two
    ways raises what ``bearer_token`` raises, made fatal.
    """
    try:
        token = bearer_token(
            authorization=websocket.headers.get("authorization"),
            subprotocols=list(websocket.scope.get("subprotocols") or ()),
            query_token=websocket.query_params.get("token"),
        )
    except ProtocolError as exc:
        raise exc.evolve(fatal=True) from None
    try:
        return authorize(settings, token, (role,))
    except ApiError as exc:
        code = ErrorCode.UNAUTHORIZED if exc.status == 401 else ErrorCode.FORBIDDEN
        raise ProtocolError(code, exc.detail, fatal=True) from None


async def serve(
    websocket: WebSocket,
    connection: Driver,
    subprotocol: str | None,
    principal: Principal,
    *,
    publisher: bool = False,
    wait_first: bool = True,
) -> None:
    """Admit ``connection`` (limits and quotas), accept, and run it until it ends.

    Refused (OVERLOADED: full, over a quota, shutting down), the client gets the error
    and the close in bounded time (``refuse``; ``wait_first``: for its first message).
    ``connection.leave`` runs in every case, after the registry forgot it.
    """
    app = websocket.app
    registry = app.state.sessions
    settings: Settings = app.state.settings
    owner = Owner.of(settings, principal.name, websocket.client)
    why = registry.admit(connection, Quotas.from_settings(settings), owner, publisher=publisher)
    if why is not None:
        error = ProtocolError(ErrorCode.OVERLOADED, why, fatal=True)
        await refuse(
            websocket, error, subprotocol, timeout=settings.refuse_timeout, wait_first=wait_first
        )
        await connection.leave()
        return
    app.state.metrics.connections.inc()
    try:
        await websocket.accept(subprotocol=subprotocol)
        await connection.run()
    finally:
        registry.remove(connection)
        app.state.metrics.connections.dec()
        await connection.leave()  # idempotent; covers a failed accept

"""``WS /v1/stream``: authenticate, admit and hand the connection to a ``Session``.

Refusals (no/unknown token, wrong role, too many connections, shutting down) accept the
handshake, send one protocol ``error`` and close, so clients see a code, not a bare 403.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from fastapi import APIRouter, WebSocket

from facecast.protocol import (
    STREAM_PATH,
    ErrorCode,
    ProtocolError,
    ServerProtocol,
    bearer_token,
    close_code,
    select_subprotocol,
)

from .auth import authorize
from .blending import BlendBatcher
from .errors import ApiError
from .session import Session
from .settings import Settings

__all__ = ["router"]

log = logging.getLogger("facecast.server.stream")

router = APIRouter(tags=["stream"])


#: How long a refused connection may take to send its first message (see ``_refuse``).
_REFUSE_WAIT = 1.0


async def _refuse(websocket: WebSocket, error: ProtocolError, subprotocol: str | None) -> None:
    """Accept, answer the client's first message with ``error`` (fatal), then close.

    Waiting for that first message (the ``hello``, at most ``_REFUSE_WAIT`` seconds)
    means a client that sends right after connecting has finished sending before the
    close arrives, so it reads the error instead of failing on a send to a closed socket.
    """
    with contextlib.suppress(Exception):
        await websocket.accept(subprotocol=subprotocol)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(_REFUSE_WAIT):
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
        await websocket.send_bytes(ServerProtocol().fail(error))
        await websocket.close(close_code(error), error.code.name.lower())


@router.websocket(STREAM_PATH)
async def stream(websocket: WebSocket) -> None:
    """One streaming session per connection (protocol: facecast.protocol, PROTOCOL.md)."""
    app = websocket.app
    settings: Settings = app.state.settings
    offered = list(websocket.scope.get("subprotocols") or ())
    subprotocol = select_subprotocol(offered)
    try:
        token = bearer_token(
            authorization=websocket.headers.get("authorization"),
            subprotocols=offered,
            query_token=websocket.query_params.get("token"),
        )
        principal = authorize(settings, token, ("stream",))
    except ProtocolError as exc:
        await _refuse(websocket, exc.evolve(fatal=True), subprotocol)
        return
    except ApiError as exc:
        code = ErrorCode.UNAUTHORIZED if exc.status == 401 else ErrorCode.FORBIDDEN
        log.info(
            "stream refused",
            extra={"event": "stream.refused", "code": code.name, "status": exc.status},
        )
        app.state.metrics.errors.labels(code.name).inc()
        await _refuse(websocket, ProtocolError(code, exc.detail, fatal=True), subprotocol)
        return

    blender = getattr(app.state, "blend_batcher", None)
    if blender is None:
        # One per app, so frames of all its sessions on one rig blend together.
        blender = app.state.blend_batcher = BlendBatcher(
            app.state.clone_executor,
            concurrency=settings.clone_threads,
            stages=app.state.metrics.stages if settings.stage_timing else None,
        )
    session = Session(
        websocket,
        settings=settings,
        store=app.state.store,
        metrics=app.state.metrics,
        executor=app.state.clone_executor,
        blender=blender,
        principal=principal.name,
    )
    registry = app.state.sessions
    if not registry.admit(session, settings.max_connections):
        why = (
            "the server is shutting down"
            if registry.closing
            else f"the server is at its limit of {settings.max_connections} connections"
        )
        app.state.metrics.errors.labels(ErrorCode.OVERLOADED.name).inc()
        await _refuse(websocket, ProtocolError(ErrorCode.OVERLOADED, why, fatal=True), subprotocol)
        return
    app.state.metrics.connections.inc()
    try:
        await websocket.accept(subprotocol=subprotocol)
        await session.run()
    finally:
        registry.remove(session)
        app.state.metrics.connections.dec()

"""``WS /v1/stream``: authenticate, admit and hand the connection to a ``Session``.

Refusals (no/unknown token, wrong role, too many connections, shutting down) accept the
handshake, send one protocol ``error`` and close, so clients see a code, not a bare 403.
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, WebSocket

from facecast.protocol import (
    STREAM_PATH,
    ErrorCode,
    ProtocolError,
    bearer_token,
    select_subprotocol,
)

from .auth import authorize
from .blending import BlendBatcher
from .errors import ApiError
from .refusal import refuse
from .session import Session
from .sessions import Owner, Quotas
from .settings import Settings

__all__ = ["router"]

log = logging.getLogger("facecast.server.stream")

router = APIRouter(tags=["stream"])


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
        await refuse(
            websocket, exc.evolve(fatal=True), subprotocol, timeout=settings.refuse_timeout
        )
        return
    except ApiError as exc:
        code = ErrorCode.UNAUTHORIZED if exc.status == 401 else ErrorCode.FORBIDDEN
        log.info(
            "stream refused",
            extra={"event": "stream.refused", "code": code.name, "status": exc.status},
        )
        app.state.metrics.errors.labels(code.name).inc()
        await refuse(
            websocket,
            ProtocolError(code, exc.detail, fatal=True),
            subprotocol,
            timeout=settings.refuse_timeout,
        )
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
    owner = Owner.of(settings, principal.name, websocket.client)
    why = registry.admit(session, Quotas.from_settings(settings), owner)
    if why is not None:
        app.state.metrics.errors.labels(ErrorCode.OVERLOADED.name).inc()
        await refuse(
            websocket,
            ProtocolError(ErrorCode.OVERLOADED, why, fatal=True),
            subprotocol,
            timeout=settings.refuse_timeout,
        )
        return
    app.state.metrics.connections.inc()
    try:
        await websocket.accept(subprotocol=subprotocol)
        await session.run()
    finally:
        registry.remove(session)
        app.state.metrics.connections.dec()

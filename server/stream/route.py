"""``WS /v1/stream``: authenticate, admit and hand the connection to a ``Session``.

Refusals (no/unknown token, wrong role, too many connections, shutting down) accept the
handshake, send one protocol ``error`` and close, so clients see a code, not a bare 403.
"""

from __future__ import annotations

import logging
import time

from fastapi import APIRouter, WebSocket

from facecast.protocol import STREAM_PATH, ProtocolError, select_subprotocol

from ..connection.admission import authorize_websocket, serve
from ..connection.refusal import refuse
from ..logs import RefusalLog
from ..settings import Settings
from .session import Session

__all__ = ["router"]

log = logging.getLogger("facecast.server.stream")

router = APIRouter(tags=["stream"])


@router.websocket(STREAM_PATH)
async def stream(websocket: WebSocket) -> None:
    """One streaming session per connection (protocol: facecast.protocol, PROTOCOL.md)."""
    app = websocket.app
    settings: Settings = app.state.settings
    subprotocol = select_subprotocol(list(websocket.scope.get("subprotocols") or ()))
    try:
        principal = authorize_websocket(websocket, settings, "stream")
    except ProtocolError as exc:
        refusals = getattr(app.state, "stream_refusals", None)
        if refusals is None:  # one per app: a tokenless flood is one line per streak
            refusals = app.state.stream_refusals = RefusalLog(log, "stream.refused",
                                                              "stream refused")  # fmt: skip
        refusals.refused(exc.code_name, time.monotonic())
        await refuse(websocket, exc, subprotocol, timeout=settings.refuse_timeout)
        return
    session = Session(
        websocket,
        settings=settings,
        store=app.state.store,
        metrics=app.state.metrics,
        executor=app.state.clone_executor,
        blender=app.state.blend_batcher,
        principal=principal.name,
    )
    await serve(websocket, session, subprotocol, principal)

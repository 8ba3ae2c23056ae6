"""Refusing a WebSocket connection with a protocol error, in bounded time whatever the peer does.

One rule for ``/v1/stream`` and the channel endpoints: count the error (the app's
``facecast_errors`` metric), accept (so the client reads a code, not a bare 403), wait
briefly for its first message, send one fatal ``error``, close.
It decides nothing about why a connection is refused.
"""

from __future__ import annotations

import asyncio
import contextlib

from starlette.websockets import WebSocket

from facecast.protocol import ProtocolError, ServerProtocol

from .closing import Closing

__all__ = ["FIRST_MESSAGE_WAIT", "refuse"]

#: How long a refused connection may take to send its first message (its ``hello``).
FIRST_MESSAGE_WAIT = 1.0


async def refuse(
    websocket: WebSocket,
    error: ProtocolError,
    subprotocol: str | None,
    *,
    timeout: float,
    wait_first: bool = True,
) -> None:
    """Count ``error``; accept, answer the first message with it (fatal), close: ``timeout`` s.

    Waiting for that first message (at most ``FIRST_MESSAGE_WAIT``) means a client that
    sends right after connecting has finished sending before the close arrives, so it
    reads the error instead of failing on a send to a closed socket. A peer that does
    not read cannot hold the refusal open: past ``timeout`` the handler returns, and
    uvicorn drops the connection.
    """
    websocket.app.state.metrics.errors.labels(error.code_name).inc()
    with contextlib.suppress(Exception):
        async with asyncio.timeout(timeout):
            await websocket.accept(subprotocol=subprotocol)
            if wait_first:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(min(FIRST_MESSAGE_WAIT, timeout / 2)):
                        message = await websocket.receive()
                        if message["type"] == "websocket.disconnect":
                            return
            ending = Closing.for_error(error)
            await websocket.send_bytes(ServerProtocol().fail(error))
            await websocket.close(ending.code, ending.reason)

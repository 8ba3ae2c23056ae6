"""Opening and closing one facecast WebSocket: the connect options, the wait for ``ready``.

Shared by stream sessions and channel publishers and watchers (PROTOCOL.md §2, §5.2); it
opens a single connection and never retries (`facecast.client.reconnect` does).
"""

from __future__ import annotations

import asyncio
import contextlib

from websockets.asyncio.client import ClientConnection
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import ConnectionClosed

from facecast.protocol import (
    SUBPROTOCOL,
    ClientProtocol,
    Error,
    ErrorCode,
    Limits,
    ProtocolError,
    Ready,
)

__all__ = ["await_ready", "close_websocket", "open_websocket"]


async def open_websocket(
    url: str, headers: dict[str, str], limits: Limits, open_timeout: float
) -> ClientConnection:
    """The WebSocket handshake at ``url`` with facecast's subprotocol; raises on failure."""
    return await ws_connect(
        url,
        additional_headers=headers,
        subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
        max_size=limits.max_server_message_bytes,
        open_timeout=open_timeout,
        # Frames are float arrays: deflate costs CPU and latency and gains little.
        compression=None,
    )


async def await_ready(ws: ClientConnection, protocol: ClientProtocol) -> Ready:
    """Read until the server's ``ready`` (returned) or ``error`` (raised as ProtocolError)."""
    while True:
        data = await ws.recv()
        if isinstance(data, str):
            raise ProtocolError(ErrorCode.TEXT_NOT_SUPPORTED, "server sent a text message")
        message = protocol.receive(data)
        if isinstance(message, Ready):
            return message
        if isinstance(message, Error):
            raise message.to_exception()


async def close_websocket(ws: ClientConnection) -> None:
    """Close ``ws``, discarding what the server still sends until its close frame comes.

    Results in flight when a client stops reading (a pipelined session's window, a
    channel's 60 fps) fill websockets' incoming queue, which then stops reading the socket
    and with it the server's close frame: the closing handshake waited out websockets'
    ``close_timeout``, 10 s, and ended abnormally (python-websockets/websockets#1555).
    Nothing else may be reading ``ws`` meanwhile.
    """
    closing = asyncio.ensure_future(ws.close())
    try:
        with contextlib.suppress(ConnectionClosed):
            async for _ in ws:
                pass
    finally:
        await closing

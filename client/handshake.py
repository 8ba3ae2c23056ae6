"""Opening one facecast WebSocket: the client's connect options and the wait for ``ready``.

Shared by stream sessions and channel publishers and watchers (PROTOCOL.md §2, §5.2); it
opens a single connection and never retries (`facecast.client.reconnect` does).
"""

from __future__ import annotations

from websockets.asyncio.client import ClientConnection
from websockets.asyncio.client import connect as ws_connect

from facecast.protocol import (
    SUBPROTOCOL,
    ClientProtocol,
    Error,
    ErrorCode,
    Limits,
    ProtocolError,
    Ready,
)

__all__ = ["await_ready", "open_websocket"]


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

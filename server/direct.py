"""Writing a server's WebSocket frames straight to uvicorn's transport, where that is safe.

Builds one RFC 6455 binary frame per message and hands it to the socket without the ASGI
send path; it decides nothing about what is sent, and refuses whenever it cannot be sure.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from starlette.websockets import WebSocket, WebSocketState

__all__ = ["binary_frame", "direct_writer", "queued_messages"]

_LENGTH16 = struct.Struct(">BBH")
_LENGTH64 = struct.Struct(">BBQ")
_last_frame: tuple[bytes, bytes] = (b"", b"\x82\x00")


def binary_frame(data: bytes) -> bytes:
    """``data`` as one unmasked, unfragmented RFC 6455 binary frame (a server's frame).

    The fan-out hands the same result bytes to every member of a key in a row, so the
    newest frame is kept: it is built once per result, not once per viewer.
    """
    global _last_frame
    cached = _last_frame  # one read: servers in other threads (tests) may replace it
    if cached[0] is data:
        return cached[1]
    n = len(data)
    if n < 126:
        header = bytes((0x82, n))
    elif n < 65536:
        header = _LENGTH16.pack(0x82, 126, n)
    else:
        header = _LENGTH64.pack(0x82, 127, n)
    frame = header + data
    _last_frame = (data, frame)
    return frame


def direct_writer(websocket: WebSocket) -> Callable[[bytes], bool] | None:
    """A function writing a whole frame to ``websocket``'s socket, or None if unsafe.

    Only for uvicorn's ``websockets-sansio`` protocol reached through Starlette's own
    exception wrapper (nothing else between the route and uvicorn that might look at
    sends), with no extension negotiated (the frame is sent as built). Each call checks
    that the connection is open, accepted by the app, not closing and not paused by
    back-pressure; it returns False otherwise, and the caller uses the ASGI send (which
    waits, raises or closes as uvicorn decides). The protocol object only sees whole
    frames written between its own, so its state machine is unaffected: a server's data
    frame changes no protocol state (RFC 6455 §5; websockets ``send_binary`` only
    appends the serialised frame).
    """
    protocol = _sansio_protocol(getattr(websocket, "_send", None))
    if protocol is None:
        return None
    conn = protocol.conn
    if conn.extensions:
        return None
    from websockets.protocol import State

    opened = State.OPEN
    connected = WebSocketState.CONNECTED
    writable = protocol.writable
    transport = protocol.transport

    def write(frame: bytes) -> bool:
        if (
            websocket.application_state is not connected
            or protocol.close_sent
            or protocol.disconnected
            or not writable.is_set()
            or conn.state is not opened
            or conn.writes
            or transport.is_closing()
        ):
            return False
        transport.write(frame)
        return True

    return write


def queued_messages(websocket: WebSocket) -> Callable[[], int] | None:
    """A function counting the messages already received for ``websocket``'s app, or None.

    Where `direct_writer` is allowed (uvicorn's ``websockets-sansio`` protocol reached
    through Starlette only), the app's ``receive`` is that protocol's: it returns what
    its queue holds, so a count above zero means the next receive will not wait. A
    reader uses it to tell a burst of messages that arrived together from a lone one.
    """
    protocol = _sansio_protocol(getattr(websocket, "_send", None))
    return None if protocol is None else protocol.queue.qsize


def _sansio_protocol(send: Any, depth: int = 4) -> Any:
    """The uvicorn ``WebSocketsSansIOProtocol`` whose ``send`` ``send`` is, or None."""
    try:
        from uvicorn.protocols.websockets.websockets_sansio_impl import (
            WebSocketsSansIOProtocol,
        )
    except ImportError:  # pragma: no cover - uvicorn without websockets
        return None
    for _ in range(depth):
        owner = getattr(send, "__self__", None)
        if isinstance(owner, WebSocketsSansIOProtocol):
            return owner if send.__func__ is WebSocketsSansIOProtocol.send else None
        # Starlette's exception wrapper only notes http.response.start: see through it.
        if getattr(send, "__qualname__", "") != _STARLETTE_SENDER:
            return None
        names = send.__code__.co_freevars
        if "send" not in names:
            return None
        send = send.__closure__[names.index("send")].cell_contents
    return None


_STARLETTE_SENDER = "wrap_app_handling_exceptions.<locals>.wrapped_app.<locals>.sender"

"""The session layer's writers: whole RFC 6455 frames, written through `transport.Transport`.

Builds one unmasked binary frame per message and hands it to the connection's transport;
it decides nothing about what is sent. The seam to uvicorn is ``transport.py``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from starlette.websockets import WebSocket

from .transport import transport_for

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
    frame = frame_header(len(data)) + data
    _last_frame = (data, frame)
    return frame


def frame_header(n: int) -> bytes:
    """The header of an unmasked, unfragmented binary frame of ``n`` payload bytes."""
    if n < 126:
        return bytes((0x82, n))
    if n < 65536:
        return _LENGTH16.pack(0x82, 126, n)
    return _LENGTH64.pack(0x82, 127, n)


def direct_writer(websocket: WebSocket) -> Callable[[bytes], bool] | None:
    """``Transport.write`` of ``websocket``'s connection, or None where it never writes.

    None: every frame goes through the ASGI send (see ``transport.transport_for`` for
    where the direct path is allowed). The writer returns False when the frame must go
    through the ASGI send after all (closing, back-pressure).
    """
    transport = transport_for(websocket)
    return transport.write if transport.direct else None


def queued_messages(websocket: WebSocket) -> Callable[[], int] | None:
    """A function counting the messages already received for ``websocket``'s app, or None.

    Where `direct_writer` is allowed, a count above zero means the next receive will not
    wait: a reader uses it to tell a burst of messages that arrived together from a lone
    one. None where the transport cannot tell.
    """
    transport = transport_for(websocket)
    return transport.messages_waiting if transport.direct else None

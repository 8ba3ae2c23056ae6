"""The seam between facecast's WebSocket writers and uvicorn's connection: one small interface.

``TransportSeam`` (pure ASGI middleware, outermost in the app) records the ``send``
uvicorn hands the app in the connection's scope; ``transport_for`` turns it into a
`Transport`, whose ``write`` takes whole frames built by ``binary_frame``. It decides
nothing about what is sent, and never reads framework state that is not its own: no
closure cells, no qualnames.

What it relies on, pinned in pyproject.toml and tested under both WebSocket
implementations (tests/server/test_server_transport.py):

- ASGI: the ``scope`` a middleware sees is the dict the route's ``WebSocket.scope`` is
  (Starlette routes update it in place), so a key set here reaches the route.
- uvicorn's ``WebSocketsSansIOProtocol``: ``send`` is a bound method of the connection's
  protocol (``send.__self__``, checked with ``send.__func__``), whose ``transport``,
  ``writable`` (cleared while the transport is paused), ``close_sent``, ``disconnected``,
  ``queue`` (received messages the app has not read) and ``conn`` (websockets'
  ``ServerProtocol``: ``state``, ``writes``, ``extensions``) it reads.
- Starlette's ``WebSocket.application_state``: whether the app accepted and has not closed.

Anything else (uvicorn's legacy ``websockets`` implementation, wsproto, a middleware
outside the seam that wraps ``send``, a negotiated extension) gets `AsgiTransport`: every
frame goes through the ASGI send, which waits, raises or closes as uvicorn decides.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any, Final

from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket, WebSocketState
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

from .ws_guard import BoundedSansIO

__all__ = [
    "AsgiTransport",
    "SansIOTransport",
    "Transport",
    "TransportSeam",
    "binary_frame",
    "transport_for",
]

#: Scope keys set by `TransportSeam` (uvicorn's own send) and by `transport_for`.
SEND_KEY: Final = "facecast.uvicorn_send"
_TRANSPORT_KEY: Final = "facecast.transport"

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


class TransportSeam:
    """Pure-ASGI middleware recording the server's own ``send`` in a WebSocket scope.

    Must be the outermost middleware of the app (``create_app`` adds it last): a send that
    something else has wrapped is not uvicorn's, and `transport_for` then refuses the
    direct path. Everything is passed on unchanged; HTTP scopes are not touched.
    Middlewares inside it (between it and the routes) must not need to see a WebSocket's
    data frames, which the direct path writes past them: facecast's own (access log,
    Host/Origin checks, CORS) look at HTTP requests and the handshake only.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            scope[SEND_KEY] = send
        await self.app(scope, receive, send)


class Transport:
    """Writing one connection's frames: the interface every implementation offers.

    ``write`` takes a whole RFC 6455 frame (`binary_frame`) and returns whether it
    was handed to the socket now; on False the caller sends the message through the ASGI
    send instead (``websocket.send_bytes``), which waits for back-pressure and raises on a
    closed connection. This base class is that fallback: it never writes directly.
    """

    #: Whether ``write`` can ever return True (frames may bypass the ASGI send).
    direct: bool = False

    def write(self, frame: bytes) -> bool:
        """Hand ``frame`` (one whole frame) to the socket now, or return False."""
        return False

    def buffered_bytes(self) -> int:
        """Bytes written but not yet taken by the socket (0 where not known)."""
        return 0

    def messages_waiting(self) -> int:
        """Received messages the app has not read yet (0 where not known)."""
        return 0

    def take_messages(
        self, hook: Callable[[bytes], bool] | None, done: Callable[[], None] | None = None
    ) -> bool:
        """Offer each received binary message to ``hook`` first (None: stop); False if not.

        ``hook`` runs on the protocol's ``data_received`` stack, only while no received
        message waits for the app's receive; returning True takes the message (the app's
        receive never sees it), False leaves it to the receive, in order. ``done`` is
        called once the messages of each read from the socket have all been offered
        (write what they produced together). Neither may raise or block.
        """
        return False

    @property
    def closed(self) -> bool:
        """Whether no more frames can be written (closed, closing or never accepted)."""
        return True


class AsgiTransport(Transport):
    """The fallback: frames go through the ASGI send only (see `Transport`)."""

    def __init__(self, websocket: WebSocket) -> None:
        self._websocket = websocket

    @property
    def closed(self) -> bool:
        return self._websocket.application_state is not WebSocketState.CONNECTED


class SansIOTransport(Transport):
    """Writes straight to uvicorn's ``websockets-sansio`` transport, when that is safe.

    Only with no extension negotiated (the frame is sent as built). Each ``write`` checks
    that the connection is open, accepted by the app, not closing, has nothing of the
    protocol's own waiting to be written and is not paused by back-pressure. The protocol
    object only sees whole frames written between its own, so its state machine is
    unaffected: a server's data frame changes no protocol state (RFC 6455 §5; websockets'
    ``send_binary`` only appends the serialised frame).
    """

    direct = True

    def __init__(self, websocket: WebSocket, protocol: Any) -> None:
        self._websocket = websocket
        self._protocol = protocol
        self._transport = protocol.transport
        #: Received messages waiting for the app (a bound method: no wrapper on the hot path).
        self.messages_waiting = protocol.queue.qsize  # type: ignore[method-assign]
        self.buffered_bytes = protocol.transport.get_write_buffer_size  # type: ignore[method-assign]
        # A closure per connection: the fan-out calls it once per viewer and result.
        self.write = _direct_write(websocket, protocol)  # type: ignore[method-assign,assignment]

    def take_messages(
        self, hook: Callable[[bytes], bool] | None, done: Callable[[], None] | None = None
    ) -> bool:
        protocol = self._protocol
        if not isinstance(protocol, BoundedSansIO):
            return False  # uvicorn's own class (not facecast's runner): no hook
        protocol.message_hook, protocol.read_hook = hook, done if hook is not None else None
        return True

    @property
    def closed(self) -> bool:
        protocol = self._protocol
        return bool(
            self._websocket.application_state is not WebSocketState.CONNECTED
            or protocol.close_sent
            or protocol.disconnected
            or self._transport.is_closing()
        )


def _direct_write(websocket: WebSocket, protocol: Any) -> Callable[[bytes], bool]:
    """`SansIOTransport.write` for one connection, as a closure.

    The fan-out calls it once per viewer and result: what it reads is bound here (cell
    reads), not looked up on ``self`` on every call.
    """
    conn, writable, transport = protocol.conn, protocol.writable.is_set, protocol.transport
    opened, connected = State.OPEN, WebSocketState.CONNECTED
    closing, send = transport.is_closing, transport.write

    def write(frame: bytes) -> bool:
        if (
            websocket.application_state is not connected
            or protocol.close_sent
            or protocol.disconnected
            or not writable()
            or conn.state is not opened
            or conn.writes
            or closing()
        ):
            return False
        send(frame)
        return True

    return write


def transport_for(websocket: WebSocket) -> Transport:
    """The `Transport` of ``websocket``'s connection (built once, kept in its scope).

    `SansIOTransport` where `TransportSeam` recorded a send that is uvicorn's
    ``WebSocketsSansIOProtocol.send`` itself, bound to a protocol with no extension;
    `AsgiTransport` otherwise.
    """
    scope = websocket.scope
    found = scope.get(_TRANSPORT_KEY)
    if isinstance(found, Transport):
        return found
    protocol = _sansio_protocol(scope.get(SEND_KEY))
    transport: Transport
    if protocol is None or protocol.conn.extensions:
        transport = AsgiTransport(websocket)
    else:
        transport = SansIOTransport(websocket, protocol)
    scope[_TRANSPORT_KEY] = transport
    return transport


def _sansio_protocol(send: Any) -> Any:
    """The uvicorn ``WebSocketsSansIOProtocol`` whose own ``send`` ``send`` is, or None."""
    owner = getattr(send, "__self__", None)
    if not isinstance(owner, WebSocketsSansIOProtocol):
        return None
    if getattr(send, "__func__", None) is not WebSocketsSansIOProtocol.send:
        return None  # a subclass overriding send might look at what it sends
    return owner

"""uvicorn's WebSocket protocols with back-pressure on pongs and a short closing handshake.

uvicorn's ``websockets-sansio`` answers every ping by writing a pong to the transport at
once, whether or not the client reads: a client flooding pings and reading nothing
grew the server's write buffer without bound. Here pongs queued while the transport is
paused (its buffer above the high-water mark) are counted, and past
``max_pong_backlog`` bytes the connection is cut. Both implementations wait at most
``ws_close_timeout`` for the peer's part of the closing handshake (uvicorn: 10 s), and
a connection whose app has ended is dropped ``2 x ws_close_timeout`` later whatever the
peer does (uvicorn's ``transport.close()`` waits for the peer to read everything
buffered). On the sans-I/O one, the app may take binary messages as they are parsed
(``message_hook``, for the per-frame path: no queue, task switch or read pause per
message); whatever it declines goes to the app's receive as before. And on the sans-I/O
one, a handshake the app answered with an HTTP response (a 403 denial, ``origins``) counts
as answered: uvicorn leaves it marked incomplete and then logs "ASGI callable returned
without completing handshake." at error level for every refused connection, a log
flood any web page could cause. Nothing else of uvicorn's protocols changes.

Subclasses uvicorn's classes (pinned in pyproject.toml); relies on both having
``run_asgi``, ``loop``, ``transport`` and ``close_timeout`` (read when closing), and on the
sans-I/O one's ``handle_ping``, ``conn``, ``writable``, ``send_receive_event_to_app``
with ``frames``, ``curr_msg_data_type``, ``close_sent`` and ``queue`` (the message hook),
and ``app``, ``initial_response`` and ``handshake_complete`` (the denial).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

__all__ = ["BoundedSansIO", "guarded_ws_protocol"]

log = logging.getLogger("facecast.server.ws")


class _AbortLingering:
    """After the app has ended, a connection is dropped ``2 x ws_close_timeout`` s later at most.

    uvicorn ends both protocols with ``transport.close()``, which waits for the peer to
    read everything buffered: a peer that reads nothing would hold the connection (and
    its buffer) for ever.
    """

    ws_close_timeout = 10.0
    transport: Any
    loop: Any

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.close_timeout = self.ws_close_timeout

    async def run_asgi(self) -> None:
        try:
            await super().run_asgi()  # type: ignore[misc]
        finally:
            # Aborting a transport that has closed meanwhile does nothing.
            self.loop.call_later(2 * self.ws_close_timeout, self.transport.abort)


class BoundedSansIO(_AbortLingering, WebSocketsSansIOProtocol):
    """uvicorn's ``websockets-sansio`` protocol with bounded pongs and the message hook."""

    max_pong_backlog = 64 * 1024
    _pong_backlog = 0
    #: Set by the app through the transport seam (``transport.SansIOTransport.take_messages``):
    #: offered each whole binary message first, on ``data_received``'s stack, while
    #: nothing received waits for the app; True means it took the message. ``read_hook``
    #: is called after each read's messages have all been parsed.
    message_hook: Callable[[bytes], bool] | None = None
    read_hook: Callable[[], None] | None = None

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        done = self.read_hook
        if done is not None:
            done()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        app = self.app

        async def app_whose_denial_answers(scope: Any, receive: Any, send: Any) -> None:
            await app(scope, receive, send)
            if self.initial_response is not None:
                # The app denied the handshake with an HTTP response (written, and the
                # transport closed): answered, with a response instead of a 101.
                self.handshake_complete = True

        # Not an override of ``send``: ``transport`` writes frames directly only under
        # uvicorn's own ``send`` (``transport._sansio_protocol``).
        self.app = app_whose_denial_answers

    def send_receive_event_to_app(self) -> None:
        hook = self.message_hook
        if (
            hook is not None
            and self.curr_msg_data_type == "bytes"
            and not self.close_sent
            and self.queue.empty()
        ):
            frames = self.frames
            data = frames[0] if len(frames) == 1 else b"".join(frames)
            if hook(data):
                # Taken: not queued for the app's receive, so reading is not paused
                # for it either (uvicorn pauses after each queued message).
                self.frames = []
                return
        super().send_receive_event_to_app()

    def handle_ping(self) -> None:
        if self.writable.is_set():  # the client reads: pongs go out as uvicorn writes them
            self._pong_backlog = 0
            super().handle_ping()
            return
        output = b"".join(self.conn.data_to_send())
        self._pong_backlog += len(output)
        if self._pong_backlog > self.max_pong_backlog:
            log.warning(
                "ping flood: connection cut",
                extra={"event": "ws.ping_flood", "client": self.client,
                       "backlog": self._pong_backlog},
            )  # fmt: skip
            # The peer reads nothing, so a close frame would only wait in the buffer too.
            self.transport.abort()
            return
        self.transport.write(output)

    def resume_writing(self) -> None:
        self._pong_backlog = 0
        super().resume_writing()


def guarded_ws_protocol(ws: str, *, max_pong_backlog: int, close_timeout: float) -> type:
    """uvicorn's WebSocket protocol class ``ws`` ("websockets-sansio" or "websockets"), bounded."""
    if ws == "websockets-sansio":
        return type("GuardedWebSocketsSansIOProtocol", (BoundedSansIO,),
                    {"max_pong_backlog": max_pong_backlog,
                     "ws_close_timeout": close_timeout})  # fmt: skip
    if ws == "websockets":
        # Imported only when chosen: importing uvicorn's legacy module warns that it is
        # deprecated, which only those who choose it should read.
        from uvicorn.protocols.websockets.websockets_impl import WebSocketProtocol

        return type("GuardedWebSocketProtocol", (_AbortLingering, WebSocketProtocol),
                    {"ws_close_timeout": close_timeout})  # fmt: skip
    raise ValueError(f"no WebSocket implementation {ws!r}")

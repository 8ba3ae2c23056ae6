"""A channel connection's sending side: a bounded outbox and a writer, newest result wins.

Sends on the fan-out's own stack when the socket takes the bytes at once (a result's
WebSocket frame is built once and written as is where uvicorn's protocol allows), else
through the writer task; a slow client only ever slows itself. No protocol decisions here.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Coroutine, Generator, Iterable
from typing import Any, cast

from starlette.websockets import WebSocket

from facecast.protocol import ClientMessage, ProtocolError

from ..connection.core import ConnectionCore
from ..connection.driver import Driver
from ..serving.seam import binary_frame, transport_for
from .context import ChannelMember
from .fanout import Key

__all__ = ["MAX_OUTBOX", "Member", "offer_results"]

log = logging.getLogger("facecast.server.channels")

#: Messages waiting in one member's outbox. Consecutive results collapse into the newest,
#: so this bounds control messages (events, pongs, errors); beyond it the oldest go.
MAX_OUTBOX = 32


class Member(Driver):
    """One accepted WebSocket in a channel: an outbox of encoded messages and a writer.

    ``offer_result`` replaces a result still waiting (the viewer skips to the newest
    frame; ``skipped`` counts it); ``offer`` queues a control message. Memory per member
    is at most ``MAX_OUTBOX`` references to bytes shared with other members. What it
    reads goes to its ``core`` (the rules); the subclasses say what to do with frames
    and hellos.
    """

    watcher = True
    crash_event = "channel.crash"
    log = log

    def __init__(
        self, websocket: WebSocket, key: Key, core: ConnectionCore, member_id: str
    ) -> None:
        super().__init__(websocket, core, f"member-{member_id}")
        self.id = member_id
        self.key = key
        self.protocol = core.protocol
        self.sent = 0
        self.skipped = 0
        self._items: deque[list[Any]] = deque()
        self._wake = asyncio.Event()
        # Direct sends (``_send_now``) only once the socket is accepted and the writer runs.
        self._open = False
        self._writing = False
        self._inflight: asyncio.Task[None] | None = None
        #: Writes a whole frame straight to the socket, or False; found once accepted.
        self._direct: Callable[[bytes], bool] | None = None

    @property
    def direct(self) -> bool:
        """Whether results are written straight to the socket (``Transport.direct``)."""
        return self._direct is not None

    @property
    def queued(self) -> int:
        """Messages waiting to be sent (bounded by ``MAX_OUTBOX``)."""
        return len(self._items)

    def offer_result(self, data: bytes) -> None:
        """Send or queue one result (``offer_results`` for this member alone)."""
        offer_results((self,), data)

    def _queue_result(self, data: bytes) -> None:
        """``offer_result`` once the direct write is ruled out: replace, send or queue."""
        if self._items and self._items[-1][0] == "r":
            self._items[-1][1] = data
            self.skipped += 1
            return
        self._push("r", data)

    def offer(self, data: bytes) -> None:
        self._push("c", data)

    def _push(self, kind: str, data: bytes) -> None:
        if not self._items and self._idle and self._send_now(data):
            return
        if len(self._items) >= MAX_OUTBOX:
            self._items.popleft()
            self.skipped += 1
        self._items.append([kind, data])
        self._wake.set()

    @property
    def _idle(self) -> bool:
        return self._open and self._inflight is None and not self._writing

    def _send_now(self, data: bytes) -> bool:
        """Send on the caller's stack when the socket takes it at once; False if not tried.

        The fan-out reaches thousands of members per frame: waking a writer task for
        each costs more than the send itself. Most sends complete without suspending
        (uvicorn's buffer has room), so run the send coroutine right here; if it does
        suspend (slow client), a task finishes it and the outbox holds newer results.
        """
        if self._direct is not None and self._direct(binary_frame(data)):
            self.sent += 1
            return True
        coro = self.ws.send_bytes(data)
        try:
            yielded = coro.send(None)
        except StopIteration:
            self.sent += 1
            return True
        except Exception:
            # The client is gone; the reader sees the disconnect and ends the member.
            self._open = False
            return True
        self._inflight = asyncio.get_running_loop().create_task(_finish(coro, yielded))
        self._inflight.add_done_callback(self._finished)
        return True

    def _finished(self, task: asyncio.Task[None]) -> None:
        self._inflight = None
        if task.cancelled() or task.exception() is not None:
            self._open = False
            return
        self.sent += 1
        self._wake.set()  # the writer flushes what queued up meanwhile

    def _deliver(self) -> None:
        for data in self.core.data_to_send():
            self.offer(data)

    def report(self, error: ProtocolError) -> None:
        """Queue an error; a fatal one ends the connection after it is sent."""
        self.core.report(error)  # raises Closing when fatal
        self._deliver()

    async def _read_loop(self) -> None:
        receive, clock, core = self.ws.receive, time.monotonic, self.core
        while True:
            message = await receive()
            if message["type"] == "websocket.disconnect":
                return
            now = clock()
            data = message.get("bytes")
            try:
                if data is None:
                    core.receive_text(message.get("text") or "", now)
                await self._on_message(core.receive(data, now), now)
            except ProtocolError as exc:
                self.report(exc)

    async def _on_message(self, message: ClientMessage, now: float) -> None:
        """A decoded message: by default, the core's answer (a watcher's pong)."""
        self.core.handle(message, now)
        self._deliver()

    async def _write_loop(self) -> None:
        transport = transport_for(self.ws)
        self._direct = transport.write if transport.direct else None
        self._open = True
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._inflight is not None:
                continue  # its completion wakes us again
            self._writing = True
            try:
                while self._items:
                    _, data = self._items.popleft()
                    # Blocks while this client does not read (uvicorn's write buffer is
                    # full); meanwhile its outbox keeps only the newest result.
                    await self.ws.send_bytes(data)
                    self.sent += 1
            finally:
                self._writing = False

    def _stopping(self) -> None:
        self._open = False

    def _extra_tasks(self) -> list[asyncio.Task[None]]:
        return [] if self._inflight is None else [self._inflight]


def offer_results(members: Iterable[ChannelMember], data: bytes) -> int:
    """Offer one result to every member of a key: the fan-out's loop, once per key and frame.

    The RFC 6455 frame is built once for all of them, and an idle member whose socket
    takes it at once is written in this loop, without a call per viewer; any other has
    it replace, send or queue (``_queue_result``). Returns how many were offered.
    """
    frame = binary_frame(data)
    offered = 0
    for one in members:
        member = cast(Member, one)
        offered += 1
        direct = member._direct
        if (
            direct is not None
            and not member._items
            and member._open
            and member._inflight is None
            and not member._writing
            and direct(frame)
        ):
            member.sent += 1
        else:
            member._queue_result(data)
    return offered


class _Resume:
    """Awaitable handing a future a coroutine yielded back to the running task."""

    __slots__ = ("future",)

    def __init__(self, future: Any) -> None:
        self.future = future

    def __await__(self) -> Generator[Any, None, Any]:
        return (yield self.future)


async def _finish(coro: Coroutine[Any, Any, None], yielded: Any) -> None:
    """Drive a coroutine started by hand (``coro.send(None)`` gave ``yielded``) to its end."""
    try:
        while True:
            await _Resume(yielded)
            try:
                yielded = coro.send(None)
            except StopIteration:
                return
    except BaseException:
        coro.close()
        raise

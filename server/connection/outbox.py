"""A connection's sending side: what waits for its socket, and the one rule for writing it.

Stream sessions, channel publishers and watchers all write through an `Outbox`: a
message goes straight to the socket (`Transport.write` of its whole frame) when nothing
waits before it and the socket takes it at once; else it waits, bounded, for the writer
(`Outbox.run`), which sends through the ASGI send and so waits while the client does
not read. No protocol decisions here: what to send is the core's.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable, Iterable

from starlette.websockets import WebSocket

from ..compute.stages import CPU_CLOCK, StageTimes
from ..serving.seam import Transport, binary_frame

__all__ = ["CORK_BYTES", "Outbox", "offer_results"]

#: Results of one burst written to the socket together (one syscall) at the burst's end,
#: or as soon as they reach this many bytes (`Outbox.cork`).
CORK_BYTES = 64 * 1024


class Outbox:
    """One connection's messages on their way to its socket, and its writer.

    Control messages (``offer``: pongs, errors, events) are sent before results; past
    ``limit`` the oldest is dropped (counted in ``skipped``). Results (``offer_result``)
    are sent in order, or with ``collapse`` the newest replaces one still waiting (a
    viewer skips to the newest frame; counted in ``skipped``). Nothing is written
    directly before ``start`` (the socket may not be accepted yet).

    Parameters
    ----------
    websocket : the connection's (its ASGI ``send_bytes`` is the writer's fallback)
    limit : control messages waiting at most (with ``collapse``, the waiting result counts)
    collapse : whether a result replaces one still waiting
    stages : where result writes are timed ("write"), or None
    on_results : told how many results were handed to the socket, as they are
    """

    def __init__(
        self,
        websocket: WebSocket,
        *,
        limit: int,
        collapse: bool,
        stages: StageTimes | None = None,
        on_results: Callable[[int], None] | None = None,
    ) -> None:
        self._ws = websocket
        self._limit = limit
        self._collapse = collapse
        self._stages = stages
        self._on_results = on_results
        self._control: deque[bytes] = deque()
        self._results: deque[bytes] = deque()
        #: Bytes of the results waiting (bounded by the caller, who reads it).
        self.result_bytes = 0
        #: Messages handed to the socket, and messages dropped or replaced unsent.
        self.sent = 0
        self.skipped = 0
        self._corked: list[bytes] = []
        self._corked_bytes = 0
        self._wake = asyncio.Event()
        #: Writes a whole frame straight to the socket, or False; None: never (``start``).
        self._direct: Callable[[bytes], bool] | None = None
        self._open = False
        #: The writer waits for something to send (nothing in its hands).
        self.idle = False
        self._sending = False

    # -- state ---------------------------------------------------------------------------
    def start(self, transport: Transport) -> None:
        """The socket is accepted: direct writes may begin (where ``transport`` allows)."""
        self._direct = transport.write if transport.direct else None
        self._open = True

    def stop(self) -> None:
        """The connection is ending: write nothing more directly."""
        self._open = False

    @property
    def direct(self) -> bool:
        """Whether results are written straight to the socket (``Transport.direct``)."""
        return self._direct is not None

    @property
    def queued(self) -> int:
        """Messages waiting for the writer."""
        return len(self._control) + len(self._results)

    @property
    def queued_results(self) -> tuple[int, int]:
        """Results waiting for the writer: (count, bytes)."""
        return len(self._results), self.result_bytes

    def wake(self) -> None:
        """Wake the writer (the caller has given its ``produce`` something to do)."""
        self._wake.set()

    # -- offering ------------------------------------------------------------------------
    def write_now(self, frame: bytes) -> bool:
        """Write ``frame`` (a whole frame, `binary_frame`) at once if the rule allows.

        Only while nothing waits before it and the writer is not sending: what is
        written never overtakes what is queued. False: not written (queue it instead).
        `offer_results` applies the same rule inline (keep the two alike).
        """
        direct = self._direct
        if (
            direct is not None
            and self._open
            and not self._sending
            and not self._control
            and not self._results
            and direct(frame)
        ):
            self.sent += 1
            return True
        return False

    def offer(self, data: bytes) -> None:
        """Send a control message now, or queue it (before any result waiting)."""
        self.flush()
        if self.write_now(binary_frame(data)):
            return
        control = self._control
        if len(control) + (len(self._results) if self._collapse else 0) >= self._limit:
            if control:
                control.popleft()
            else:
                self.result_bytes -= len(self._results.popleft())
            self.skipped += 1
        control.append(data)
        self._wake.set()

    def offer_result(self, data: bytes) -> None:
        """Send one result now, or queue it (``collapse``: replacing one still waiting)."""
        self.flush()
        if self.write_now(binary_frame(data)):
            self._count(1)
            return
        self._queue_result(data)

    def _queue_result(self, data: bytes) -> None:
        results = self._results
        if self._collapse and results:
            self.result_bytes += len(data) - len(results[-1])
            results[-1] = data
            self.skipped += 1
            return
        results.append(data)
        self.result_bytes += len(data)
        self._wake.set()

    def cork(self, data: bytes) -> bool:
        """Hold a result of the burst being read, to write it with the others (``flush``).

        Only while results go straight to the socket and nothing waits for the writer
        (it is idle, nothing queued). False: not held; offer it instead (`offer_result`).
        """
        if self._direct is None or not self.idle or self._control or self._results:
            return False
        self._corked.append(data)
        self._corked_bytes += len(data)
        if self._corked_bytes >= CORK_BYTES:
            self.flush()
        return True

    def flush(self) -> None:
        """Write the corked results in one go (one syscall), or queue them for the writer.

        Called before anything else is offered and before the reader waits, so results
        never overtake one another or a control message.
        """
        corked = self._corked
        if not corked:
            return
        self._corked, self._corked_bytes = [], 0
        data = binary_frame(corked[0]) if len(corked) == 1 else b"".join(map(binary_frame, corked))
        stages = self._stages
        writing = CPU_CLOCK() if stages is not None else 0.0
        if self.write_now(data):
            self.sent += len(corked) - 1
            if stages is not None:
                stages.add("write", CPU_CLOCK() - writing, len(corked))
            self._count(len(corked))
            return
        # The socket cannot take them at once (back-pressure): the writer sends them.
        for one in corked:
            self._queue_result(one)

    def _count(self, n: int) -> None:
        if self._on_results is not None:
            self._on_results(n)

    # -- writing -------------------------------------------------------------------------
    async def send(self, data: bytes) -> None:
        """Hand ``data`` to the socket: at once if it takes it, else through the ASGI send.

        The writer's own send (also for a ``produce`` that must send before its result):
        waits while the client does not read.
        """
        direct = self._direct
        self._sending = True
        try:
            if direct is None or not direct(binary_frame(data)):
                await self._ws.send_bytes(data)
        finally:
            self._sending = False
        self.sent += 1

    async def run(
        self,
        produce: Callable[[], Awaitable[bytes | None]] | None = None,
        has_work: Callable[[], bool] | None = None,
    ) -> None:
        """The writer: control messages, then results, then what ``produce`` makes.

        ``produce`` (with ``has_work`` saying when it has something to do) makes the next
        result on the writer's stack (a frame the reader left it); None: nothing to send.
        """
        control, results = self._control, self._results
        stages, clock = self._stages, CPU_CLOCK
        while True:
            if control:
                await self.send(control.popleft())
                continue
            if results:
                data = results.popleft()
                self.result_bytes -= len(data)
            elif produce is not None and has_work is not None and has_work():
                made = await produce()
                if made is None:
                    continue
                data = made
            else:
                self._wake.clear()
                self.idle = True
                try:
                    await self._wake.wait()
                finally:
                    self.idle = False
                continue
            # Blocks while the client does not read; meanwhile newer results collapse
            # (``collapse``) or frames wait in the reader's mailbox.
            writing = clock() if stages is not None else 0.0
            await self.send(data)
            if stages is not None:
                stages.add("write", clock() - writing)
            self._count(1)


def offer_results(outboxes: Iterable[Outbox], data: bytes) -> int:
    """Offer one result to many connections: the fan-out's loop, once per key and frame.

    The RFC 6455 frame is built once for all of them, and an idle outbox whose socket
    takes it at once is written in this loop; any other queues it (``collapse``: the
    newest replaces a waiting one). Returns how many were offered.
    """
    frame = binary_frame(data)
    offered = 0
    for outbox in outboxes:
        offered += 1
        # `Outbox.write_now`'s rule, inline: this loop runs once per viewer and frame, and
        # a method call per viewer costs more than the rule itself.
        direct = outbox._direct
        if (
            direct is not None
            and outbox._open
            and not outbox._sending
            and not outbox._control
            and not outbox._results
            and direct(frame)
        ):
            outbox.sent += 1
        else:
            outbox._queue_result(data)
    return offered

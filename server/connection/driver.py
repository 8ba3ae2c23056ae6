"""The asyncio half of a client connection: its reader, its writer, its timer, its close.

Runs one read loop and one writer (its `Outbox`) beside a `ConnectionCore` until either
side ends it, runs the work the core asks for off the loop (a neutral's fit), calls the
core's ``tick`` at its ``deadline`` (one timer, not one per message) and sends the close
in bounded time. It makes no protocol decision (the core does); what a frame or a
``hello`` leads to is the subclasses' (``stream.session.Session``, ``channels.members``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import Executor
from typing import Any

import numpy as np
from starlette.websockets import WebSocket, WebSocketDisconnect

from facecast.protocol import ClientMessage, Frame, Hello, ProtocolError
from facecast.rig.errors import RigError
from facecast.rig.filters import KalmanFilter
from facecast.rig.rebase import calibrate as calibrate_rig

from ..compute.stages import CPU_CLOCK, StageTimes
from ..serving.seam import transport_for
from .closing import CLOSE_GRACE, Closing
from .core import ConnectionCore
from .outbox import Outbox

__all__ = ["BURST_SECONDS", "Driver"]

#: Frames that arrived together are cloned in order for at most this long after the
#: first of them was read; later ones in the same burst replace one another (§8).
BURST_SECONDS = 0.005


class Driver:
    """Serve one accepted WebSocket with ``core``'s rules until either side ends it.

    Subclasses say what a frame (``_on_frame``) and a ``hello`` (``_open``) lead to;
    everything written goes through ``outbox``. The hooks ``_stopping``, ``_ended`` and
    ``_log_end`` run, in that order, as the connection ends.

    Parameters
    ----------
    websocket : accepted before ``run``
    core : the connection's rules
    name : names its tasks and log lines
    outbox : its sending side
    executor : where a neutral is fitted (the clone pool; None: asyncio's default)
    stages : where decode times go, or None
    """

    #: Logged (``event``) when a task fails with an unexpected exception.
    crash_event = "connection.crash"
    log = logging.getLogger("facecast.server")

    def __init__(
        self,
        websocket: WebSocket,
        core: ConnectionCore,
        name: str,
        outbox: Outbox,
        *,
        executor: Executor | None = None,
        stages: StageTimes | None = None,
    ) -> None:
        self.ws = websocket
        self.core = core
        self.outbox = outbox
        self.executor = executor
        self._stages = stages
        self._name = name
        #: Received messages waiting for the reader (where the transport tells), or None.
        self._queued: Callable[[], int] | None = None
        self._reader_waited = False
        #: The reader waits in its receive with nothing of its own in flight.
        self._parked = False
        self._loop = asyncio.get_running_loop()
        self._stop: asyncio.Future[Closing] = self._loop.create_future()
        self._done = asyncio.Event()
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = math.inf
        self._finishing = False

    # -- subclasses ----------------------------------------------------------------------
    def _on_frame(self, frame: Frame, now: float, in_burst: bool) -> Awaitable[None] | None:
        """A frame received at ``now`` (``in_burst``: with others that arrived together).

        By default the core's answer, as to any message; an awaitable is awaited before
        the next message is read.
        """
        return self._on_message(frame, now)

    async def _open(self, hello: Hello) -> None:
        """Load the rig ``hello`` asks for and open the core (then ``ready`` is sent).

        A watcher, opened by its query string, asks for nothing.
        """

    async def _write_loop(self) -> None:
        await self.outbox.run()

    def _stopping(self) -> None:
        """The connection is ending: stop sending on other tasks' stacks."""
        self._parked = False
        self.outbox.stop()

    async def _ended(self) -> None:
        """The tasks are gone; before the close is sent."""
        await self.leave()

    async def leave(self) -> None:
        """Unregister from what the connection joined (a channel); safe to call again."""

    def _log_end(self, ending: Closing | None) -> None:
        """Log the end (``ending`` None: the client left)."""

    # -- running -------------------------------------------------------------------------
    async def run(self) -> None:
        """Run until the client leaves, a fatal error, the idle timeout or ``close``."""
        transport = transport_for(self.ws)
        self.outbox.start(transport)
        if transport.direct:
            self._queued = transport.messages_waiting
        name = self._name
        reader = asyncio.create_task(self._read_loop(), name=f"{name}-reader")
        writer = asyncio.create_task(self._write_loop(), name=f"{name}-writer")
        self.arm()
        ending: Closing | None = None
        order: tuple[asyncio.Future[Any], ...] = (self._stop, reader, writer)
        try:
            done, _ = await asyncio.wait(order, return_when=asyncio.FIRST_COMPLETED)
            ending = self._ending(done, order)
        finally:
            self._finishing = True
            self._disarm()
            self._stopping()
            tasks = [reader, writer]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self._ended()
            if ending is not None:
                await self._send_close(ending)
            self._log_end(ending)
            self._done.set()

    def _ending(
        self, done: set[asyncio.Future[Any]], tasks: tuple[asyncio.Future[Any], ...]
    ) -> Closing | None:
        """Why the connection ends, from the first of ``tasks`` that is done."""
        for task in tasks:
            if task not in done or task.cancelled():
                continue
            exc = task.exception()
            if isinstance(exc, Closing):
                return exc
            if isinstance(exc, WebSocketDisconnect | OSError):
                return None  # the client went away mid-send: a normal end
            if exc is not None:
                self.log.error(
                    "connection failed",
                    exc_info=exc,
                    extra={"event": self.crash_event, "session": self._name},
                )
                return Closing.internal()
            if task is self._stop:
                result: Closing = task.result()
                return result
            return None
        return None

    @property
    def ending(self) -> bool:
        """Whether the connection is ending: asked to stop, or its client left."""
        return self._finishing or self._stop.done()

    async def close(self, code: int, reason: str) -> None:
        """Ask the connection to end with ``code`` (e.g. 1001 at shutdown) and wait for it."""
        self.stop(Closing(code, reason))
        await self._done.wait()

    def stop(self, ending: Closing) -> None:
        """End the connection with ``ending`` (from outside its tasks); the first one wins."""
        if not self._stop.done():
            self._stop.set_result(ending)

    def end(self, error: ProtocolError) -> None:
        """End the connection with a fatal ``error`` (from outside its tasks)."""
        self.stop(Closing.for_error(error))

    async def _send_close(self, ending: Closing) -> None:
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_GRACE):
                data = self.core.closing_bytes(ending)
                if data is not None and self.ws.application_state.name == "CONNECTED":
                    await self.ws.send_bytes(data)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_GRACE):
                await self.ws.close(ending.code, ending.reason[:120])

    # -- reading -------------------------------------------------------------------------
    async def _read_loop(self) -> None:
        receive, clock, queued = self.ws.receive, time.monotonic, self._queued
        core, stages, outbox = self.core, self._stages, self.outbox
        burst_start = 0.0
        waits = False
        while True:
            if queued is not None:
                waits = not queued()
                if waits:
                    outbox.flush()  # the burst is over: its results go out together
            else:
                self._reader_waited = False
                self._loop.call_soon(self._mark_reader_waited)
            self._parked = True
            try:
                message = await receive()
            finally:
                self._parked = False
            now = clock()
            if waits if queued is not None else self._reader_waited:
                # The receive had to wait: this message starts a new burst (messages
                # that were already queued when the reader got to them belong to one).
                burst_start = time.perf_counter()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            try:
                if data is None:
                    core.receive_text(message.get("text") or "", now)
                decoding = CPU_CLOCK() if stages is not None else 0.0
                decoded = core.receive(data, now)
                if type(decoded) is Frame:
                    if stages is not None:
                        stages.add("decode", CPU_CLOCK() - decoding)
                    in_burst = time.perf_counter() - burst_start < BURST_SECONDS
                    work = self._on_frame(decoded, now, in_burst)
                    if work is not None:
                        await work
                else:
                    outbox.flush()
                    await self._on_message(decoded, now)
            except ProtocolError as exc:
                self.report(exc)

    def _mark_reader_waited(self) -> None:
        # Scheduled before each receive: it runs before the receive returns only if the
        # receive suspended (the loop turned), i.e. no message was already queued.
        self._reader_waited = True

    async def _on_message(self, message: ClientMessage, now: float) -> None:
        """A decoded message: the core's answer, and the work it asks for."""
        work = self.core.handle(message, now)
        if isinstance(work, Hello):
            await self._open(work)
        elif work is not None:
            assert work.points is not None  # the core hands over only calibrates with points
            await self._calibrate(work.points, None, work.noise, work.blinks, work.blink_contrast)
        self._deliver()
        self.arm()  # a wait for the rig or a neutral suspended the idle deadline

    async def _calibrate(
        self,
        points: np.ndarray,
        seq: int | None,
        noise: float | None,
        blinks: Mapping[str, np.ndarray] | None = None,
        contrast: tuple[float, float] | None = None,
    ) -> bool:
        """Fit the neutral ``points`` (a ``calibrate`` message's, or frame ``seq``'s).

        ``noise``: the calibrate's landmark noise, for a noise-aware, bounded re-base
        (``rig.rebase``); None re-bases exactly. ``blinks``: the calibrate's closed eyes,
        read as closed (``rig.rebase.calibrate``), through the performer's own ``contrast``
        curve when given (calibrate ``blink_contrast``). The core queues its ``calibrated`` or its
        CALIBRATION_FAILED error; False if failed.
        """
        core = self.core
        base = core.base_rig
        assert base is not None
        try:
            # Re-fitting the projection (or, with noise, the weight model) is milliseconds:
            # in the clone pool.
            rig = await self._loop.run_in_executor(
                self.executor, calibrate_rig, base, points, noise, blinks, contrast
            )
        except RigError as exc:
            core.calibration_failed(exc, time.monotonic(), seq)
            return False
        kalman = core.calibrated_filter(rig)
        if kalman is not None:
            self._filter_points(kalman)
        core.calibrated(
            rig, time.monotonic(), seq, points=points, noise=noise, blinks=blinks,
            contrast=contrast,
        )  # fmt: skip
        return True

    def _filter_points(self, kalman: KalmanFilter) -> None:
        """Filter the points with ``kalman`` from the next frame on: an auto smoothing's
        filter once a calibrate gave the noise it lacked (``core.calibrated_filter``).
        Connections that take calibrates (a stream session, a channel's publisher) hold the
        filter and override this; the core asks for it only when ``hello`` has smoothing."""
        raise NotImplementedError(f"{type(self).__name__} takes no calibrate")

    # -- writing -------------------------------------------------------------------------
    def _deliver(self) -> None:
        """Hand what the core has to send (pongs, errors, acks) to the outbox."""
        for data in self.core.data_to_send():
            self.outbox.offer(data)

    def report(self, error: ProtocolError) -> None:
        """Queue an error for the client; a fatal one ends the connection after it is sent."""
        self.outbox.flush()
        self.core.report(error)  # raises Closing when fatal
        self._deliver()

    # -- the core's deadline -------------------------------------------------------------
    def arm(self) -> None:
        """(Re)arm the timer for the core's deadline, if that is sooner than the armed one."""
        deadline = self.core.deadline()
        if deadline is None or deadline >= self._timer_at:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer_at = deadline
        delay = max(0.0, deadline - time.monotonic())
        self._timer = self._loop.call_later(delay, self._on_deadline)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer, self._timer_at = None, math.inf

    def _on_deadline(self) -> None:
        self._timer, self._timer_at = None, math.inf
        if self._stop.done():
            return
        try:
            self.core.tick(time.monotonic())
        except Closing as ending:
            self.stop(ending)
            return
        self._deliver()
        self.arm()

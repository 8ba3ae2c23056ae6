"""One streaming session: a reader task, a one-slot frame mailbox and a writer task.

The reader clones cheap frames itself (on the loop) and queues their results; other
frames wait for the writer in a one-slot mailbox (newer replace older, counted), and
large blends run batched in the clone pool. The writer sends. Memory per session is
bounded whatever the client does. No auth and no admission here.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import secrets
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
from starlette.websockets import WebSocket, WebSocketDisconnect

from facecast.protocol import (
    Calibrate,
    Calibrated,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Limits,
    Ping,
    Pong,
    ProtocolError,
    Ready,
    ServerProtocol,
    close_code,
)
from facecast.rig.errors import InputError, RigError

from .blending import BlendBatcher
from .cloning import (
    Outputs,
    Smoother,
    blend_seconds,
    clone_frame,
    frame_error,
    frame_weights,
    smoothing_filter,
    smoothing_name,
)
from .direct import binary_frame, direct_writer, queued_messages
from .frame_rate import FrameRateLimit
from .metrics import Metrics
from .settings import Settings
from .stages import CPU_CLOCK
from .store import RigNotFoundError, RigStore, valid_rig_id

__all__ = ["INLINE_MAX_SECONDS", "Session", "SessionCounters", "ready_message"]

log = logging.getLogger("facecast.server.session")

#: Control messages (pongs, errors, acks) waiting for the writer; beyond this the oldest
#: are dropped: a client that floods pings but never reads must not grow memory.
_MAX_CONTROL = 32
#: How long a closing session waits to hand its last error / close frame to the socket.
_CLOSE_GRACE = 1.0
#: A vertices frame whose clone is estimated (``blend_seconds``) to take at most this
#: long is cloned on the event loop; costlier ones go to the clone pool, batched with
#: other sessions' frames (``blending``). Weights-only frames always run on the loop
#: (tens of µs). See SERVER.md, "Streaming choices".
INLINE_MAX_SECONDS = 0.0005
#: Frames that arrived together are cloned in order for at most this long after the
#: first of them was read; later ones in the same burst replace one another (§8).
_BURST_SECONDS = 0.005
#: Results of one burst written to the socket together (one syscall) at the burst's end,
#: or as soon as they reach this many bytes.
_CORK_BYTES = 64 * 1024
#: Encoded results the reader may leave for the writer (at least one is always
#: allowed); past this, frames wait in the mailbox and newer ones replace them (§8).
_MAX_OUTBOX_BYTES = 256 * 1024


@dataclass
class SessionCounters:
    """What a session has done; read by tests and logged when it ends."""

    frames_in: int = 0
    results_out: int = 0
    dropped_superseded: int = 0
    dropped_rate: int = 0
    errors: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_superseded + self.dropped_rate


class _Closing(Exception):
    """Raised inside the session's tasks to end it with a close code (and maybe an error)."""

    def __init__(self, code: int, reason: str, error: ProtocolError | None = None) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.error = error


class Session:
    """Serve one accepted WebSocket until either side ends it.

    Parameters
    ----------
    websocket : starlette WebSocket, already accepted
    settings, store, metrics : the app's
    executor : the app's clone thread pool, shared by all sessions of this worker
    blender : the app's blend batcher (over ``executor``); default: one of this session's
    """

    def __init__(
        self,
        websocket: WebSocket,
        *,
        settings: Settings,
        store: RigStore,
        metrics: Metrics,
        executor: Executor,
        blender: BlendBatcher | None = None,
        principal: str = "anonymous",
    ) -> None:
        self.id = secrets.token_hex(8)
        self.ws = websocket
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.executor = executor
        self.blender = blender if blender is not None else BlendBatcher(executor)
        self.principal = principal
        self.counters = SessionCounters()
        #: Where stage times go (``stages``), with ``settings.stage_timing`` only.
        self._stages = metrics.stages if settings.stage_timing else None
        self.protocol = ServerProtocol(
            Limits(max_message_bytes=settings.max_message_bytes),
        )
        self.hello: Hello | None = None
        self.rig_id: str | None = None
        self._base_rig: Any = None  # as loaded; calibration derives ``_rig`` from it
        self._rig: Any = None
        self._calibrate_next = False
        self._smoother: Smoother | None = None
        self._outputs: Outputs | None = None
        self._inline = True  # whether frames are cloned on the loop (set by hello)
        self._rate = FrameRateLimit(
            settings.max_fps,
            settings.rate_burst,
            total=lambda: self.counters.dropped,
            tell=self._tell_rate_limited,
        )
        # Frames as (frame, arrival perf_counter). ``_held`` is the one the writer clones
        # next (or is cloning); ``_pending`` is the one-slot mailbox behind it, where a
        # newer frame replaces an older one (§8). So at most two frames per session.
        self._held: tuple[Frame, float] | None = None
        self._pending: tuple[Frame, float] | None = None
        self._control: deque[bytes] = deque(maxlen=_MAX_CONTROL)
        # Results cloned by the reader itself (cheap frames while the writer keeps up),
        # in frame order, waiting for the writer to send them.
        self._outbox: deque[bytes] = deque()
        self._outbox_bytes = 0
        self._wake = asyncio.Event()
        self._writer_idle = False
        #: Writes a whole frame straight to the socket, or False (``direct_writer``);
        #: None where uvicorn's protocol does not allow it. Set once the session runs.
        self._direct: Callable[[bytes], bool] | None = None
        #: Results of the current burst waiting to be written in one go (``_flush``),
        #: and how many received messages wait for the reader (with ``_direct`` only).
        self._corked: list[bytes] = []
        self._corked_bytes = 0
        self._queued: Callable[[], int] | None = None
        self._reader_waited = False
        self._loop = asyncio.get_running_loop()
        self._stop: asyncio.Future[_Closing] = self._loop.create_future()
        self._last_message = self._loop.time()
        self._idle_timer: asyncio.TimerHandle | None = None
        self._started = time.monotonic()
        self._done = asyncio.Event()

    # -- public --------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Frames waiting in the mailbox (not yet in the writer's hands): 0 or 1."""
        return 0 if self._pending is None else 1

    @property
    def queued_results(self) -> tuple[int, int]:
        """Results cloned but not yet sent: (count, bytes); the bytes are bounded."""
        return len(self._outbox), self._outbox_bytes

    async def run(self) -> None:
        """Run until the client leaves, a fatal error, the idle timeout or ``close``."""
        self._direct = direct_writer(self.ws)
        self._queued = queued_messages(self.ws) if self._direct is not None else None
        reader = asyncio.create_task(self._read_loop(), name=f"session-{self.id}-reader")
        writer = asyncio.create_task(self._write_loop(), name=f"session-{self.id}-writer")
        self._arm_idle_timer()
        ending: _Closing | None = None
        try:
            done, _ = await asyncio.wait(
                {reader, writer, self._stop}, return_when=asyncio.FIRST_COMPLETED
            )
            for task in (self._stop, reader, writer):
                if task in done and not task.cancelled():
                    exc = task.exception()
                    if isinstance(exc, _Closing):
                        ending = exc
                        break
                    if isinstance(exc, WebSocketDisconnect):
                        break  # the client went away mid-send: a normal end
                    if exc is not None:
                        log.error(
                            "session failed",
                            exc_info=exc,
                            extra={"event": "session.crash", "session": self.id},
                        )
                        ending = _Closing(
                            1011,
                            "internal error",
                            ProtocolError(ErrorCode.INTERNAL, "internal server error", fatal=True),
                        )
                        break
                    if task is self._stop:
                        ending = task.result()
                        break
        finally:
            if self._idle_timer is not None:
                self._idle_timer.cancel()
            self._rate.close()
            for task in (reader, writer):
                task.cancel()
            await asyncio.gather(reader, writer, return_exceptions=True)
            if ending is not None:
                await self._send_close(ending)
            self._log_end(ending)
            self._done.set()

    async def close(self, code: int, reason: str) -> None:
        """Ask the session to end with ``code`` (e.g. 1001 at shutdown) and wait for it."""
        if not self._stop.done():
            self._stop.set_result(_Closing(code, reason))
        await self._done.wait()

    # -- idle timeout --------------------------------------------------------------------
    def _arm_idle_timer(self) -> None:
        # One timer per idle period, re-armed from the last message's time when it fires,
        # instead of a timeout scope around every receive (a timer per message).
        when = self._last_message + self.settings.idle_timeout
        self._idle_timer = self._loop.call_at(when, self._check_idle)

    def _check_idle(self) -> None:
        if self._stop.done():
            return
        if self._loop.time() < self._last_message + self.settings.idle_timeout:
            self._arm_idle_timer()
            return
        error = ProtocolError(
            ErrorCode.IDLE_TIMEOUT,
            f"no message for {self.settings.idle_timeout:g} s; closing",
            fatal=True,
        )
        self.counters.errors += 1
        self.metrics.errors.labels(ErrorCode.IDLE_TIMEOUT.name).inc()
        self._stop.set_result(_Closing(close_code(error), "idle timeout", error))

    # -- reading -------------------------------------------------------------------------
    async def _read_loop(self) -> None:
        receive, clock, queued = self.ws.receive, self._loop.time, self._queued
        stages = self._stages
        burst_start = 0.0
        while True:
            if queued is not None:
                waits = not queued()
                if waits:
                    self._flush()  # the burst is over: its results go out together
            else:
                self._reader_waited = False
                self._loop.call_soon(self._mark_reader_waited)
            message = await receive()
            self._last_message = clock()
            if waits if queued is not None else self._reader_waited:
                # The receive had to wait: this message starts a new burst (messages
                # that were already queued when the reader got to them belong to one).
                burst_start = time.perf_counter()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            try:
                if data is None:
                    self.protocol.receive_text(message.get("text") or "")
                decoding = CPU_CLOCK() if stages is not None else 0.0
                decoded = self.protocol.receive(data)
                if type(decoded) is Frame:
                    if stages is not None:
                        stages.add("decode", CPU_CLOCK() - decoding)
                    in_burst = time.perf_counter() - burst_start < _BURST_SECONDS
                    self._on_frame(decoded, in_burst)
                else:
                    self._flush()
                    await self._dispatch(decoded)
            except ProtocolError as exc:
                self._report(exc)

    def _mark_reader_waited(self) -> None:
        # Scheduled before each receive: it runs before the receive returns only if the
        # receive suspended (the loop turned), i.e. no message was already queued.
        self._reader_waited = True

    def _flush(self) -> None:
        """Write the burst's corked results to the socket in one go (or hand them on).

        Called by the reader before anything else is queued or sent, and before it
        waits, so results never overtake one another or a control message.
        """
        corked = self._corked
        if not corked:
            return
        self._corked, self._corked_bytes = [], 0
        data = binary_frame(corked[0]) if len(corked) == 1 else b"".join(map(binary_frame, corked))
        direct, stages = self._direct, self._stages
        writing = CPU_CLOCK() if stages is not None else 0.0
        if direct is not None and not self._outbox and not self._control and direct(data):
            if stages is not None:
                stages.add("write", CPU_CLOCK() - writing, len(corked))
            self.counters.results_out += len(corked)
            self.metrics.frames_out.inc(len(corked))
            return
        # The socket cannot take them at once (back-pressure): the writer sends them.
        self._outbox.extend(corked)
        self._outbox_bytes += sum(map(len, corked))
        self._wake.set()

    def _report(self, error: ProtocolError) -> None:
        """Queue an error for the client; a fatal one ends the session after it is sent."""
        self._flush()
        self.counters.errors += 1
        name = error.code.name if isinstance(error.code, ErrorCode) else str(error.code)
        self.metrics.errors.labels(name).inc()
        if error.fatal:
            raise _Closing(close_code(error), name.lower(), error)
        self._queue_control(error.to_message())

    def _tell_rate_limited(self, error: Error) -> None:
        self.counters.errors += 1
        self.metrics.errors.labels(ErrorCode.RATE_LIMITED.name).inc()
        self._queue_control(error)

    def _queue_control(self, message: Any) -> None:
        self._flush()
        self._control.append(self.protocol.send(message))
        self._wake.set()

    async def _dispatch(self, message: Any) -> None:
        if isinstance(message, Ping):
            self._queue_control(Pong(id=message.id, ts=message.ts))
        elif isinstance(message, Hello):
            await self._on_hello(message)
        elif isinstance(message, Calibrate):
            await self._on_calibrate(message)

    def _on_frame(self, frame: Frame, in_burst: bool) -> None:
        """Clone a cheap frame at once, or put it in the writer's hands or the mailbox.

        ``in_burst``: the frame was read within ``_BURST_SECONDS`` of the first message
        of its burst (the messages that were already waiting when the reader got to them).
        """
        self.counters.frames_in += 1
        self.metrics.frames_in.inc()
        if self._rig is None:  # hello accepted but ready not sent: cannot happen after await
            raise ProtocolError(ErrorCode.WRONG_STATE, "frame before ready", seq=frame.seq)
        if not self._rate.allow():
            # Over the rate: drop this frame (not the pending one, which is older but
            # within the rate); the client is told the total (``frame_rate``).
            self.counters.dropped_rate += 1
            self.metrics.frames_dropped.labels("rate_limited").inc()
            self._rate.discarded(frame.seq)
            return
        arrived = time.perf_counter()
        if (
            self._inline
            and in_burst
            and self._held is None
            and self._pending is None
            and not self._calibrate_next
            and (not self._outbox or self._outbox_bytes < _MAX_OUTBOX_BYTES)
        ):
            # Cheap and nothing older waits: clone it right here, no hand-over to the
            # writer task; frames that arrived together are so all answered, in order,
            # while the writer keeps sending (a blocked send fills the outbox, and then
            # frames go to the mailbox below).
            data = self._clone_inline(frame, arrived)
            if data is None:
                return
            if (
                self._direct is not None
                and self._writer_idle
                and not self._outbox
                and not self._control
            ):
                # Nothing queued before it: the reader writes it to the socket itself
                # at the end of this burst (``_flush``), without waking the writer task
                # or the ASGI send path, and with one syscall for the whole burst.
                self._corked.append(data)
                self._corked_bytes += len(data)
                if self._corked_bytes >= _CORK_BYTES:
                    self._flush()
                return
            self._flush()
            self._outbox.append(data)
            self._outbox_bytes += len(data)
            if self._writer_idle:
                self._wake.set()
            return
        self._flush()
        item = (frame, arrived)
        if self._held is None:
            self._held = item
        else:
            if self._pending is not None:
                self.counters.dropped_superseded += 1
                self.metrics.frames_dropped.labels("superseded").inc()
            self._pending = item
        if self._writer_idle:
            self._wake.set()

    async def _on_hello(self, hello: Hello) -> None:
        if not valid_rig_id(hello.rig):
            raise ProtocolError(
                ErrorCode.UNKNOWN_RIG, f"no rig with id {hello.rig[:64]!r}", fatal=True
            )
        loop = asyncio.get_running_loop()
        try:
            # File I/O and parsing: never on the loop.
            rig = await loop.run_in_executor(None, self.store.get, hello.rig)
        except RigNotFoundError:
            raise ProtocolError(
                ErrorCode.UNKNOWN_RIG, f"no rig with id {hello.rig!r}", fatal=True
            ) from None
        except RigError as exc:
            raise ProtocolError(
                ErrorCode.UNKNOWN_RIG, f"rig {hello.rig!r} cannot be loaded: {exc}", fatal=True
            ) from None
        if hello.align_scale and not rig.align_scale:
            # The rig's weights() reads this flag; a shallow copy keeps the cached rig as is.
            rig = copy.copy(rig)
            rig.align_scale = True
        # A scan of the basis the first time a rig is asked for it (~3 ms for ICT's).
        moving = hello.output == "moving"
        if moving and (await loop.run_in_executor(None, lambda: rig.moving_vertices)).size == 0:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"rig {hello.rig!r} moves no vertex; ask for output vertices",
                fatal=True,
            )
        self.hello = hello
        self.rig_id = hello.rig
        self._base_rig = rig
        self._rig = rig
        self._calibrate_next = hello.calibration
        self._outputs = outputs = Outputs(hello, rig)
        self._inline = (
            hello.output == "weights"
            or blend_seconds(outputs.rows, rig.num_examples) <= INLINE_MAX_SECONDS
        )
        if hello.smoothing is not None:
            sm = hello.smoothing
            self._smoother = Smoother(smoothing_filter(sm, rig), sm.target)
        s = self.settings
        self._queue_control(ready_message(self.id, hello, rig, self.protocol.limits, s))
        log.info(
            "session open",
            extra={
                "event": "session.open",
                "session": self.id,
                "rig": hello.rig,
                "output": hello.output,
                "dtype": hello.dtype,
                "inline": self._inline,
                "by": self.principal,
            },
        )

    async def _on_calibrate(self, message: Calibrate) -> None:
        if message.reset:
            self._calibrate_next = False
            self._rig = self._base_rig
            self._queue_control(Calibrated(active=False))
        elif message.points is None:
            # The next frame the writer clones becomes the neutral.
            self._calibrate_next = True
        else:
            self._rig = await self._calibrated(message.points)
            self._queue_control(Calibrated(active=True))

    async def _calibrated(self, points: np.ndarray, seq: int | None = None) -> Any:
        loop = asyncio.get_running_loop()
        try:
            # Re-fitting the projection is milliseconds for large K: in the clone pool.
            return await loop.run_in_executor(self.executor, self._base_rig.calibrated, points)
        except RigError as exc:
            raise ProtocolError(
                ErrorCode.CALIBRATION_FAILED, f"calibration failed: {exc}", seq=seq
            ) from None

    # -- writing -------------------------------------------------------------------------
    async def _write_loop(self) -> None:
        ws_send, direct = self.ws.send_bytes, self._direct
        # "write" includes waiting for a client that does not read (the ASGI send).
        stages, clock = self._stages, CPU_CLOCK

        async def send(data: bytes) -> None:
            # Straight to the socket when it takes the frame at once (one copy of a large
            # result instead of three); else the ASGI send, which waits for the client.
            if direct is None or not direct(binary_frame(data)):
                await ws_send(data)

        while True:
            if self._control:
                await send(self._control.popleft())
                continue
            if self._outbox:
                data = self._outbox.popleft()
                self._outbox_bytes -= len(data)
                writing = clock() if stages is not None else 0.0
                await send(data)
                if stages is not None:
                    stages.add("write", clock() - writing)
                self.counters.results_out += 1
                self.metrics.frames_out.inc()
                continue
            if self._held is None:
                # Normally empty here (a pending frame is promoted before each send).
                self._held, self._pending = self._pending, None
            if self._held is None:
                self._wake.clear()
                self._writer_idle = True
                try:
                    await self._wake.wait()
                finally:
                    self._writer_idle = False
                continue
            frame, arrived = self._held
            data = await self._result_bytes(frame, arrived)
            # Hand the waiting frame to the writer before a send that may block: a frame
            # arriving meanwhile then waits in the empty mailbox instead of replacing it,
            # so a client keeping two frames in flight never loses one (§8).
            self._held, self._pending = self._pending, None
            if data is None:
                continue
            # Blocks while the client does not read; the reader keeps replacing the
            # pending frame meanwhile, so nothing piles up.
            writing = clock() if stages is not None else 0.0
            await send(data)
            if stages is not None:
                stages.add("write", clock() - writing)
            self.counters.results_out += 1
            self.metrics.frames_out.inc()

    async def _result_bytes(self, frame: Frame, arrived: float) -> bytes | None:
        """The encoded result of ``frame``, or None when it was refused (error queued)."""
        if self._calibrate_next:
            self._calibrate_next = False
            try:
                self._rig = await self._calibrated(frame.points, frame.seq)
            except ProtocolError as exc:
                self._report(exc)
                return None
            await self.ws.send_bytes(self.protocol.send(Calibrated(active=True, seq=frame.seq)))
        if self._inline:
            return self._clone_inline(frame, arrived)
        rig, hello, outputs = self._rig, self.hello, self._outputs
        assert hello is not None and outputs is not None
        # A large blend (ICT: 27k vertices x 56 examples, 0.3-0.8 ms plus 0.2 ms for the
        # f16 cast) goes to the clone pool, batched with other sessions' frames on the
        # same rig; the weights before it are cheap.
        values = outputs.wire if outputs.wire is not None else outputs.vertices
        assert values is not None
        stages = self._stages
        try:
            started = CPU_CLOCK() if stages is not None else 0.0
            weights = frame_weights(rig, frame, hello, self._smoother)
            if stages is not None:
                stages.add("weights", CPU_CLOCK() - started)
            await self.blender.blend(rig, weights, values, moving=outputs.moving)
        except InputError as exc:
            self._refuse(frame, exc)
            return None
        return self._encode(frame, arrived, values)

    def _clone_inline(self, frame: Frame, arrived: float) -> bytes | None:
        """Clone on the loop (weights: µs; small blends: < INLINE_MAX_SECONDS) and encode."""
        hello, outputs = self.hello, self._outputs
        assert hello is not None and outputs is not None
        try:
            values = clone_frame(self._rig, frame, hello, self._smoother, outputs, self._stages)
        except InputError as exc:
            self._refuse(frame, exc)
            return None
        return self._encode(frame, arrived, values)

    def _refuse(self, frame: Frame, exc: InputError) -> None:
        self._report(frame_error(exc, frame.seq))

    def _encode(self, frame: Frame, arrived: float, values: np.ndarray) -> bytes | None:
        """The result's bytes, or None (error queued) when ``values`` are not finite."""
        elapsed = time.perf_counter() - arrived
        stages = self._stages
        encoding = CPU_CLOCK() if stages is not None else 0.0
        outputs = self._outputs
        assert outputs is not None
        # Encoding copies ``values`` out of the session's reused buffers.
        dropped = self.counters.dropped
        try:
            data = self.protocol.send_result(
                frame.seq,
                frame.ts,
                values,
                output=outputs.name,
                proc_us=int(elapsed * 1e6),
                dropped=dropped,
            )
        except ProtocolError as exc:  # RESULT_NOT_FINITE: this frame only
            self._report(exc)
            return None
        self._rate.told(dropped)
        if stages is not None:
            stages.add("encode", CPU_CLOCK() - encoding)
        self.metrics.processing_seconds.observe(elapsed)
        return data

    async def _send_close(self, ending: _Closing) -> None:
        with contextlib.suppress(Exception):
            async with asyncio.timeout(_CLOSE_GRACE):
                if ending.error is not None and self.ws.application_state.name == "CONNECTED":
                    await self.ws.send_bytes(self.protocol.fail(ending.error))
        with contextlib.suppress(Exception):
            async with asyncio.timeout(_CLOSE_GRACE):
                await self.ws.close(ending.code, ending.reason[:120])

    def _log_end(self, ending: _Closing | None) -> None:
        c = self.counters
        log.info(
            "session closed",
            extra={
                "event": "session.close",
                "session": self.id,
                "rig": self.rig_id,
                "code": None if ending is None else ending.code,
                "reason": "client left" if ending is None else ending.reason,
                "seconds": round(time.monotonic() - self._started, 3),
                "frames_in": c.frames_in,
                "results_out": c.results_out,
                "dropped_superseded": c.dropped_superseded,
                "dropped_rate": c.dropped_rate,
                "errors": c.errors,
            },
        )


def ready_message(session_id: str, hello, rig, limits, settings) -> Ready:
    """The ``ready`` answering ``hello`` for ``rig``, with the limits the server enforces."""
    return Ready(
        session=session_id,
        rig=hello.rig,
        names=rig.names,
        num_points=rig.num_points,
        num_vertices=rig.num_vertices,
        output=hello.output,
        dtype=hello.dtype,
        moving=rig.moving_vertices if hello.output == "moving" else None,
        smoothing=None if hello.smoothing is None else smoothing_name(hello.smoothing, rig),
        limits={
            "max_points": int(limits.max_points),
            "max_fps": float(settings.max_fps),
            "rate_burst": int(settings.rate_burst),
            "max_message_bytes": int(settings.max_message_bytes),
            "idle_timeout": float(settings.idle_timeout),
        },
    )

"""One streaming session: a reader task, a one-slot frame mailbox and a writer task.

The reader clones cheap frames itself (on the loop) and queues their results; other
frames wait for the writer in a one-slot mailbox (newer replace older, counted), and
large blends run batched in the clone pool. The writer sends. Memory per session is
bounded whatever the client does. No auth and no admission here.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor

import numpy as np
from starlette.websockets import WebSocket

from facecast.protocol import (
    ClientMessage,
    Frame,
    Hello,
    Limits,
    ProtocolError,
    ServerProtocol,
)
from facecast.rig import Rig
from facecast.rig.errors import InputError, RigError
from facecast.rig.rebase import calibrate as calibrate_rig

from ..compute.blending import BlendBatcher
from ..compute.cloning import (
    Outputs,
    Smoother,
    blend_seconds,
    clone_frame,
    frame_error,
    frame_weights,
)
from ..compute.stages import CPU_CLOCK
from ..connection.core import Closing, Counters, StreamCore, rig_unavailable
from ..connection.driver import Driver
from ..metrics import Metrics
from ..serving.seam import Transport, binary_frame, transport_for
from ..settings import Settings
from ..storage.rig_store import RigNotFoundError, RigStore

__all__ = ["INLINE_MAX_SECONDS", "Session"]

log = logging.getLogger("facecast.server.session")

#: Control messages (pongs, errors, acks) waiting for the writer; beyond this the oldest
#: are dropped: a client that floods pings but never reads must not grow memory.
_MAX_CONTROL = 32
#: A vertices frame whose clone is estimated (``blend_seconds``) to take at most this
#: long is cloned on the event loop; costlier ones go to the clone pool, batched with
#: other sessions' frames (``blending``). Weights-only frames always run on the loop
#: (tens of µs). See SERVER.md, "Streaming choices".
INLINE_MAX_SECONDS = 0.0005
#: Frames that arrived together are cloned in order for at most this long after the
#: first of them was read; later ones in the same burst replace one another (§8).
_BURST_SECONDS = 0.005
#: Frames of one read from the socket are taken on the protocol's stack (``_take``) for
#: at most this long (less than ``_BURST_SECONDS``: every frame taken is in its burst);
#: later ones go to the reader, so a flood shares the loop.
_TAKE_SECONDS = 0.001
#: Results of one burst written to the socket together (one syscall) at the burst's end,
#: or as soon as they reach this many bytes.
_CORK_BYTES = 64 * 1024
#: Encoded results the reader may leave for the writer (at least one is always
#: allowed); past this, frames wait in the mailbox and newer ones replace them (§8).
_MAX_OUTBOX_BYTES = 256 * 1024


class Session(Driver):
    """Serve one accepted WebSocket until either side ends it.

    The rules (hello, rate, calibration, idle, close) are the `StreamCore`'s; this
    object schedules the clone work and writes.

    Parameters
    ----------
    websocket : starlette WebSocket, already accepted
    settings, store, metrics : the app's
    executor : the app's clone thread pool, shared by all sessions of this worker
    blender : the app's blend batcher (over ``executor``); default: one of this session's
    """

    crash_event = "session.crash"
    log = log
    core: StreamCore

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
        core = StreamCore(
            ServerProtocol(Limits(max_message_bytes=settings.max_message_bytes)),
            settings,
            time.monotonic(),
            idle_timeout=settings.idle_timeout,
        )
        core.on_error = self._count_error
        super().__init__(websocket, core, f"session-{self.id}")
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.executor = executor
        self.blender = blender if blender is not None else BlendBatcher(executor)
        self.principal = principal
        self.protocol = core.protocol
        #: Where stage times go (``stages``), with ``settings.stage_timing`` only.
        self._stages = metrics.stages if settings.stage_timing else None
        self.rig_id: str | None = None
        self._smoother: Smoother | None = None
        self._outputs: Outputs | None = None
        self._inline = True  # whether frames are cloned on the loop (set by hello)
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
        #: Writes a whole frame straight to the socket, or False (``Transport.write``);
        #: None where uvicorn's protocol does not allow it. Set once the session runs.
        self._direct: Callable[[bytes], bool] | None = None
        #: Results of the current burst waiting to be written in one go (``_flush``),
        #: and how many received messages wait for the reader (with ``_direct`` only).
        self._corked: list[bytes] = []
        self._corked_bytes = 0
        self._queued: Callable[[], int] | None = None
        self._reader_waited = False
        #: The reader waits in its receive with nothing of its own in flight: frames may
        #: then be taken on the protocol's stack (``_take``), ahead of the receive.
        self._parked = False
        #: When the first frame ``_take`` took since the last flush was read, and whether
        #: a flush is due when the protocol's read is done (``_read_done``).
        self._taken_burst = 0.0
        self._flush_due = False
        self._transport: Transport | None = None
        #: Frames handled on the protocol's stack (``_take``) rather than by the reader.
        self.frames_taken = 0
        self._started = time.monotonic()

    # -- public --------------------------------------------------------------------------
    @property
    def counters(self) -> Counters:
        return self.core.counters

    @property
    def hello(self) -> Hello | None:
        return self.core.hello if self.core.rig is not None else None

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
        transport = transport_for(self.ws)
        if transport.direct:
            self._direct, self._queued = transport.write, transport.messages_waiting
            if transport.take_messages(self._take, self._read_done):
                self._transport = transport
        await super().run()

    def _stopping(self) -> None:
        self._parked = False
        if self._transport is not None:
            self._transport.take_messages(None)

    def _count_error(self, name: str) -> None:
        self.metrics.errors.labels(name).inc()

    # -- reading -------------------------------------------------------------------------
    async def _read_loop(self) -> None:
        receive, clock, queued = self.ws.receive, time.monotonic, self._queued
        core, stages = self.core, self._stages
        burst_start = 0.0
        waits = False
        while True:
            if queued is not None:
                waits = not queued()
                if waits:
                    self._flush()  # the burst is over: its results go out together
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
                    in_burst = time.perf_counter() - burst_start < _BURST_SECONDS
                    self._on_frame(decoded, in_burst, now)
                else:
                    self._flush()
                    await self._dispatch(decoded, now)
            except ProtocolError as exc:
                self._report(exc)

    def _take(self, data: bytes) -> bool:
        """Take a received frame on the protocol's ``data_received`` stack; False: not here.

        The transport offers each binary message here first while nothing waits for the
        reader's receive (``Transport.take_messages``). While the reader is parked in it,
        a frame the session may take as is (``ServerProtocol.receive_frame``) is handled
        exactly as the reader would (``_on_frame``) without the queue, the task switch
        and uvicorn's read pause of each message, and the results of one read are
        written together once the protocol has parsed all of it (``_read_done``).
        Anything else goes to the reader, in order. Never raises: an error ends the
        session as the reader's would.
        """
        if not self._parked or self._stop.done():
            return False
        read_at = time.perf_counter()
        if self._flush_due and read_at - self._taken_burst > _TAKE_SECONDS:
            # This read has had its share of the loop: the rest goes to the reader, one
            # message per turn of the loop (uvicorn pauses reading behind it).
            return False
        stages = self._stages
        decoding = CPU_CLOCK() if stages is not None else 0.0
        frame = self.protocol.receive_frame(data)
        if frame is None:
            return False
        now = time.monotonic()
        self.frames_taken += 1
        self.core.last_message = now
        if stages is not None:
            stages.add("decode", CPU_CLOCK() - decoding)
        if not self._flush_due:
            self._flush_due = True
            self._taken_burst = read_at
        # Within the read's first _TAKE_SECONDS, so within its burst (_BURST_SECONDS).
        self._guarded(self._on_frame, frame, True, now)
        return True

    def _read_done(self) -> None:
        """The protocol has offered every message of one read: write the burst's results."""
        if self._flush_due:
            self._flush_due = False
            if not self._stop.done():
                self._guarded(self._flush)

    def _guarded(self, work: Callable[..., None], *args: object) -> None:
        """Run the reader's ``work`` on the protocol's stack: what it raises ends the session."""
        try:
            try:
                work(*args)
            except ProtocolError as exc:
                self._report(exc)
        except Closing as ending:
            self.stop(ending)
        except Exception as exc:  # a bug: end the session as a crashed reader would
            log.error("session failed", exc_info=exc,
                      extra={"event": self.crash_event, "session": self.id})  # fmt: skip
            self.stop(Closing.internal())

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
            self.core.counters.results_out += len(corked)
            self.metrics.frames_out.inc(len(corked))
            return
        # The socket cannot take them at once (back-pressure): the writer sends them.
        self._outbox.extend(corked)
        self._outbox_bytes += sum(map(len, corked))
        self._wake.set()

    def _report(self, error: ProtocolError) -> None:
        """Queue an error for the client; a fatal one ends the session after it is sent."""
        self._flush()
        self.core.report(error)  # raises Closing when fatal
        self._deliver()

    def _deliver(self) -> None:
        """Queue what the core has to send (pongs, errors, acks) for the writer."""
        out = self.core.data_to_send()
        if out:
            self._flush()
            self._control.extend(out)
            self._wake.set()

    async def _dispatch(self, message: ClientMessage, now: float) -> None:
        work = self.core.handle(message, now)
        if isinstance(work, Hello):
            await self._open(work)
        elif work is not None:
            assert work.points is not None  # the core hands over only calibrates with points
            await self._calibrate(work.points, noise=work.noise)
        self._deliver()
        self.arm()  # a wait for the rig or a neutral suspended the idle deadline

    def _on_frame(self, frame: Frame, in_burst: bool, now: float) -> None:
        """Clone a cheap frame at once, or put it in the writer's hands or the mailbox.

        ``in_burst``: the frame was read within ``_BURST_SECONDS`` of the first message
        of its burst (the messages that were already waiting when the reader got to them).
        """
        self.metrics.frames_in.inc()
        if not self.core.frame_allowed(frame, now):
            # Over the rate: this frame is dropped (not the pending one, which is older
            # but within the rate); the core tells the client the total (``frame_rate``).
            self.metrics.frames_dropped.labels("rate_limited").inc()
            self._deliver()
            self.arm()
            return
        arrived = time.perf_counter()
        if (
            self._inline
            and in_burst
            and self._held is None
            and self._pending is None
            and not self.core.calibrate_next
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
                self.core.counters.dropped_superseded += 1
                self.metrics.frames_dropped.labels("superseded").inc()
            self._pending = item
        if self._writer_idle:
            self._wake.set()

    async def _open(self, hello: Hello) -> None:
        """Load, bind and warm the rig ``hello`` names (off the loop), then open the core."""
        core, loop = self.core, self._loop
        try:
            try:
                # File I/O and parsing: never on the loop.
                loaded: Rig = await loop.run_in_executor(None, self.store.get, hello.rig)
            except (RigNotFoundError, RigError) as exc:
                raise rig_unavailable(hello.rig, exc) from None
            rig = core.bind(loaded)
            smoother = core.smoother(rig)  # a refused smoothing comes instead of ready
            if hello.output == "moving":
                # A scan of the basis the first time a rig is asked for it (~3 ms for ICT's).
                await loop.run_in_executor(None, lambda: rig.moving_vertices)
            core.open(rig, time.monotonic(), self.id)
        except ProtocolError:
            core.failed(time.monotonic())
            raise
        self.rig_id = hello.rig
        self._outputs = outputs = Outputs(hello, rig)
        self._inline = (
            hello.output == "weights"
            or blend_seconds(outputs.rows, rig.num_examples) <= INLINE_MAX_SECONDS
        )
        self._smoother = smoother
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

    async def _calibrate(
        self, points: np.ndarray, seq: int | None = None, *, noise: float | None = None
    ) -> bool:
        """Fit the neutral ``points`` (a ``calibrate`` message's, or frame ``seq``'s).

        ``noise``: the calibrate's landmark noise, for a noise-aware, bounded re-base
        (``rig.rebase``); None re-bases exactly. The core queues its ``calibrated`` or its
        CALIBRATION_FAILED error; False if failed.
        """
        base = self.core.base_rig
        assert base is not None
        try:
            # Re-fitting the projection (or, with noise, the weight model) is milliseconds:
            # in the clone pool.
            rig = await self._loop.run_in_executor(
                self.executor, calibrate_rig, base, points, noise
            )
        except RigError as exc:
            self.core.calibration_failed(exc, time.monotonic(), seq)
            return False
        self.core.calibrated(rig, time.monotonic(), seq)
        return True

    # -- writing -------------------------------------------------------------------------
    async def _write_loop(self) -> None:
        ws_send, direct = self.ws.send_bytes, self._direct
        # "write" includes waiting for a client that does not read (the ASGI send).
        stages, clock = self._stages, CPU_CLOCK
        counters, frames_out = self.core.counters, self.metrics.frames_out

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
            else:
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
                result = await self._result_bytes(frame, arrived)
                # Hand the waiting frame to the writer before a send that may block: a
                # frame arriving meanwhile then waits in the empty mailbox instead of
                # replacing it, so a client keeping two frames in flight never loses one.
                self._held, self._pending = self._pending, None
                if result is None:
                    continue
                data = result
            # Blocks while the client does not read; the reader keeps replacing the
            # pending frame meanwhile, so nothing piles up.
            writing = clock() if stages is not None else 0.0
            await send(data)
            if stages is not None:
                stages.add("write", clock() - writing)
            counters.results_out += 1
            frames_out.inc()

    async def _result_bytes(self, frame: Frame, arrived: float) -> bytes | None:
        """The encoded result of ``frame``, or None when it was refused (error queued)."""
        core = self.core
        if core.take_neutral():
            if not await self._calibrate(frame.points, frame.seq, noise=core.calibrate_noise):
                self._deliver()  # the CALIBRATION_FAILED error, instead of a result
                return None
            for data in core.data_to_send():  # its ``calibrated``, before its result
                await self.ws.send_bytes(data)
        if self._inline:
            return self._clone_inline(frame, arrived)
        rig, hello, outputs = core.rig, core.hello, self._outputs
        assert rig is not None and hello is not None and outputs is not None
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
        core, outputs = self.core, self._outputs
        rig, hello = core.rig, core.hello
        assert rig is not None and hello is not None and outputs is not None
        try:
            values = clone_frame(rig, frame, hello, self._smoother, outputs, self._stages)
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
        try:
            data = self.core.result(frame, values, outputs.name, int(elapsed * 1e6))
        except ProtocolError as exc:  # RESULT_NOT_FINITE: this frame only
            self._report(exc)
            return None
        if stages is not None:
            stages.add("encode", CPU_CLOCK() - encoding)
        self.metrics.processing_seconds.observe(elapsed)
        return data

    def _log_end(self, ending: Closing | None) -> None:
        c = self.core.counters
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
                "frames_taken": self.frames_taken,
                "results_out": c.results_out,
                "dropped_superseded": c.dropped_superseded,
                "dropped_rate": c.dropped_rate,
                "errors": c.errors,
            },
        )

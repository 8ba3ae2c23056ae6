"""One streaming session: the driver's reader, a one-slot frame mailbox and its writer.

The reader clones cheap frames itself (on the loop) and writes or queues their results
(the driver's `Outbox`); other frames wait for the writer in a one-slot mailbox (newer
replace older, counted), and large blends run batched in the clone pool. Memory per
session is bounded whatever the client does. No auth and no admission here.
"""

from __future__ import annotations

import logging
import secrets
import time
from collections.abc import Callable
from concurrent.futures import Executor

import numpy as np
from starlette.websockets import WebSocket

from facecast.protocol import Frame, Hello, Limits, ProtocolError, ServerProtocol
from facecast.rig.errors import InputError
from facecast.rig.filters import KalmanFilter

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
from ..connection.closing import Closing
from ..connection.core import Counters, StreamCore
from ..connection.driver import Driver
from ..connection.opening import load_rig
from ..connection.outbox import Outbox
from ..metrics import Metrics
from ..serving.seam import Transport, transport_for
from ..settings import Settings
from ..storage.rig_store import RigStore

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
#: Frames of one read from the socket are taken on the protocol's stack (``_take``) for
#: at most this long (less than the driver's ``BURST_SECONDS``: every frame taken is in
#: its burst); later ones go to the reader, so a flood shares the loop.
_TAKE_SECONDS = 0.001
#: Encoded results the reader may leave for the writer (at least one is always
#: allowed); past this, frames wait in the mailbox and newer ones replace them (§8).
_MAX_OUTBOX_BYTES = 256 * 1024


class Session(Driver):
    """Serve one accepted WebSocket until either side ends it.

    The rules (hello, rate, calibration, idle, close) and the counts are the
    `StreamCore`'s; reading and writing are the `Driver`'s; this object schedules the
    clone work.

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
            metrics=metrics,
        )
        #: Where stage times go (``stages``), with ``settings.stage_timing`` only.
        stages = metrics.stages if settings.stage_timing else None
        outbox = Outbox(websocket, limit=_MAX_CONTROL, collapse=False, stages=stages,
                        on_results=core.results_sent)  # fmt: skip
        super().__init__(websocket, core, f"session-{self.id}", outbox, executor=executor,
                         stages=stages)  # fmt: skip
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.blender = blender if blender is not None else BlendBatcher(executor)
        self.principal = principal
        self.rig_id: str | None = None
        self._smoother: Smoother | None = None
        self._outputs: Outputs | None = None
        self._inline = True  # whether frames are cloned on the loop (set by hello)
        # Frames as (frame, arrival perf_counter). ``_held`` is the one the writer clones
        # next (or is cloning); ``_pending`` is the one-slot mailbox behind it, where a
        # newer frame replaces an older one (§8). So at most two frames per session.
        self._held: tuple[Frame, float] | None = None
        self._pending: tuple[Frame, float] | None = None
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
        return self.outbox.queued_results

    async def run(self) -> None:
        """Run until the client leaves, a fatal error, the idle timeout or ``close``."""
        transport = transport_for(self.ws)
        if transport.direct and transport.take_messages(self._take, self._read_done):
            # While the reader is parked in its receive, frames are taken on the
            # protocol's stack (``_take``), ahead of the receive.
            self._transport = transport
        await super().run()

    def _stopping(self) -> None:
        super()._stopping()
        if self._transport is not None:
            self._transport.take_messages(None)

    # -- reading -------------------------------------------------------------------------
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
        now = time.monotonic()
        frame = self.core.receive_frame(data, now)
        if frame is None:
            return False
        self.frames_taken += 1
        if stages is not None:
            stages.add("decode", CPU_CLOCK() - decoding)
        if not self._flush_due:
            self._flush_due = True
            self._taken_burst = read_at
        # Within the read's first _TAKE_SECONDS, so within its burst (_BURST_SECONDS).
        self._guarded(self._on_frame, frame, now, True)
        return True

    def _read_done(self) -> None:
        """The protocol has offered every message of one read: write the burst's results."""
        if self._flush_due:
            self._flush_due = False
            if not self._stop.done():
                self._guarded(self.outbox.flush)

    def _guarded(self, work: Callable[..., None], *args: object) -> None:
        """Run the reader's ``work`` on the protocol's stack: what it raises ends the session."""
        try:
            try:
                work(*args)
            except ProtocolError as exc:
                self.report(exc)
        except Closing as ending:
            self.stop(ending)
        except Exception as exc:  # a bug: end the session as a crashed reader would
            log.error("session failed", exc_info=exc,
                      extra={"event": self.crash_event, "session": self.id})  # fmt: skip
            self.stop(Closing.internal())

    def _on_frame(self, frame: Frame, now: float, in_burst: bool) -> None:
        """Clone a cheap frame at once, or put it in the writer's hands or the mailbox.

        ``in_burst``: the frame was read within ``BURST_SECONDS`` of the first message
        of its burst (the messages that were already waiting when the reader got to them).
        """
        if not self.core.frame_allowed(frame, now):
            # Over the rate: this frame is dropped (not the pending one, which is older
            # but within the rate); the core tells the client the total (``frame_rate``).
            self._deliver()
            self.arm()
            return None
        arrived = time.perf_counter()
        outbox = self.outbox
        if (
            self._inline
            and in_burst
            and self._held is None
            and self._pending is None
            and not self.core.calibrate_next
            and outbox.result_bytes < _MAX_OUTBOX_BYTES
        ):
            # Cheap and nothing older waits: clone it right here, no hand-over to the
            # writer task; frames that arrived together are so all answered, in order,
            # while the writer keeps sending (a blocked send fills the outbox, and then
            # frames go to the mailbox below).
            data = self._clone_inline(frame, arrived)
            if data is None:
                return None
            # Nothing queued before it: the reader writes it to the socket itself at the
            # end of this burst (``Outbox.flush``), without waking the writer task or the
            # ASGI send path, and with one syscall for the whole burst.
            if not outbox.cork(data):
                outbox.offer_result(data)
            return None
        outbox.flush()
        item = (frame, arrived)
        if self._held is None:
            self._held = item
        else:
            if self._pending is not None:
                self.core.frame_superseded()
            self._pending = item
        if outbox.idle:
            outbox.wake()
        return None

    def _filter_points(self, kalman: KalmanFilter) -> None:
        self._smoother = Smoother(kalman, "points")

    async def _open(self, hello: Hello) -> None:
        """Load, bind and warm the rig ``hello`` names (off the loop), then open the core."""
        core, loop = self.core, self._loop
        try:
            rig = core.bind(await load_rig(self.store, hello.rig))
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

    # -- writing -------------------------------------------------------------------------
    async def _write_loop(self) -> None:
        await self.outbox.run(self._produce, self._has_work)

    def _has_work(self) -> bool:
        return self._held is not None or self._pending is not None

    async def _produce(self) -> bytes | None:
        """The result of the frame in the writer's hands (or the mailbox's), or None."""
        if self._held is None:
            # Normally empty here (a pending frame is promoted before each send).
            self._held, self._pending = self._pending, None
        if self._held is None:
            return None
        frame, arrived = self._held
        result = await self._result_bytes(frame, arrived)
        # Hand the waiting frame to the writer before a send that may block: a frame
        # arriving meanwhile then waits in the empty mailbox instead of replacing it, so
        # a client keeping two frames in flight never loses one.
        self._held, self._pending = self._pending, None
        return result

    async def _result_bytes(self, frame: Frame, arrived: float) -> bytes | None:
        """The encoded result of ``frame``, or None when it was refused (error queued)."""
        core = self.core
        if core.take_neutral():
            if not await self._calibrate(frame.points, frame.seq, core.calibrate_noise):
                self._deliver()  # the CALIBRATION_FAILED error, instead of a result
                return None
            for data in core.data_to_send():  # its ``calibrated``, before its result
                await self.outbox.send(data)
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
        self.report(frame_error(exc, frame.seq))

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
            self.report(exc)
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

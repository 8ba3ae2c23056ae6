"""The rules of one client connection, sans I/O: what each message means and what to answer.

``/v1/stream`` sessions and channel publishers and watchers all drive a `ConnectionCore`:
fed received bytes and the clock, it returns messages (bytes to send), asks for rigs to
be loaded or calibrated, decides when to close, and counts what the connection did (its
``counters`` and, given ``metrics``, the app's). No asyncio, sockets or Starlette here
(the websockets sans-I/O precedent): the `Driver` schedules, runs the work asked for in
threads and writes.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import NoReturn

import numpy as np

from facecast.protocol import (
    CHANNEL_OUTPUTS,
    Calibrate,
    Calibrated,
    ClientMessage,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Ping,
    Pong,
    ProtocolError,
    ServerMessage,
    ServerProtocol,
    Smoothing,
    close_code,
)
from facecast.rig import Rig
from facecast.rig.errors import RigError
from facecast.rig.filters import KalmanFilter, OneEuroFilter

from ..compute.cloning import Smoother, calibrated_filter, smoothing_filter
from ..guards.calibrate_rate import CalibrateRateLimit
from ..guards.frame_rate import FrameRateLimit
from ..metrics import Metrics
from ..settings import Settings
from ..storage.rig_store import valid_rig_id
from .closing import CLOSE_GRACE, Closing
from .opening import ready_message

__all__ = [
    "CLOSE_GRACE",
    "Closing",
    "ConnectionCore",
    "Counters",
    "PublisherCore",
    "StreamCore",
    "WatcherCore",
]


@dataclass
class Counters:
    """What a connection has done; read by tests and logged when it ends."""

    frames_in: int = 0
    results_out: int = 0
    dropped_superseded: int = 0
    dropped_rate: int = 0
    errors: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_superseded + self.dropped_rate


def _none() -> int:
    return 0


class ConnectionCore:
    """One connection's protocol state, rate limit, calibration, idle and close rules.

    The driver feeds each received message to `receive` (bytes) or `receive_text`, then
    a `Frame` to `frame_allowed` (the hot path: no event objects) and anything else to
    `handle`. What the core wants sent waits in `data_to_send`. It asks for work by
    return value (`handle` returns a `Hello` to load its rig, or the points to calibrate
    on) and is told the outcome (`open`, `calibrated`, `calibration_failed`, `failed`);
    while it waits (`waiting`), the client is not idle. A fatal error raises `Closing`.
    The clock (``time.monotonic()``) is always passed in; `deadline` says when `tick`
    must be called next.

    Parameters
    ----------
    protocol : the connection's `ServerProtocol` (the core decodes and encodes with it)
    settings : the app's (``max_fps``, ``rate_burst``, ``calibrate_rate``,
        ``calibrate_burst``, ``idle_timeout``)
    now : the clock when the connection was accepted
    idle_timeout : seconds without a message before IDLE_TIMEOUT; None: no idle rule
    metrics : the app's collectors, counted into along with ``counters`` (errors by code,
        frames in and out, frames dropped); None: ``counters`` only
    wall_clock : the server's wall clock (seconds since the Unix epoch) that a ``pong``
        tells, for the clients' offset estimates (PROTOCOL.md §5.4)
    """

    def __init__(
        self,
        protocol: ServerProtocol,
        settings: Settings,
        now: float,
        *,
        idle_timeout: float | None,
        metrics: Metrics | None = None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.protocol = protocol
        self.wall_clock = wall_clock
        self.metrics = metrics
        self.settings = settings
        self.counters = Counters()
        self.idle_timeout = idle_timeout
        self.rate = FrameRateLimit(settings.max_fps, settings.rate_burst, now)
        self.calibrations = CalibrateRateLimit(
            settings.calibrate_rate, settings.calibrate_burst, now
        )
        #: The rig as bound at hello; ``rig`` is it or its calibrated variant.
        self.base_rig: Rig | None = None
        self.rig: Rig | None = None
        #: The next frame becomes the neutral (``hello.calibration`` or ``calibrate``).
        self.calibrate_next = False
        #: The landmark noise that ``calibrate`` gave for it (None: an exact re-base).
        self.calibrate_noise: float | None = None
        #: The filter ``hello.smoothing`` runs (``ready.smoothing``, ``calibrated.smoothing``).
        self.smoothing_running: str | None = None
        #: The re-base's σ an auto smoothing's Kalman filter runs on (None: none).
        self.filter_noise: float | None = None
        #: Work asked for and not yet answered (a rig load, a calibration).
        self.waiting = 0
        self.last_message = now
        #: Told the code's name of every error the core counts (the app's metrics).
        self.on_error: Callable[[str], None] | None = (
            None if metrics is None else self._error_metric
        )
        self._out: list[bytes] = []

    @property
    def hello(self) -> Hello | None:
        """The ``hello`` received (or negotiated out of band), once there is one."""
        return self.protocol.hello

    # -- receiving -----------------------------------------------------------------------
    def receive(self, data: bytes, now: float) -> ClientMessage:
        """Decode one binary message received at ``now`` (ProtocolError if refused)."""
        self.last_message = now
        return self.protocol.receive(data)

    def receive_frame(self, data: bytes, now: float) -> Frame | None:
        """``data`` received at ``now`` as a frame taken as is (``ServerProtocol.receive_frame``).

        None: not such a frame (nothing is consumed; `receive` it in order instead).
        """
        frame = self.protocol.receive_frame(data)
        if frame is not None:
            self.last_message = now
        return frame

    def receive_text(self, text: str, now: float) -> NoReturn:
        """A text message received at ``now``: always refused (TEXT_NOT_SUPPORTED)."""
        self.last_message = now
        self.protocol.receive_text(text)

    def handle(self, message: ClientMessage, now: float) -> Hello | Calibrate | None:
        """React to a decoded message other than a frame, received at ``now``.

        Returns the work the driver must do and report back: the `Hello` whose rig to
        load (then `open` or `failed`), or the `Calibrate` with the points to re-base on
        (then `calibrated` or `calibration_failed`); None when the answer, if any, is in
        `data_to_send`. A
        ``calibrate`` over the connection's budget (``calibrate_rate``) asks for nothing:
        its RATE_LIMITED error is in `data_to_send`.
        """
        if isinstance(message, Ping):
            self.send(Pong(id=message.id, ts=message.ts, server_ts=self.wall_clock()))
        elif isinstance(message, Hello):
            self.check_hello(message)
            self.waiting += 1
            return message
        elif isinstance(message, Calibrate):
            if message.reset:
                self.calibrate_next = False
                self.reset_calibration()
                self.send(Calibrated(active=False, smoothing=self.smoothing_running))
            elif message.points is None and self.calibrate_next:
                pass  # the next frame is already to become the neutral: no second fit
            elif self._calibration_refused(now):
                pass
            elif message.points is None:
                self.calibrate_next = True
                self.calibrate_noise = message.noise
            else:
                self.waiting += 1
                return message
        return None

    def _calibration_refused(self, now: float) -> bool:
        error = self.calibrations.refusal(now)
        if error is None:
            return False
        self.report(error)
        return True

    def check_hello(self, hello: Hello) -> None:
        """Refuse a ``hello`` this endpoint cannot serve (fatal ProtocolError)."""
        if not valid_rig_id(hello.rig):
            raise ProtocolError(
                ErrorCode.UNKNOWN_RIG, f"no rig with id {hello.rig[:64]!r}", fatal=True
            )

    def open(self, rig: Rig, now: float, session_id: str) -> None:
        """The rig ``hello`` asked for is ``rig``: send ``ready``, start streaming."""
        self._done_waiting(now)
        hello = self.hello
        assert hello is not None
        self.base_rig = self.rig = rig
        self.calibrate_next = hello.calibration
        self.calibrate_noise = None
        ready = ready_message(session_id, hello, rig, self.protocol.limits, self.settings)
        self.smoothing_running = ready.smoothing
        self.send(ready)

    def failed(self, now: float) -> None:
        """The work asked for ended without an answer (the driver reports why)."""
        self._done_waiting(now)

    def smoothing(self, rig: Rig) -> OneEuroFilter | KalmanFilter | None:
        """A new filter with ``hello``'s smoothing options (§5.1.1) for ``rig``, or None.

        Raises ProtocolError (INVALID_FIELD, fatal) for a Kalman filter without a noise:
        build it before ``open``, so the refusal comes instead of ``ready``.
        """
        hello = self.hello
        sm = None if hello is None else hello.smoothing
        return None if sm is None else smoothing_filter(sm, rig)

    # -- frames --------------------------------------------------------------------------
    def frame_allowed(self, frame: Frame, now: float) -> bool:
        """Count ``frame``; False when it is over the rate (dropped, counted, maybe told)."""
        counters, metrics = self.counters, self.metrics
        counters.frames_in += 1
        if metrics is not None:
            metrics.frames_in.inc()
        if self.rig is None:  # hello accepted but ready not sent: the driver awaits the rig
            raise ProtocolError(ErrorCode.WRONG_STATE, "frame before ready", seq=frame.seq)
        if self.rate.allow(now):
            return True
        counters.dropped_rate += 1
        if metrics is not None:
            metrics.frames_dropped.labels("rate_limited").inc()
        error = self.rate.discarded(frame.seq, now, self.dropped_total())
        if error is not None:
            self._count(ErrorCode.RATE_LIMITED.name)
            self.send(error)
        return False

    def dropped_total(self) -> int:
        """Frames of this connection discarded so far (``result.dropped``, §8)."""
        return self.counters.dropped

    def frame_superseded(self) -> None:
        """A frame waiting to be cloned was replaced by a newer one (§8): dropped, counted."""
        self.counters.dropped_superseded += 1
        if self.metrics is not None:
            self.metrics.frames_dropped.labels("superseded").inc()

    def results_sent(self, n: int) -> None:
        """``n`` results were handed to the socket."""
        self.counters.results_out += n
        if self.metrics is not None:
            self.metrics.frames_out.inc(n)

    def take_neutral(self) -> bool:
        """Whether this frame is to become the neutral (once per ``calibrate`` asked)."""
        if self.calibrate_next:
            self.calibrate_next = False
            return True
        return False

    def result(self, frame: Frame, values: np.ndarray, output: str, proc_us: int) -> bytes:
        """The ``result`` bytes for ``frame``; RESULT_NOT_FINITE (this frame only) if bad."""
        dropped = self.dropped_total()
        data = self.protocol.send_result(
            frame.seq, frame.ts, values, output=output, proc_us=proc_us, dropped=dropped
        )
        self.rate.told(dropped)
        return data

    # -- calibration ---------------------------------------------------------------------
    def calibrated(
        self,
        rig: Rig,
        now: float,
        seq: int | None = None,
        *,
        points: np.ndarray | None = None,
        noise: float | None = None,
        blinks: Mapping[str, np.ndarray] | None = None,
        contrast: tuple[float, float] | None = None,
    ) -> None:
        """The calibration asked for gave ``rig``; ``seq``: the frame taken as neutral.

        Only a calibration `handle` asked for (``seq`` None) ends a wait: a frame's
        neutral (`take_neutral`) is fitted while the reader goes on reading. ``points``,
        ``noise``, ``blinks`` and ``contrast`` (what it was fitted on) matter to a channel's
        publisher only.
        """
        if seq is None:
            self._done_waiting(now)
        self.rig = rig
        self.send(Calibrated(active=True, seq=seq, smoothing=self.smoothing_running))

    def calibrated_filter(self, calibrated: Rig) -> KalmanFilter | None:
        """The Kalman filter ``hello``'s auto smoothing switches to once a calibrate with a
        noise re-based the rig into ``calibrated`` (``compute.cloning.calibrated_filter``:
        a rig fitted exactly and no ``smoothing.noise``), or None; the ``calibrated`` then
        says "kalman". None too when the filter already runs on that noise (a calibrate
        again with the closed eyes, the same neutral): it goes on, with no restart."""
        hello, base = self.hello, self.base_rig
        if hello is None or base is None:
            return None
        kalman = calibrated_filter(hello.smoothing, base, calibrated)
        if kalman is None or kalman.noise == self.filter_noise:
            return None
        self.smoothing_running, self.filter_noise = "kalman", kalman.noise
        return kalman

    def calibration_failed(self, exc: RigError, now: float, seq: int | None = None) -> None:
        """The calibration asked for was refused by the rig: CALIBRATION_FAILED, not fatal."""
        if seq is None:
            self._done_waiting(now)
        self.report(
            ProtocolError(ErrorCode.CALIBRATION_FAILED, f"calibration failed: {exc}", seq=seq)
        )

    def reset_calibration(self) -> None:
        self.rig = self.base_rig

    # -- errors, time and closing --------------------------------------------------------
    def report(self, error: ProtocolError) -> None:
        """Send ``error``; a fatal one raises `Closing` instead (sent with the close)."""
        self._count(error.code_name)
        if error.fatal:
            raise Closing.for_error(error)
        self.send(Error.of(error))

    def deadline(self) -> float | None:
        """When `tick` is due next (idle timeout, a rate error owed), or None."""
        late = self.rate.deadline
        if self.idle_timeout is None or self.waiting:
            return late
        idle = self.last_message + self.idle_timeout
        return idle if late is None else min(idle, late)

    def tick(self, now: float) -> None:
        """Apply the rules that depend on time alone; raises `Closing` when idle too long."""
        error = self.rate.due(now, self.dropped_total())
        if error is not None:
            self._count(ErrorCode.RATE_LIMITED.name)
            self.send(error)
        timeout = self.idle_timeout
        if timeout is not None and not self.waiting and now >= self.last_message + timeout:
            self._count(ErrorCode.IDLE_TIMEOUT.name)
            error_ = ProtocolError(
                ErrorCode.IDLE_TIMEOUT, f"no message for {timeout:g} s; closing", fatal=True
            )
            raise Closing(close_code(error_), "idle timeout", error_)

    def closing_bytes(self, ending: Closing) -> bytes | None:
        """The fatal ``error`` to send before the close frame, if ``ending`` has one."""
        if ending.error is None:
            return None
        return self.protocol.fail(ending.error)

    # -- output --------------------------------------------------------------------------
    def send(self, message: ServerMessage) -> None:
        """Queue ``message`` for the client (``data_to_send``)."""
        self._out.append(self.protocol.send(message))

    def data_to_send(self) -> list[bytes]:
        """The messages queued since the last call, in order (the driver sends them)."""
        out = self._out
        if out:
            self._out = []
        return out

    def _error_metric(self, name: str) -> None:
        assert self.metrics is not None
        self.metrics.errors.labels(name).inc()

    def _count(self, name: str) -> None:
        self.counters.errors += 1
        if self.on_error is not None:
            self.on_error(name)

    def _done_waiting(self, now: float) -> None:
        # Time spent on the server's own work (loading a rig, fitting a neutral) is not
        # the client's idle time: the idle clock restarts when it is done.
        self.waiting = max(0, self.waiting - 1)
        self.last_message = max(self.last_message, now)


class StreamCore(ConnectionCore):
    """``/v1/stream`` (PROTOCOL.md §5): any output; align, smoothing, calibration here."""

    def bind(self, rig: Rig) -> Rig:
        """The rig this session clones with, as ``hello`` asks; ``rig`` is not mutated."""
        hello = self.hello
        assert hello is not None
        # A rig of its own when it differs: the store's cached rig is shared by every session.
        return rig.with_align_scale(True) if hello.align_scale else rig

    def open(self, rig: Rig, now: float, session_id: str) -> None:
        """As `ConnectionCore.open`; fatal INVALID_FIELD for ``moving`` on a rig moving nothing.

        Read ``rig.moving_vertices`` off the loop first: its first scan takes ms.
        """
        hello = self.hello
        assert hello is not None
        if hello.output == "moving" and rig.moving_vertices.size == 0:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"rig {hello.rig!r} moves no vertex; ask for output vertices",
                fatal=True,
            )
        super().open(rig, now, session_id)

    def smoother(self, rig: Rig) -> Smoother | None:
        """The session's smoothing of points or weights, as ``hello`` asks (None: none)."""
        chosen, hello = self.smoothing(rig), self.hello
        if chosen is None or hello is None or hello.smoothing is None:
            return None
        return Smoother(chosen, hello.smoothing.target)


class PublisherCore(ConnectionCore):
    """A channel's publisher (§5.1): channel outputs only; its neutral goes to the channel.

    Calibration does not change how the publisher's frames are cloned here (each watched
    key re-bases its own rig on ``neutral``): ``rig`` is the layout rig the frames'
    range is checked against, calibrated once a neutral is captured.
    """

    def __init__(
        self, protocol: ServerProtocol, settings: Settings, now: float, *, idle_timeout: float
    ) -> None:
        super().__init__(protocol, settings, now, idle_timeout=idle_timeout)
        self.neutral: np.ndarray | None = None
        #: The landmark noise the neutral was re-based with (None: exactly; §5.1.3).
        self.neutral_noise: float | None = None
        #: The performer's closed eyes the neutral came with (calibrate ``blinks``, §5.1.3).
        self.neutral_blinks: dict[str, np.ndarray] | None = None
        #: Their own blink curve (calibrate ``blink_contrast``), or None: the server's.
        self.neutral_contrast: tuple[float, float] | None = None
        #: Names the neutral, so keys see a new one even if its points are equal.
        self.neutral_id = ""
        #: Frames of this publisher the channel discarded (superseded): ``channel.dropped``.
        self.superseded: Callable[[], int] = _none

    def check_hello(self, hello: Hello) -> None:
        if hello.output not in CHANNEL_OUTPUTS:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"hello.output {hello.output!r} is for /v1/stream only; a channel serves "
                f"{list(CHANNEL_OUTPUTS)}",
                fatal=True,
            )
        super().check_hello(hello)

    def dropped_total(self) -> int:
        return self.counters.dropped_rate + self.superseded()

    def point_filter(self, rig: Rig) -> OneEuroFilter | KalmanFilter | None:
        """Smoothing of the points, done once here for every key (``target: points``)."""
        hello = self.hello
        if hello is None or hello.smoothing is None or hello.smoothing.target != "points":
            return None
        return self.smoothing(rig)

    @property
    def channel_smoothing(self) -> Smoothing | None:
        """Smoothing of the weights, done by each key for its own rig (``target: weights``)."""
        hello = self.hello
        if hello is None or hello.smoothing is None or hello.smoothing.target != "weights":
            return None
        return hello.smoothing

    def calibrated(
        self,
        rig: Rig,
        now: float,
        seq: int | None = None,
        *,
        points: np.ndarray | None = None,
        noise: float | None = None,
        blinks: Mapping[str, np.ndarray] | None = None,
        contrast: tuple[float, float] | None = None,
    ) -> None:
        """As `ConnectionCore.calibrated`; ``points`` (the neutral), the ``noise``, the
        closed eyes (``blinks``) and their curve (``contrast``) it was re-based with go to
        the channel, whose every key re-bases its own rig the same way."""
        assert points is not None
        self.neutral, self.neutral_noise = np.array(points, copy=True), noise
        self.neutral_blinks = (
            None if not blinks else {name: np.array(a, copy=True) for name, a in blinks.items()}
        )
        self.neutral_contrast = contrast if blinks else None
        self.neutral_id = secrets.token_hex(6)
        super().calibrated(rig, now, seq)

    def reset_calibration(self) -> None:
        super().reset_calibration()
        self.neutral, self.neutral_noise, self.neutral_id = None, None, ""
        self.neutral_blinks, self.neutral_contrast = None, None


class WatcherCore(ConnectionCore):
    """A channel watcher (§2.1): opened by its query string, it may only send ``ping``."""

    def __init__(self, protocol: ServerProtocol, settings: Settings, now: float) -> None:
        # No idle rule: a watcher only listens (its pings are optional).
        super().__init__(protocol, settings, now, idle_timeout=None)

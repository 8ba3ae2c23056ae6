"""The rules of one client connection, sans I/O: what each message means and what to answer.

``/v1/stream`` sessions and channel publishers and watchers all drive a `ConnectionCore`:
fed received bytes and the clock, it returns messages (bytes to send), asks for rigs to
be loaded or calibrated, and decides when to close. No asyncio, sockets or Starlette here
(the websockets sans-I/O precedent): the drivers (``session``, ``members``) schedule,
run the work asked for in threads and write.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable
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
    Limits,
    Ping,
    Pong,
    ProtocolError,
    Ready,
    ServerMessage,
    ServerProtocol,
    Smoothing,
    close_code,
)
from facecast.rig import Rig
from facecast.rig.errors import RigError
from facecast.rig.filters import KalmanFilter, OneEuroFilter

from ..compute.cloning import Smoother, smoothing_filter, smoothing_name
from ..guards.calibrate_rate import CalibrateRateLimit
from ..guards.frame_rate import FrameRateLimit
from ..settings import Settings
from ..storage.rig_store import RigNotFoundError, valid_rig_id

__all__ = [
    "CLOSE_GRACE",
    "Closing",
    "ConnectionCore",
    "Counters",
    "PublisherCore",
    "StreamCore",
    "WatcherCore",
    "ready_message",
    "rig_unavailable",
    "watch_ready",
]

#: How long a closing connection waits to hand its last error, then its close frame, to
#: the socket (each).
CLOSE_GRACE = 1.0


class Closing(Exception):
    """Ends a connection with a close code (and maybe a fatal error sent first)."""

    def __init__(self, code: int, reason: str, error: ProtocolError | None = None) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.error = error

    @classmethod
    def for_error(cls, error: ProtocolError) -> Closing:
        """The close a fatal ``error`` calls for (PROTOCOL.md §7: its code's close code)."""
        return cls(close_code(error), error.code_name.lower(), error)

    @classmethod
    def internal(cls) -> Closing:
        """The close of a connection whose server side failed (a bug): 1011, INTERNAL."""
        error = ProtocolError(ErrorCode.INTERNAL, "internal server error", fatal=True)
        return cls(1011, "internal error", error)


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


def rig_unavailable(rig_id: str, exc: Exception) -> ProtocolError:
    """The fatal UNKNOWN_RIG for a ``hello`` whose rig could not be loaded (``exc``)."""
    if isinstance(exc, RigNotFoundError):
        return ProtocolError(ErrorCode.UNKNOWN_RIG, f"no rig with id {rig_id!r}", fatal=True)
    return ProtocolError(
        ErrorCode.UNKNOWN_RIG, f"rig {rig_id!r} cannot be loaded: {exc}", fatal=True
    )


def ready_message(
    session_id: str, hello: Hello, rig: Rig, limits: Limits, settings: Settings
) -> Ready:
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
            "calibrate_rate": float(settings.calibrate_rate),
            "calibrate_burst": int(settings.calibrate_burst),
            "max_message_bytes": int(settings.max_message_bytes),
            "idle_timeout": float(settings.idle_timeout),
        },
    )


def watch_ready(
    session_id: str, rig_id: str, rig: Rig, output: str, dtype: str, settings: Settings
) -> Ready:
    """The ``ready`` a channel watcher gets on joining (§2.1): what it will receive.

    Its limits hold ``max_message_bytes`` only: a watcher sends no frames or calibrations.
    """
    return Ready(
        session=session_id,
        rig=rig_id,
        names=rig.names,
        num_points=rig.num_points,
        num_vertices=rig.num_vertices,
        output=output,
        dtype=dtype,
        limits={"max_message_bytes": int(settings.max_message_bytes)},
    )


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
    """

    def __init__(
        self,
        protocol: ServerProtocol,
        settings: Settings,
        now: float,
        *,
        idle_timeout: float | None,
    ) -> None:
        self.protocol = protocol
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
        #: Work asked for and not yet answered (a rig load, a calibration).
        self.waiting = 0
        self.last_message = now
        #: Told the code's name of every error the core counts (the app's metrics).
        self.on_error: Callable[[str], None] | None = None
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
            self.send(Pong(id=message.id, ts=message.ts))
        elif isinstance(message, Hello):
            self.check_hello(message)
            self.waiting += 1
            return message
        elif isinstance(message, Calibrate):
            if message.reset:
                self.calibrate_next = False
                self.reset_calibration()
                self.send(Calibrated(active=False))
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
        self.send(ready_message(session_id, hello, rig, self.protocol.limits, self.settings))

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
        counters = self.counters
        counters.frames_in += 1
        if self.rig is None:  # hello accepted but ready not sent: the driver awaits the rig
            raise ProtocolError(ErrorCode.WRONG_STATE, "frame before ready", seq=frame.seq)
        if self.rate.allow(now):
            return True
        counters.dropped_rate += 1
        error = self.rate.discarded(frame.seq, now, self.dropped_total())
        if error is not None:
            self._count(ErrorCode.RATE_LIMITED.name)
            self.send(error)
        return False

    def dropped_total(self) -> int:
        """Frames of this connection discarded so far (``result.dropped``, §8)."""
        return self.counters.dropped

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
    def calibrated(self, rig: Rig, now: float, seq: int | None = None) -> None:
        """The calibration asked for gave ``rig``; ``seq``: the frame taken as neutral.

        Only a calibration `handle` asked for (``seq`` None) ends a wait: a frame's
        neutral (`take_neutral`) is fitted while the reader goes on reading.
        """
        if seq is None:
            self._done_waiting(now)
        self.rig = rig
        self.send(Calibrated(active=True, seq=seq))

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
    ) -> None:
        """As `ConnectionCore.calibrated`; ``points`` (the neutral) and the ``noise`` it was
        re-based with go to the channel, whose every key re-bases its own rig the same way."""
        assert points is not None
        self.neutral = np.array(points, copy=True)
        self.neutral_noise = noise
        self.neutral_id = secrets.token_hex(6)
        super().calibrated(rig, now, seq)

    def reset_calibration(self) -> None:
        super().reset_calibration()
        self.neutral, self.neutral_noise, self.neutral_id = None, None, ""


class WatcherCore(ConnectionCore):
    """A channel watcher (§2.1): opened by its query string, it may only send ``ping``."""

    def __init__(self, protocol: ServerProtocol, settings: Settings, now: float) -> None:
        # No idle rule: a watcher only listens (its pings are optional).
        super().__init__(protocol, settings, now, idle_timeout=None)

"""The load generator: N concurrent streaming clients at F fps for S seconds, and its report.

Bounded in clients, frames and time (it stops by itself) and talks only to the URL it is
given; it measures, it does not judge (pass/fail belongs to the callers).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from facecast.client.connection import ConnectionFailed, StreamSession, connect
from facecast.client.latency import latency_stats
from facecast.protocol import ProtocolError, Result

__all__ = [
    "MAX_CLIENTS",
    "MAX_DURATION",
    "ClientTally",
    "LoadReport",
    "motion_frames",
    "run_load",
    "write_histogram",
]

#: Upper bounds a load test accepts: it must never become an accidental flood.
MAX_CLIENTS = 1000
MAX_DURATION = 3600.0
MAX_FPS = 1000.0
#: After the last frame, how long to wait for results still in flight (a loaded machine
#: can hold the last one for seconds; what is still out then is counted ``unanswered``).
_DRAIN_SECONDS = 10.0
#: How long the sessions may take to connect before the schedule starts without them.
_CONNECT_SECONDS = 30.0
#: Frames of motion precomputed per client (cycled).
_CYCLE = 120


@dataclass
class ClientTally:
    """What one load client did."""

    sent: int = 0
    received: int = 0
    payload_bytes: int = 0
    dropped: int = 0
    #: Frames still without a result when the drain after the last frame ran out.
    unanswered: int = 0
    reconnects: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    rtts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: The most frames sent within less than one frame period: 2 when the client never
    #: catches up (a frame up to a period late, then the next one on time).
    max_burst: int = 0


@dataclass
class LoadReport:
    """The figures of one load run (``to_dict`` for JSON)."""

    url: str
    rig: str
    clients: int
    fps: float
    duration: float
    output: str
    dtype: str
    elapsed: float
    tallies: list[ClientTally]

    @property
    def rtts(self) -> np.ndarray:
        """(N,) float64 round-trip times of every client, seconds."""
        parts = [t.rtts for t in self.tallies if t.rtts.size]
        return np.concatenate(parts) if parts else np.zeros(0)

    def per_client_fps(self) -> list[float]:
        """Results received per second of sending, per client."""
        return [t.received / self.duration for t in self.tallies]

    def to_dict(self) -> dict[str, Any]:
        errors: Counter[str] = Counter()
        for t in self.tallies:
            errors.update(t.errors)
        received = sum(t.received for t in self.tallies)
        per_client = self.per_client_fps()
        payload = sum(t.payload_bytes for t in self.tallies)
        return {
            "url": self.url,
            "rig": self.rig,
            "clients": self.clients,
            "fps": self.fps,
            "duration": self.duration,
            "output": self.output,
            "dtype": self.dtype,
            "elapsed": self.elapsed,
            "sent": sum(t.sent for t in self.tallies),
            "received": received,
            "dropped": sum(t.dropped for t in self.tallies),
            "unanswered": sum(t.unanswered for t in self.tallies),
            "reconnects": sum(t.reconnects for t in self.tallies),
            "max_burst": max((t.max_burst for t in self.tallies), default=0),
            "errors": dict(sorted(errors.items())),
            "throughput_fps": received / self.elapsed if self.elapsed > 0 else 0.0,
            "payload_mb_per_s": payload / 1e6 / self.duration,
            "per_client_fps": per_client,
            "min_client_fps": min(per_client) if per_client else 0.0,
            "latency_ms": latency_stats(self.rtts).to_dict(),
        }


def motion_frames(neutral: np.ndarray, seed: int, *, amplitude: float) -> np.ndarray:
    """A cycle of small smooth motion around ``neutral`` (K, 3): (_CYCLE, K, 3) float32."""
    rng = np.random.default_rng(seed)
    k = neutral.shape[0]
    phase = rng.uniform(0, 2 * np.pi, size=(k, 3))
    t = np.arange(_CYCLE)[:, None, None] * (2 * np.pi / _CYCLE)
    return (neutral[None] + amplitude * np.sin(t + phase)).astype(np.float32)


def _code(error: BaseException) -> str:
    if isinstance(error, ProtocolError):
        return error.code_name
    if isinstance(error, ConnectionFailed):
        return "CONNECTION_FAILED"
    return type(error).__name__


async def _one_client(
    connecting: asyncio.Task[StreamSession],
    *,
    frames: np.ndarray,
    fps: float,
    count: int,
    start: asyncio.Future[float],
    stagger: float,
    tally: ClientTally,
) -> None:
    session: StreamSession | None = None
    try:
        try:
            session = await connecting
        except asyncio.CancelledError:
            if not connecting.cancelled():
                raise
            tally.errors["TIMEOUT"] += 1
            return
        origin = await start + stagger
        sender_done = asyncio.Event()

        async def sender() -> None:
            nonlocal origin
            period = 1.0 / fps
            recent: deque[float] = deque()  # send times within the last period
            try:
                for i in range(count):
                    now = time.perf_counter()
                    delay = origin + i * period - now
                    if delay > 0:
                        await asyncio.sleep(delay)
                        # The sleep itself may end late (this process was busy).
                        now = time.perf_counter()
                        delay = origin + i * period - now
                    if delay < -period:
                        # More than a frame late: go on from now at the same rate
                        # rather than send the missed frames in a burst, which the
                        # server would rightly treat as superseded.
                        origin -= delay
                    while recent and recent[0] <= now - period:
                        recent.popleft()
                    recent.append(now)
                    tally.max_burst = max(tally.max_burst, len(recent))
                    await session.send(frames[i % len(frames)])
                    tally.sent += 1
            finally:
                sender_done.set()

        task = asyncio.create_task(sender())
        try:
            while True:
                if sender_done.is_set():
                    if session.latency.in_flight == 0:
                        break
                    timeout = _DRAIN_SECONDS
                else:
                    timeout = 1.0
                try:
                    item = await session.receive(errors="return", timeout=timeout)
                except TimeoutError:
                    if sender_done.is_set():
                        break
                    continue
                if isinstance(item, Result):
                    tally.received += 1
                    tally.payload_bytes += item.values.nbytes
                else:
                    tally.errors[_code(item)] += 1
            await task
        finally:
            task.cancel()
    except (ProtocolError, ConnectionFailed, OSError) as exc:
        tally.errors[_code(exc)] += 1
    finally:
        if session is not None:
            tally.dropped = session.dropped
            tally.unanswered = session.latency.in_flight
            tally.reconnects = session.reconnects
            tally.rtts = session.latency.samples()
            await session.close()


async def run_load(
    url: str,
    rig: str,
    *,
    clients: int,
    fps: float,
    duration: float,
    neutral: np.ndarray,
    amplitude: float = 0.01,
    output: Literal["weights", "vertices", "moving"] = "weights",
    dtype: Literal["f32", "f16"] = "f32",
    token: str | None = None,
    reconnect: int = 0,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> LoadReport:
    """Run ``clients`` sessions, each sending ``fps`` frames/s for ``duration`` s.

    Parameters
    ----------
    neutral : (K, 3) float
        Points the motion is centred on (the rig's source neutral, or zeros).
    amplitude : float
        Size of the motion, in the points' units.
    progress : callable, optional
        Called about once a second with {"elapsed", "sent", "received", "errors"}.

    Every session connects first; the schedule starts once all are ready (or failed),
    so slow connections do not leave frames overdue. Frames then go on a fixed schedule
    (client i starts i/(clients*fps) s later, so sends spread evenly); a client that
    falls more than a frame behind goes on from where it is, never in a burst of
    catch-up frames.
    """
    if not 1 <= clients <= MAX_CLIENTS:
        raise ValueError(f"clients must be in 1..{MAX_CLIENTS}, got {clients}")
    if not 0 < fps <= MAX_FPS:
        raise ValueError(f"fps must be in (0, {MAX_FPS:g}], got {fps}")
    if not 0 < duration <= MAX_DURATION:
        raise ValueError(f"duration must be in (0, {MAX_DURATION:g}] s, got {duration}")
    neutral = np.asarray(neutral, dtype=np.float64)
    count = max(1, math.ceil(duration * fps))
    tallies = [ClientTally() for _ in range(clients)]

    async def opened() -> StreamSession:
        return await connect(url, rig, output=output, dtype=dtype, token=token, reconnect=reconnect)

    connecting = [asyncio.create_task(opened()) for _ in range(clients)]
    scheduled: asyncio.Future[float] = asyncio.get_running_loop().create_future()
    tasks = [
        asyncio.create_task(
            _one_client(
                connecting[i],
                frames=motion_frames(neutral, i, amplitude=amplitude),
                fps=fps,
                count=count,
                start=scheduled,
                stagger=i / (clients * fps),
                tally=tallies[i],
            )
        )
        for i in range(clients)
    ]
    _, late = await asyncio.wait(connecting, timeout=_CONNECT_SECONDS)
    for pending in late:
        pending.cancel()  # its client counts a TIMEOUT error
    start = time.perf_counter() + 0.05
    scheduled.set_result(start)
    # Hard stop: whatever happens, the run ends this long after its nominal end.
    deadline = duration + _DRAIN_SECONDS + 30.0
    all_done = asyncio.gather(*tasks)
    try:
        while not all_done.done():
            await asyncio.wait({all_done}, timeout=1.0)
            if progress is not None:
                errors = sum(sum(t.errors.values()) for t in tallies)
                progress(
                    {
                        "elapsed": time.perf_counter() - start,
                        "sent": sum(t.sent for t in tallies),
                        "received": sum(t.received for t in tallies),
                        "errors": errors,
                    }
                )
            if time.perf_counter() - start > deadline:
                for task in tasks:
                    task.cancel()
                for tally in tallies:
                    tally.errors["TIMEOUT"] += 1
                break
        await asyncio.gather(*tasks, return_exceptions=True)
    finally:
        for task in tasks:
            task.cancel()
    return LoadReport(
        url=url,
        rig=rig,
        clients=clients,
        fps=fps,
        duration=duration,
        output=output,
        dtype=dtype,
        elapsed=time.perf_counter() - start,
        tallies=tallies,
    )


def write_histogram(path: str | Path, rtts_s: np.ndarray, *, title: str) -> Path:
    """A PNG histogram of round-trip times (ms) with p50/p99 marked (matplotlib Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    ms = np.asarray(rtts_s, dtype=np.float64) * 1e3
    figure = Figure(figsize=(7, 4), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    if ms.size:
        top = float(np.percentile(ms, 99.9)) * 1.2 or 1.0
        axes.hist(np.clip(ms, 0, top), bins=60, range=(0, top), color="#4878a8")
        for q, style in ((50, "-"), (99, "--")):
            value = float(np.percentile(ms, q))
            axes.axvline(value, color="#c44e52", linestyle=style, label=f"p{q} {value:.2f} ms")
        axes.legend()
    else:
        axes.text(0.5, 0.5, "no results", ha="center", va="center", transform=axes.transAxes)
    axes.set_xlabel("round-trip latency (ms)")
    axes.set_ylabel("frames")
    axes.set_title(title)
    figure.tight_layout()
    path = Path(path)
    figure.savefig(path, format="png")
    return path

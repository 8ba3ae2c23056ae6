"""Stream a whole animation through a `StreamSession`: paced or windowed, complete at the end.

Sends every frame (in real time, or as fast as a bounded window allows), collects the
results by ``seq`` and re-requests any frame the server dropped; it never writes files.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from facecast.protocol import Result

from .latency import LatencyStats

if TYPE_CHECKING:
    from facecast.rig import Rig

    from .connection import StreamSession

__all__ = ["Progress", "StreamOutcome", "stream_frames", "weights_from_vertices"]

#: Without any result for this long, the frames in flight are taken as lost (a dropped
#: connection or a rate-limited frame never answers) and the sender moves on.
_STALL_SECONDS = 1.0
#: After the last frame is sent, how long to wait for the results still in flight.
_DRAIN_SECONDS = 5.0
#: Seconds between two progress reports.
_PROGRESS_INTERVAL = 0.25


@dataclass(frozen=True)
class Progress:
    """A live snapshot passed to the progress callback."""

    done: int
    total: int
    elapsed: float
    fps: float
    latency: LatencyStats
    dropped: int
    reconnects: int


@dataclass
class StreamOutcome:
    """What streaming an animation produced.

    Attributes
    ----------
    values : (F, M), (F, V, 3) or (output "moving") (F, N, 3) float32
        The result of every frame, in frame order.
    live : int
        Frames whose result arrived while streaming.
    rerequested : int
        Frames re-sent one at a time afterwards because no live result came.
    dropped : int
        Frames the server reported dropping.
    seconds : float
        Wall time of the live pass.
    latency : LatencyStats
    errors : dict of str to int
        Non-fatal server errors by code name.
    """

    values: np.ndarray
    live: int
    rerequested: int
    dropped: int
    seconds: float
    latency: LatencyStats
    errors: dict[str, int] = field(default_factory=dict)

    @property
    def fps(self) -> float:
        return self.live / self.seconds if self.seconds > 0 else float("nan")


class _Pacer:
    """Keeps the send rate under the server's announced limit (a client-side token bucket).

    Runs a little below the server's own bucket so frames are never dropped for rate.
    """

    def __init__(self, max_fps: float | None, burst: int | None) -> None:
        self.rate = None if not max_fps else 0.9 * float(max_fps)
        self.burst = max(1.0, float(burst or 1) / 2)
        self.tokens = self.burst
        self.last = time.perf_counter()

    async def take(self) -> None:
        if self.rate is None:
            return
        while True:
            now = time.perf_counter()
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
            self.last = now
            if self.tokens >= 1.0:
                self.tokens -= 1.0
                return
            await asyncio.sleep((1.0 - self.tokens) / self.rate)


async def stream_frames(
    session: StreamSession,
    points: np.ndarray,
    *,
    fps: float,
    realtime: bool = False,
    window: int = 2,
    progress: Callable[[Progress], None] | None = None,
) -> StreamOutcome:
    """Send every frame of ``points`` and return every frame's result.

    Parameters
    ----------
    session : StreamSession
        An open session; nothing else may read from it meanwhile.
    points : (F, K, 3) float
        The animation's feature points.
    fps : float
        The animation's frame rate; frames are paced at it with ``realtime``.
    realtime : bool
        Send frame i at i / fps seconds (frames may then be dropped by the server if it
        falls behind). Otherwise send as fast as ``window`` frames in flight allow.
    window : int
        Frames in flight at most when not real-time. The server keeps only the newest
        pending frame, so 2 (one being cloned, one waiting) is the most that can never
        be dropped in principle; if the server still reports drops, the window falls
        to 1.
    progress : callable, optional
        Called with a `Progress` a few times a second.

    Returns
    -------
    StreamOutcome
        With ``values`` complete: frames without a live result are re-requested one by
        one (request/response) at the end.
    """
    if points.ndim != 3 or points.shape[0] == 0:
        raise ValueError(f"points must be a non-empty (F, K, 3) array, got {points.shape}")
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    ready = session.ready
    assert ready is not None
    total = points.shape[0]
    shape = (ready.num_examples,) if ready.output == "weights" else (ready.result_vertices, 3)
    values = np.zeros((total, *shape), dtype=np.float32)
    have = np.zeros(total, dtype=bool)
    errors: Counter[str] = Counter()
    base = session.next_seq
    last_seq = base + total - 1
    state = {"sent": base - 1, "done": base - 1, "window": window}
    moved = asyncio.Event()
    pacer = _Pacer(ready.limits.get("max_fps"), int(ready.limits.get("rate_burst", 1)))
    dropped_at_start = session.dropped
    start = time.perf_counter()

    async def sender() -> None:
        for i in range(total):
            if realtime:
                delay = start + i / fps - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
            else:
                while state["sent"] - state["done"] >= state["window"]:
                    moved.clear()
                    reconnects = session.reconnects
                    try:
                        async with asyncio.timeout(_STALL_SECONDS):
                            await moved.wait()
                    except TimeoutError:
                        state["done"] = state["sent"]  # in flight and never answered: lost
                    if session.reconnects != reconnects:
                        state["done"] = state["sent"]
            await pacer.take()
            state["sent"] = await session.send(points[i], seq=base + i)

    def report(now: float) -> None:
        if progress is None:
            return
        elapsed = now - start
        done = int(have.sum())
        progress(
            Progress(
                done=done,
                total=total,
                elapsed=elapsed,
                fps=done / elapsed if elapsed > 0 else 0.0,
                latency=session.latency.stats(),
                dropped=session.dropped - dropped_at_start,
                reconnects=session.reconnects,
            )
        )

    send_task = asyncio.create_task(sender())
    last_report = 0.0
    try:
        while state["done"] < last_seq:
            timeout = _DRAIN_SECONDS if send_task.done() else _STALL_SECONDS
            if send_task.done() and send_task.exception() is not None:
                raise send_task.exception()  # type: ignore[misc]
            try:
                item = await session.receive(errors="return", timeout=timeout)
            except TimeoutError:
                if send_task.done():
                    break
                continue
            if isinstance(item, Result):
                index = item.seq - base
                if 0 <= index < total:
                    values[index] = item.values
                    have[index] = True
                state["done"] = max(state["done"], item.seq)
                if session.dropped > dropped_at_start and not realtime:
                    state["window"] = 1
            else:
                errors[item.code_name] += 1
                if item.seq is not None:
                    state["done"] = max(state["done"], item.seq)
            moved.set()
            now = time.perf_counter()
            if now - last_report >= _PROGRESS_INTERVAL:
                last_report = now
                report(now)
        await send_task
    finally:
        if not send_task.done():
            send_task.cancel()
    seconds = time.perf_counter() - start
    live = int(have.sum())
    report(time.perf_counter())
    latency = session.latency.stats()
    dropped = session.dropped - dropped_at_start
    for missing in np.flatnonzero(~have):
        result = await session.clone(points[missing])
        values[missing] = result.values
    return StreamOutcome(
        values=values,
        live=live,
        rerequested=total - live,
        dropped=dropped,
        seconds=seconds,
        latency=latency,
        errors=dict(errors),
    )


def weights_from_vertices(rig: Rig, vertices: np.ndarray) -> np.ndarray:
    """Blend weights reproducing cloned vertices (least squares on the rig's deltas).

    Used to write animation formats that store weights (.glb) from a ``vertices``
    session; exact up to float rounding because the server's vertices are a blend.

    Parameters
    ----------
    rig : Rig
    vertices : (F, V, 3) float

    Returns
    -------
    (F, M) float64, each row summing to 1 (``w_0 = 1 - sum(w_1..)``, eq. 3.14's convention).
    """
    basis = np.asarray(rig.blend_basis, dtype=np.float64)
    deltas = basis[1:]  # (M-1, 3V)
    frames = vertices.shape[0]
    offsets = vertices.reshape(frames, -1).astype(np.float64) - basis[0]
    gram = deltas @ deltas.T
    rest = np.linalg.lstsq(gram, deltas @ offsets.T, rcond=None)[0].T  # (F, M-1)
    weights = np.empty((frames, rig.num_examples))
    weights[:, 1:] = rest
    weights[:, 0] = 1.0 - rest.sum(axis=1)
    return weights

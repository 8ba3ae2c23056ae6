"""Per-frame round-trip latency: send time by sequence number in, RTT percentiles out.

Bounded in memory however long a stream runs (frames never answered are forgotten after
``max_pending``; samples past ``max_samples`` are reservoir-sampled); no I/O here.
"""

from __future__ import annotations

import random
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["LatencyStats", "LatencyTracker", "latency_stats"]


@dataclass(frozen=True)
class LatencyStats:
    """Round-trip times in milliseconds over ``count`` answered frames (NaN when none)."""

    count: int
    mean_ms: float
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float

    def to_dict(self) -> dict[str, float | int | None]:
        """JSON-able, with NaN written as None."""
        return {
            k: (None if isinstance(v, float) and v != v else v) for k, v in asdict(self).items()
        }

    def __str__(self) -> str:
        if not self.count:
            return "no samples"
        return (
            f"p50 {self.p50_ms:.2f} ms  p95 {self.p95_ms:.2f} ms  p99 {self.p99_ms:.2f} ms  "
            f"max {self.max_ms:.2f} ms  (n={self.count})"
        )


def latency_stats(rtts_s: np.ndarray | list[float], *, count: int | None = None) -> LatencyStats:
    """Percentiles of round-trip times given in seconds.

    Parameters
    ----------
    rtts_s : (N,) float
        Round-trip times, seconds (all of them, or a uniform sample).
    count : int, optional
        How many frames the sample stands for (default N).
    """
    x = np.asarray(rtts_s, dtype=np.float64) * 1e3
    if x.size == 0:
        nan = float("nan")
        return LatencyStats(0, nan, nan, nan, nan, nan)
    p50, p95, p99 = np.percentile(x, [50, 95, 99])
    return LatencyStats(
        count=int(x.size if count is None else count),
        mean_ms=float(x.mean()),
        p50_ms=float(p50),
        p95_ms=float(p95),
        p99_ms=float(p99),
        max_ms=float(x.max()),
    )


class LatencyTracker:
    """Match results to the frames that caused them by ``seq`` and keep the RTTs.

    Parameters
    ----------
    max_pending : int
        Send times remembered at most; the oldest are forgotten first (frames the server
        dropped under its newest-frame policy never get a result).
    max_samples : int
        RTT samples kept; beyond that a uniform reservoir sample, so percentiles stay
        unbiased while memory stays fixed. ``count`` and ``max`` stay exact.
    """

    def __init__(self, *, max_pending: int = 4096, max_samples: int = 200_000) -> None:
        self.max_pending = max_pending
        self.max_samples = max_samples
        self._sent: OrderedDict[int, float] = OrderedDict()
        self._samples: list[float] = []
        self._count = 0
        self._max = 0.0
        self._rng = random.Random(0)
        #: RTT of the most recent answered frame, seconds (None before the first).
        self.last: float | None = None

    def sent(self, seq: int, when: float | None = None) -> None:
        """Remember that frame ``seq`` left at ``when`` (``time.perf_counter()`` by default)."""
        self._sent[seq] = time.perf_counter() if when is None else when
        self._sent.move_to_end(seq)
        while len(self._sent) > self.max_pending:
            self._sent.popitem(last=False)

    def received(self, seq: int, when: float | None = None) -> float | None:
        """Record the result of frame ``seq``; its RTT in seconds, or None if unknown.

        Results arrive in ``seq`` order, so frames sent before ``seq`` and still unanswered
        were dropped: they are forgotten here too.
        """
        now = time.perf_counter() if when is None else when
        start = self._sent.pop(seq, None)
        while self._sent:
            first = next(iter(self._sent))
            if first >= seq:
                break
            del self._sent[first]
        if start is None:
            return None
        rtt = now - start
        self._add(rtt)
        return rtt

    def forget(self) -> int:
        """Forget every frame in flight (the connection was lost); how many there were."""
        n = len(self._sent)
        self._sent.clear()
        return n

    @property
    def in_flight(self) -> int:
        """Frames sent and neither answered nor known to be dropped."""
        return len(self._sent)

    def _add(self, rtt: float) -> None:
        self._count += 1
        self.last = rtt
        self._max = max(self._max, rtt)
        if len(self._samples) < self.max_samples:
            self._samples.append(rtt)
        else:
            j = self._rng.randrange(self._count)
            if j < self.max_samples:
                self._samples[j] = rtt

    def samples(self) -> np.ndarray:
        """(N,) float64 RTT samples, seconds."""
        return np.asarray(self._samples, dtype=np.float64)

    def stats(self) -> LatencyStats:
        """Percentiles over everything answered so far."""
        stats = latency_stats(self._samples, count=self._count)
        if self._count:
            stats = LatencyStats(
                stats.count,
                stats.mean_ms,
                stats.p50_ms,
                stats.p95_ms,
                stats.p99_ms,
                self._max * 1e3,
            )
        return stats

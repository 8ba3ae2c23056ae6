"""Where a stream frame's server time goes: seconds per stage, summed, and blend batch sizes.

Plain float sums updated on the event loop (a clock read and two additions a stage),
read by ``/metrics`` through a Prometheus collector; it times nothing by itself. Stages
are timed on `CPU_CLOCK`, the CPU time of the thread doing the work, so that a busy
machine (other processes taking the core) does not inflate them as wall time would.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily
from prometheus_client.registry import Collector

__all__ = ["CPU_CLOCK", "STAGES", "StageCollector", "StageTimes"]

#: A frame's way through the server (SERVER.md, "Where the time goes"): decode the
#: message, compute the weights, blend the vertices, cast them to f16, encode the
#: result, write it to the socket.
STAGES = ("decode", "weights", "blend", "cast", "encode", "write")
#: The clock of every stage: this thread's CPU seconds (``CLOCK_THREAD_CPUTIME_ID``, ns
#: resolution, ~0.4 µs a read against 0.06 µs for ``perf_counter``: stage timing is off
#: by default). A send that suspends (the ASGI path waiting for a client that does not
#: read) counts what the loop ran meanwhile, as wall time would.
CPU_CLOCK = time.thread_time


class StageTimes:
    """Seconds spent and items passed per stage, and frames per blend batch.

    Used on the event loop only (worker threads return their timings to it), so needs
    no lock.
    """

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self.items = dict.fromkeys(STAGES, 0)
        #: Batches run by ``blending.BlendBatcher``, by their number of frames.
        self.batch_sizes: Counter[int] = Counter()

    def add(self, stage: str, seconds: float, items: int = 1) -> None:
        """Count ``items`` frames through ``stage`` that took ``seconds`` together."""
        self.seconds[stage] += seconds
        self.items[stage] += items


class StageCollector(Collector):
    """``facecast_stage_seconds`` / ``facecast_stage_items`` by stage, and batch sizes."""

    def __init__(self, times: StageTimes) -> None:
        self.times = times

    def collect(self) -> Iterator[CounterMetricFamily]:
        seconds = CounterMetricFamily(
            "facecast_stage_seconds", "Server time spent per frame stage", labels=["stage"]
        )
        items = CounterMetricFamily(
            "facecast_stage_items", "Frames (or results) through each stage", labels=["stage"]
        )
        for stage in STAGES:
            seconds.add_metric([stage], self.times.seconds[stage])
            items.add_metric([stage], self.times.items[stage])
        batches = CounterMetricFamily(
            "facecast_blend_batches", "Pooled vertex blend batches by frames", labels=["frames"]
        )
        for size, count in sorted(self.times.batch_sizes.items()):
            batches.add_metric([str(size)], count)
        yield seconds
        yield items
        yield batches

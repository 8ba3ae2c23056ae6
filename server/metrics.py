"""Prometheus metrics of one app instance: the collectors and the ``/metrics`` payload.

Each ``create_app`` gets its own registry so tests can build many apps. With several
worker processes the runner sets ``PROMETHEUS_MULTIPROC_DIR`` and ``/metrics`` sums all.
"""

from __future__ import annotations

import bisect
import os
import threading
from typing import TYPE_CHECKING

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    multiprocess,
)
from prometheus_client.metrics_core import HistogramMetricFamily
from prometheus_client.registry import Collector

from .compute.stages import StageCollector, StageTimes

if TYPE_CHECKING:
    from collections.abc import Iterator

__all__ = ["CONTENT_TYPE_LATEST", "LoopCounter", "LoopHistogram", "Metrics"]

#: Increments a `LoopCounter` adds up before it pushes them to its Prometheus counter:
#: a push takes the counter's lock (~0.5 µs), once per result otherwise.
_PUSH_EVERY = 64

_LATENCY_BUCKETS = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    1.0,
)


class Metrics:
    """The server's collectors. Names are part of the ops contract; keep them stable."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.multiprocess = bool(os.environ.get("PROMETHEUS_MULTIPROC_DIR"))
        r = self.registry
        self.connections = Gauge(
            "facecast_connections",
            "Open streaming sessions",
            registry=r,
            multiprocess_mode="livesum",
        )
        # Counted once per frame on the stream path: pushed in batches (exact on scrape).
        push_every = 1 if self.multiprocess else _PUSH_EVERY
        self.frames_in = LoopCounter(
            Counter("facecast_frames_in", "Frame messages received from clients", registry=r),
            push_every,
        )
        self.frames_out = LoopCounter(
            Counter("facecast_frames_out", "Result messages sent", registry=r), push_every
        )
        self.frames_dropped = Counter(
            "facecast_frames_dropped",
            "Frames received but never cloned",
            ["reason"],
            registry=r,
        )
        processing = (
            "facecast_processing_seconds",
            "Time from a frame's arrival to its result being handed to the socket",
        )
        #: Observed once per result, on the loop; ``observe(seconds)``.
        self.processing_seconds: Histogram | LoopHistogram
        if self.multiprocess:
            # Another worker's scrape reads this process's histogram from its files.
            self.processing_seconds = Histogram(*processing, buckets=_LATENCY_BUCKETS, registry=r)
        else:
            self.processing_seconds = LoopHistogram(*processing, _LATENCY_BUCKETS)
            r.register(self.processing_seconds)
        self.errors = Counter(
            "facecast_errors", "Protocol error messages sent, by code", ["code"], registry=r
        )
        #: Per-stage time of stream frames (``stages``), exported on scrape.
        self.stages = StageTimes()
        r.register(StageCollector(self.stages))
        self.http_requests = Counter(
            "facecast_http_requests",
            "HTTP requests served",
            ["method", "route", "status"],
            registry=r,
        )

    def render(self) -> bytes:
        """The text exposition of this process, or of all workers in multiprocess mode."""
        self.frames_in.push()
        self.frames_out.push()
        if self.multiprocess:
            combined = CollectorRegistry()
            # prometheus_client leaves MultiProcessCollector unannotated.
            multiprocess.MultiProcessCollector(combined)  # type: ignore[no-untyped-call]
            return generate_latest(combined)
        return generate_latest(self.registry)


class LoopCounter:
    """A Prometheus counter incremented by one thread (the event loop), pushed in batches.

    ``inc`` adds to a plain int and pushes to ``counter`` every ``push_every`` counts;
    ``push`` (any thread: ``render`` runs in a worker thread) pushes what is left, so a
    scrape of this process is exact. In multiprocess mode ``push_every`` is 1: another
    worker's scrape reads the counter's file, and cannot push this process's counts.
    """

    def __init__(self, counter: Counter, push_every: int) -> None:
        self.counter = counter
        self.push_every = push_every
        self._counted = 0  # written by the incrementing thread only
        self._pushed = 0  # written under _lock only
        self._lock = threading.Lock()

    def inc(self, amount: int = 1) -> None:
        """Count ``amount`` (>= 0) more; from the incrementing thread only."""
        self._counted += amount
        if self._counted - self._pushed >= self.push_every:
            self.push()

    def push(self) -> None:
        """Add what was counted since the last push to the Prometheus counter."""
        with self._lock:
            counted = self._counted  # one read: the loop may count on meanwhile
            if counted != self._pushed:
                self.counter.inc(counted - self._pushed)
                self._pushed = counted


class LoopHistogram(Collector):
    """A Prometheus histogram observed by one thread (the event loop), in plain ints.

    prometheus-client's ``Histogram.observe`` takes two locks (~1 µs, once per result);
    here an observation is a bisect and two additions, and a scrape (any thread) reads
    the counts as they are. One process only: in multiprocess mode `Metrics` keeps
    prometheus-client's own, whose files the other workers read.
    """

    def __init__(self, name: str, documentation: str, buckets: tuple[float, ...]) -> None:
        self.name = name
        self.documentation = documentation
        self.bounds = tuple(float(b) for b in buckets)
        self._counts = [0] * (len(self.bounds) + 1)  # the last: above every bound (+Inf)
        self._sum = 0.0

    def observe(self, amount: float) -> None:
        """Count one observation of ``amount`` (from the observing thread only)."""
        self._counts[bisect.bisect_left(self.bounds, amount)] += 1
        self._sum += amount

    def collect(self) -> Iterator[HistogramMetricFamily]:
        counts, total = list(self._counts), self._sum  # one read each: the loop goes on
        cumulative, running = [], 0
        for bound, count in zip((*self.bounds, float("inf")), counts, strict=True):
            running += count
            # ``le`` as prometheus-client writes it ("0.001", "+Inf").
            cumulative.append(("+Inf" if bound == float("inf") else repr(bound), running))
        yield HistogramMetricFamily(
            self.name,
            self.documentation,
            buckets=cumulative,
            sum_value=total,
        )

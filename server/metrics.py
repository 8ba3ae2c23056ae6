"""Prometheus metrics of one app instance: the collectors and the ``/metrics`` payload.

Each ``create_app`` gets its own registry so tests can build many apps. With several
worker processes the runner sets ``PROMETHEUS_MULTIPROC_DIR`` and ``/metrics`` sums all.
"""

from __future__ import annotations

import os

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    multiprocess,
)

from .stages import StageCollector, StageTimes

__all__ = ["CONTENT_TYPE_LATEST", "Metrics"]

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
        self.frames_in = Counter(
            "facecast_frames_in", "Frame messages received from clients", registry=r
        )
        self.frames_out = Counter("facecast_frames_out", "Result messages sent", registry=r)
        self.frames_dropped = Counter(
            "facecast_frames_dropped",
            "Frames received but never cloned",
            ["reason"],
            registry=r,
        )
        self.processing_seconds = Histogram(
            "facecast_processing_seconds",
            "Time from a frame's arrival to its result being handed to the socket",
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
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
        if self.multiprocess:
            combined = CollectorRegistry()
            multiprocess.MultiProcessCollector(combined)
            return generate_latest(combined)
        return generate_latest(self.registry)

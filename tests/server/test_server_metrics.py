"""Batched stream counters and the loop histogram: exact on every scrape, as prometheus-client's."""

from __future__ import annotations

import threading

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest

from facecast.server.metrics import LoopCounter, LoopHistogram, Metrics


def _total(metrics: Metrics, name: str) -> float:
    for line in metrics.render().decode().splitlines():
        if line.startswith(f"{name}_total "):
            return float(line.split()[1])
    raise AssertionError(f"{name}_total not in /metrics")


def test_a_scrape_shows_every_count_even_below_a_batch():
    metrics = Metrics()

    metrics.frames_in.inc()
    metrics.frames_out.inc(3)

    assert _total(metrics, "facecast_frames_in") == 1.0
    assert _total(metrics, "facecast_frames_out") == 3.0


def test_counts_reach_the_counter_every_batch_without_a_scrape():
    registry = CollectorRegistry()
    batched = LoopCounter(Counter("c", "c", registry=registry), push_every=8)

    for _ in range(7):
        batched.inc()
    before = registry.get_sample_value("c_total")
    batched.inc()

    assert (before, registry.get_sample_value("c_total")) == (0.0, 8.0)


def test_pushes_from_another_thread_lose_no_count():
    registry = CollectorRegistry()
    batched = LoopCounter(Counter("c", "c", registry=registry), push_every=5)
    done = threading.Event()

    def scrape() -> None:
        while not done.is_set():
            batched.push()

    scraper = threading.Thread(target=scrape)
    scraper.start()
    try:
        for _ in range(200_000):
            batched.inc()
    finally:
        done.set()
        scraper.join()
    batched.push()

    assert registry.get_sample_value("c_total") == 200_000


def test_the_loop_histogram_exposes_what_prometheus_clients_histogram_does():
    buckets = (0.0001, 0.001, 0.01, 1.0)
    theirs_registry, ours_registry = CollectorRegistry(), CollectorRegistry()
    theirs = Histogram("h_seconds", "doc", buckets=buckets, registry=theirs_registry)
    ours = LoopHistogram("h_seconds", "doc", buckets)
    ours_registry.register(ours)
    # Values on the bounds (a bucket counts values <= its bound), between and above them.
    for value in (0.0, 0.00005, 0.0001, 0.0005, 0.001, 0.01, 0.5, 1.0, 3.0, 0.001):
        theirs.observe(value)
        ours.observe(value)

    def samples(registry: CollectorRegistry) -> list[str]:
        return [
            line
            for line in generate_latest(registry).decode().splitlines()
            if line.startswith("h_seconds") and "_created" not in line
        ]

    assert samples(ours_registry) == samples(theirs_registry)
    assert ours_registry.get_sample_value("h_seconds_count") == 10.0

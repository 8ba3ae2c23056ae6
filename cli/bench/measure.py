"""What the benchmarks read from outside a server: processes' CPU time and its stage clocks.

Reads /proc and ``/metrics``; starts nothing and judges nothing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import httpx
from prometheus_client.parser import text_string_to_metric_families

__all__ = ["STAGES", "cpu_seconds", "stage_delta", "stage_snapshot"]

#: The server's stages (``facecast.server.compute.stages.STAGES``, read off ``/metrics`` by name
#: so the benchmarks never import the server).
STAGES = ("decode", "weights", "blend", "cast", "encode", "write")


def cpu_seconds(pids: list[int]) -> float:
    """CPU time of processes ``pids`` (Linux /proc; NaN elsewhere).

    The scheduler's nanosecond run time of each live thread (``task/*/schedstat``) where
    the kernel keeps it: /proc's user + system time counts 10 ms ticks, and a short step
    of a few viewers costs the bare floor less than one (it read 0 and the step had no
    ratio). Else those ticks (which also count threads that have ended).
    """
    total = 0.0
    for pid in pids:
        try:
            total += _run_time(pid)
        except OSError:
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                return float("nan")
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _run_time(pid: int) -> float:
    """Seconds the threads of ``pid`` have run (schedstat); OSError where there is none."""
    nanoseconds, read = 0, 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            nanoseconds += int((task / "schedstat").read_text().split()[0])
        except FileNotFoundError:  # a thread that ended meanwhile, or no schedstat at all
            continue
        read += 1
    if not read:
        raise FileNotFoundError(f"no schedstat for process {pid}")
    return nanoseconds / 1e9


def stage_snapshot(base_url: str) -> dict[str, Any]:
    """The server's stage clocks and blend batch counts from ``GET /metrics``."""

    text = httpx.get(f"{base_url}/metrics", timeout=10).text
    seconds = dict.fromkeys(STAGES, 0.0)
    items = dict.fromkeys(STAGES, 0.0)
    batches: dict[int, float] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name == "facecast_stage_seconds_total":
                seconds[sample.labels["stage"]] = sample.value
            elif sample.name == "facecast_stage_items_total":
                items[sample.labels["stage"]] = sample.value
            elif sample.name == "facecast_blend_batches_total":
                batches[int(sample.labels["frames"])] = sample.value
    return {"seconds": seconds, "items": items, "batches": batches}


def stage_delta(before: dict[str, Any], after: dict[str, Any], results: int) -> dict[str, Any]:
    """Per-result server µs in each stage between two snapshots, and the batch sizes.

    A stage's time is divided by ``results`` (the results delivered meanwhile), so the
    stages add up to the server's time per delivered result; ``per_item_us`` divides by
    the stage's own count instead (a frame dropped before blending has no blend).
    """
    per_result = {}
    per_item = {}
    for stage in STAGES:
        spent = after["seconds"][stage] - before["seconds"][stage]
        count = after["items"][stage] - before["items"][stage]
        per_result[stage] = round(spent / results * 1e6, 2) if results else None
        per_item[stage] = round(spent / count * 1e6, 2) if count else None
    batches = {
        size: after["batches"][size] - before["batches"].get(size, 0.0)
        for size in after["batches"]
        if after["batches"][size] > before["batches"].get(size, 0.0)
    }
    frames = sum(size * count for size, count in batches.items())
    count = sum(batches.values())
    known = [v for v in per_result.values() if v is not None]
    return {
        "per_result_us": per_result,
        "per_item_us": per_item,
        "total_us": round(sum(known), 2) if known else None,
        "blend_batches": {str(size): int(n) for size, n in sorted(batches.items())},
        "mean_batch_frames": round(frames / count, 2) if count else None,
    }

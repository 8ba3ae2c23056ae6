"""``bench transport``'s text: the per-stage line says what it measured, never a bare "-"."""

from __future__ import annotations

from facecast.cli.bench.transport_report import load_line


def _figures(output: str, mean_batch_frames: float | None) -> dict:
    return {
        "clients": 4, "output": output, "min_client_fps": 59.0, "dropped": 0,
        "latency_ms": {"p99_ms": 3.0}, "errors": 0, "server_cpu_cores": 0.5,
        "server_cpu_us_per_result": 120.0, "client_cpu_cores": 0.4,
        "client_cpu_us_per_result": 90.0, "held": True,
        "stages": {"per_result_us": {"decode": 10.0, "weights": 30.0},
                   "mean_batch_frames": mean_batch_frames},
    }  # fmt: skip


def test_a_run_without_blends_says_so():
    text = load_line("weights", _figures("weights", None))

    assert "no blends (weights output: nothing blended on the server)" in text
    assert "batches of -" not in text


def test_a_run_with_blends_gives_the_mean_batch():
    text = load_line("vertices", _figures("vertices", 2.5))

    assert "blend batches of 2.5 frames on average" in text

"""``facecast loadtest`` and ``facecast bench transport`` against real servers (no timing asserts)."""

from __future__ import annotations

import argparse
import json
import math

import pytest

from facecast.cli.main import main
from facecast.rig.sources.ict import locate_ict

from ._stream_fixtures import RIG_ID, demo_rig, live_server, rigs_dir

__all__ = ["demo_rig", "live_server", "rigs_dir"]  # fixtures used by name

REPORT_KEYS = {
    "clients", "fps", "duration", "sent", "received", "dropped", "errors", "throughput_fps",
    "per_client_fps", "min_client_fps", "latency_ms", "payload_mb_per_s",
}  # fmt: skip
LATENCY_KEYS = {"count", "p50_ms", "p95_ms", "p99_ms", "max_ms", "mean_ms"}


def test_loadtest_writes_a_json_report_and_a_png_histogram(live_server, tmp_path):
    report_path, png_path = tmp_path / "load.json", tmp_path / "load.png"

    status = main(
        [
            "loadtest", live_server.base_url, "--rig", RIG_ID, "--clients", "3", "--fps", "30",
            "--duration", "1.5", "--json", str(report_path), "--png", str(png_path), "-q",
        ]
    )  # fmt: skip

    assert status == 0
    report = json.loads(report_path.read_text())
    assert report.keys() >= REPORT_KEYS
    assert report["latency_ms"].keys() >= LATENCY_KEYS
    assert report["clients"] == 3
    assert len(report["per_client_fps"]) == 3
    assert report["sent"] == 3 * 45
    assert 0 < report["received"] <= report["sent"]
    assert report["errors"] == {}
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_loadtest_refuses_more_clients_than_its_bound(live_server, capsys):
    status = main(["loadtest", live_server.base_url, "--rig", RIG_ID, "--clients", "100000"])

    assert status == 2
    assert "--clients" in capsys.readouterr().err


def test_loadtest_against_an_unreachable_server_exits_2(capsys):
    from facecast.server.testing import free_port

    status = main(
        ["loadtest", f"http://127.0.0.1:{free_port()}", "--rig", RIG_ID, "--duration", "1"]
    )

    assert status == 2
    assert "cannot reach the server" in capsys.readouterr().err


@pytest.mark.parametrize(
    "vertices_rig",
    [
        # As on a machine without ICT-FaceKit (a fresh checkout): every phase on the demo rig.
        "demo",
        # The default wherever ICT-FaceKit is (CI): the vertices phases on ICT's rigs.
        pytest.param(
            "ict",
            marks=[
                pytest.mark.ict,
                pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found"),
            ],
        ),
    ],
)
def test_bench_transport_smoke_writes_its_json_keys(tmp_path, monkeypatch, vertices_rig):
    from facecast.cli.bench import transport

    out = tmp_path / "transport.json"
    if vertices_rig == "demo":
        monkeypatch.setattr(transport, "locate_ict", lambda: None)

    status = transport.run(
        # The warm-ups too as short as the phases (2 s each, 3 of them, by default).
        argparse.Namespace(
            json=str(out), duration=0.3, clients=2, max_streams=3, warmup_seconds=0.3
        )
    )

    assert status == 0
    figures = json.loads(out.read_text())
    assert {"rtt_p50_ms", "throughput_msgs_per_s", "ratios", "goals", "vertices"} <= figures.keys()
    assert set(figures["rtt_p50_ms"]) == {"websockets", "fastapi", "facecast"}
    assert {"rtt_pass", "throughput_pass", "vertices_pass"} <= figures["goals"].keys()
    assert {"min_client_fps", "mb_per_s", "latency_ms", "pass"} <= figures["vertices"].keys()
    assert figures["vertices"]["rig"] == vertices_rig
    assert figures["vertices"]["received"] > 0 and not figures["vertices"]["errors"]
    # The server path is driven by the bare client; the library's round trip is apart.
    assert figures["library_client"]["rtt_ms"]["count"] > 0
    assert isinstance(figures["servers"]["facecast"]["pipelined_dropped"], int)
    # Attributed: CPU of every server (the scheduler's nanosecond run time, which every
    # message adds to: never 0 on Linux), facecast's time by stage, floors of the same run.
    for name in ("websockets", "fastapi", "facecast"):
        assert 0 < figures["servers"][name]["server_cpu_us_per_message"] < math.inf
    assert figures["weights_stages"]["per_result_us"]["weights"] > 0
    assert set(figures["whole_mesh"]) == {"exact", "bounded"}
    moving = figures["moving"]
    assert [step["clients"] for step in moving["ramp"]["steps"]][:1] == [2]
    assert moving["ramp"]["steps"][0]["stages"]["per_result_us"]["blend"] > 0
    assert math.isfinite(moving["floor"]["steps"][0]["server_cpu_us_per_result"])
    assert moving["floor"]["steps"][0]["received"] > 0
    whole_floor = figures["whole_mesh_floor"]  # the bare server answers the whole mesh
    assert whole_floor["output"] == "vertices" and whole_floor["received"] > 0
    assert moving["blend_floor_us"]["single_us"] > 0
    assert 0 < moving["moving_vertices"] <= moving["num_vertices"]


def test_a_client_that_falls_behind_never_sends_a_catch_up_burst(rigs_dir, demo_rig):
    # The client's own send times are judged (max_burst), not the server's rate limit:
    # arrivals bunch whenever the server process is descheduled, which says nothing
    # about the client. A busy loop of two frame periods makes a sender that only
    # judges lateness before it sleeps send 3 frames within one period (the late one,
    # the next one, then one on time); one of 0.25 s misses 7 frames.
    import asyncio
    import time

    from facecast.cli.loadgen import run_load

    from ._stream_fixtures import LiveServer, server_settings

    fps = 30.0
    stalls = [2 / fps, 0.25]
    sent_at_stall = []

    def stall_the_loop(progress: dict) -> None:
        # Called on the load's own loop about once a second while the frames go out.
        if stalls:
            sent_at_stall.append(progress["sent"])
            time.sleep(stalls.pop(0))  # this process is busy (blocks on purpose)

    server = LiveServer(server_settings(rigs_dir)).start()
    try:
        load = run_load(
            server.base_url, RIG_ID, clients=2, fps=fps, duration=3.0,
            neutral=demo_rig.source_neutral, progress=stall_the_loop,
        )  # fmt: skip
        report = asyncio.run(load).to_dict()
    finally:
        server.stop()

    assert len(sent_at_stall) == 2 and 0 < min(sent_at_stall) <= max(sent_at_stall) < 2 * 90
    assert report["sent"] == 2 * 90
    assert report["max_burst"] <= 2
    assert report["errors"] == {}
    assert report["received"] + report["dropped"] == report["sent"]

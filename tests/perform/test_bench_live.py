"""``facecast bench live`` end to end: a rendered ICT face as Chromium's fake camera, a real
server, /perform and viewer pages; the JSON holds every figure the issue names."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from facecast.cli.main import main

from .conftest import ICT_TRACKING

pytestmark = ICT_TRACKING


def test_bench_live_reports_each_stage_and_capture_to_drawn_beside_its_floor(tmp_path):
    out = tmp_path / "live.json"

    # Its own process, as a user runs it: Playwright's sync API refuses to start inside the
    # asyncio loop that this package's browser fixture leaves running in the test process.
    run = subprocess.run(
        [sys.executable, "-m", "facecast.cli", "bench", "live", "--viewers", "2",
         "--duration", "4", "--page", "overlay", "--window", "320x180",
         "--video", str(tmp_path / "camera.y4m"),
         "--json", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]

    report = json.loads(out.read_text())
    glass = report["glass_to_glass_ms"]
    assert report["viewers"] == 2 and report["page"] == "overlay"
    assert report["window"] == [320, 180]
    assert glass["n"] > 0 and 0 < glass["p50"] <= glass["p95"] <= glass["p99"] < 10_000
    parts = report["floor_parts_ms"]
    assert report["floor_ms"] == pytest.approx(parts["model"] + parts["hop"] + parts["draw"])
    assert parts["model"] > 0 and parts["hop"] > 0 and parts["hop_samples"] > 20
    assert set(report["stages"]) == {"track", "publish", "uplink", "server", "downlink", "draw"}
    assert all(stage["n"] > 0 for stage in report["stages"].values())
    assert report["fps"]["tracked"] > 0 and report["fps"]["drawn"] > 0
    # Frames a viewer never got (the server keeps the newest for a slow one): a count per
    # viewer within what was published.
    published = report["fps"]["published"] * report["seconds"]
    assert 0 <= report["lost"]["server_to_viewer"] <= published
    assert report["capture_source"] in ("frame timestamp", "video metadata")


def test_bench_live_refuses_no_viewers_with_a_clear_error(capsys):
    assert main(["bench", "live", "--viewers", "0"]) != 0
    assert "--viewers must be ≥ 1" in capsys.readouterr().err


@pytest.mark.parametrize("window", ["320", "0x100", "320x180x2", "5000x100"])
def test_bench_live_refuses_a_window_size_out_of_range(window, capsys):
    with pytest.raises(SystemExit) as exited:
        main(["bench", "live", "--window", window])
    assert exited.value.code == 2
    assert "--window" in capsys.readouterr().err

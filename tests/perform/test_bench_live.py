"""``facecast bench live`` end to end: a face as Chromium's fake camera, a real server,
/perform and viewer pages; the JSON holds every figure the issue names.

The camera is the tests' own moving photo (``facevideo``), given with ``--video``: the
bench's own rendered ICT face (120 frames, each drawn in numpy) is checked on its own, on a
few frames, by the last test."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from facecast.cli.bench import live
from facecast.cli.main import main
from facecast.cli.y4m import open_y4m

from .conftest import ICT_ARCHIVE, ICT_TRACKING, FacePose, write_y4m

pytestmark = ICT_TRACKING


def test_bench_live_reports_each_stage_and_capture_to_drawn_beside_its_floor(tmp_path):
    out = tmp_path / "live.json"
    # The mouth opening and closing twice a second, as the bench's own video does.
    mouths = 7.0 - 7.0 * np.cos(2 * np.pi * np.arange(live.VIDEO_FPS) / (live.VIDEO_FPS / 2))
    video = write_y4m(tmp_path / "camera.y4m", [FacePose(mouth=m) for m in mouths],
                      fps=live.VIDEO_FPS)  # fmt: skip

    # Its own process, as a user runs it: Playwright's sync API refuses to start inside the
    # asyncio loop that this package's browser fixture leaves running in the test process.
    run = subprocess.run(
        [sys.executable, "-m", "facecast.cli", "bench", "live", "--viewers", "2",
         "--duration", "4", "--page", "overlay", "--window", "320x180",
         "--video", str(video),
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
    # The delay the stamps cannot hold: the channel's filter (the page's auto smoothing on
    # the bench's rig, fitted exactly: one-euro), run offline at the rate the page tracked.
    lag = report["filter_lag"]
    assert lag["filter"] == "one-euro" and lag["fps"] == pytest.approx(report["fps"]["tracked"])
    assert 0 < lag["frames"] < 1


def test_bench_live_refuses_no_viewers_with_a_clear_error(capsys):
    assert main(["bench", "live", "--viewers", "0"]) != 0
    assert "--viewers must be ≥ 1" in capsys.readouterr().err


@pytest.mark.parametrize("window", ["320", "0x100", "320x180x2", "5000x100"])
def test_bench_live_refuses_a_window_size_out_of_range(window, capsys):
    with pytest.raises(SystemExit) as exited:
        main(["bench", "live", "--window", window])
    assert exited.value.code == 2
    assert "--window" in capsys.readouterr().err


def test_bench_live_renders_an_ict_face_opening_its_jaw_for_its_camera(tmp_path):
    # 4 frames of the loop: closed, half open, closed, half open (twice over).
    path = live._write_video(tmp_path / "camera.y4m", ICT_ARCHIVE, seconds=4 / live.VIDEO_FPS)

    video = open_y4m(path)
    assert video.fps == live.VIDEO_FPS and video.num_frames == 4
    lumas = [
        np.frombuffer(video.read(i), np.uint8, video.width * video.height).reshape(
            video.height, video.width).astype(int)
        for i in range(4)
    ]  # fmt: skip
    # A shaded face in the middle of the frame; the open jaw changes its lower half (1,492
    # pixels by more than 40 levels), the sway alone barely (169: its edges shift).
    h, w = lumas[0].shape
    assert np.ptp(lumas[0][h // 3 : 2 * h // 3, w // 3 : 2 * w // 3]) > 50
    opened, swayed = (np.abs(lumas[i] - lumas[0]) > 40 for i in (1, 2))
    assert opened.sum() > 5 * swayed.sum()
    assert np.argwhere(opened)[:, 0].mean() > h / 2

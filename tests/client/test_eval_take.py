"""``facecast eval --take``: a real Live Link Face take, with noise measured from it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from facecast.cli import main as cli
from facecast.rig.sources.ict import locate_ict

TAKE = Path(__file__).parents[1] / "data" / "livelink" / "llv_dao.csv"
ARCHIVE = locate_ict()


def _max_axis(entry: dict) -> float:
    return max(entry["eq41_percent"].values())


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
def test_eval_on_a_real_take_meets_the_goals_with_measured_noise(tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAST_ICT", str(ARCHIVE))
    out = tmp_path / "take.json"
    argv = ["eval", "--take", str(TAKE), "--noise", "0.05", "--kernels", "bspline"]
    code = cli.main([*argv, "--no-timing", "--estimate-noise", "--json", str(out)])
    report = json.loads(out.read_text())

    assert code == 0
    errors = report["errors"]
    # Clean input, defaults: as exact as least squares.
    assert _max_axis(errors["clean"]["rig noise=0"]) <= (
        1.01 * _max_axis(errors["clean"]["least squares"]) + 1e-4
    )
    # The noise read off the take's stillest half second: the 0.5 mm added, and a little
    # of the capture's own jitter.
    sigma = report["estimated_noise"]["sigma"]
    assert 0.05 <= sigma <= 0.06
    estimated = errors["noisy"][f"rig clamp=nonneg noise=est {sigma:.3g}"]
    assert _max_axis(estimated) <= 1.0
    assert _max_axis(estimated) < _max_axis(errors["noisy"]["nnls"])
    assert estimated["jitter_percent"] < errors["noisy"]["nnls"]["jitter_percent"]


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
@pytest.mark.parametrize(
    ("content", "message"),
    [(None, "no such file"), ("Timecode,JawOpen\n00:00:00:00,0.5\n", "no EyeBlinkLeft column")],
)
def test_eval_refuses_a_missing_or_malformed_take_with_a_message(
    tmp_path, monkeypatch, capsys, content, message
):
    monkeypatch.setenv("FACECAST_ICT", str(ARCHIVE))
    take = tmp_path / "take.csv"
    if content is not None:
        take.write_text(content)
    assert cli.main(["eval", "--take", str(take), "--no-timing"]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
def test_eval_temporal_needs_noise(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FACECAST_ICT", str(ARCHIVE))
    argv = ["eval", "--take", str(TAKE), "--noise", "0", "--temporal", "--no-timing"]
    assert cli.main([*argv, "--kernels", "bspline"]) == 2
    assert "--temporal needs --noise" in capsys.readouterr().err

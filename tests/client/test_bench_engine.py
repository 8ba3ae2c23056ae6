"""``facecast bench``: the engine benchmark's JSON, and the sub-commands' wiring."""

from __future__ import annotations

import json

import pytest

from facecast.cli import main as cli
from facecast.cli.bench import broadcast


def test_bench_engine_writes_every_figure_with_baseline_and_verdict(tmp_path, capsys):
    out = tmp_path / "bench.json"

    code = cli.main(["bench", "engine", "--demo", "--repeat", "1", "--json", str(out)])

    assert code == 0
    printed = capsys.readouterr().out
    assert "goals met" in printed
    assert "beside basis" in printed and "overlapped in two threads" in printed
    report = json.loads(out.read_text())
    assert report["dataset"] == "demo" and report["num_examples"] == 13
    assert set(report["figures"]) == {
        "weights_single", "weights_batched_per_frame", "blend_single", "fit",
        "weights_vs_rbfinterpolator", "fit_math", "fit_blend_basis",
    }  # fmt: skip
    for figure in report["figures"].values():
        assert {"value_s", "baseline_s", "baseline", "ratio", "goal", "pass"} <= set(figure)
        assert figure["value_s"] > 0 and figure["baseline_s"] > 0
    figures = report["figures"]
    # The fit's two parts stand beside their own floors.
    assert "RBFInterpolator" in figures["fit_math"]["baseline"]
    assert "copy" in figures["fit_blend_basis"]["baseline"]
    # And how the fit's wall time splits between them, built beside each other.
    split = report["fit_split"]
    assert split["overlapped"] is True
    assert 0 < split["math_s"] <= split["wall_s"] and 0 < split["basis_s"] <= split["wall_s"]


def test_bench_engine_refuses_a_zero_repeat(capsys):
    assert cli.main(["bench", "engine", "--demo", "--repeat", "0"]) == 2
    assert "--repeat" in capsys.readouterr().err


def test_bench_broadcast_takes_the_ramp_steps_given(monkeypatch):
    seen = []
    monkeypatch.setattr(broadcast, "run", lambda args: seen.append(args) or 0)

    assert cli.main(["bench", "broadcast", "--steps", "250,500", "--no-redis"]) == 0
    assert seen[0].steps == [250, 500] and seen[0].no_redis


@pytest.mark.parametrize("steps", ["0", "250,x", ""])
def test_bench_broadcast_refuses_steps_that_are_not_viewer_counts(steps, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["bench", "broadcast", "--steps", steps])
    assert info.value.code == 2
    assert "--steps" in capsys.readouterr().err

"""``facecast fit``, ``clone`` and ``eval`` end to end through ``main``, on real files."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from facecast.cli import main as cli
from facecast.cli.commands.fit import KERNEL_CHOICES
from facecast.rig import KERNELS, load_rig
from facecast.rig.sources.ict import locate_ict


@pytest.fixture(scope="module")
def demo_rig(tmp_path_factory):
    path = tmp_path_factory.mktemp("rig") / "demo.rig"
    assert cli.main(["fit", "demo", "-o", str(path)]) == 0
    return path


def test_fit_demo_writes_a_loadable_rig_and_prints_the_report(demo_rig, capsys, tmp_path):
    out = tmp_path / "again.rig"

    code = cli.main(["fit", "demo", "-o", str(out), "--noise", "0.01", "--clamp", "unit"])

    printed = capsys.readouterr().out
    assert code == 0
    assert "M = 13" in printed and "condition number" in printed and "fit time" in printed
    rig = load_rig(out)
    assert rig.num_examples == 13 and rig.model.clamp == "unit"


def test_fit_sparsity_is_stored_in_the_rig_and_printed(tmp_path, capsys):
    out = tmp_path / "sparse.rig"

    code = cli.main(
        ["fit", "demo", "-o", str(out), "--noise", "0.01", "--clamp", "nonneg", "--sparsity", "2"]
    )

    assert code == 0
    assert "sparsity prior 2" in capsys.readouterr().out
    assert load_rig(out).model.sparsity_penalty == pytest.approx(2 * 0.01**2 * 2 * 12)


def test_fit_sparsity_without_clamp_exits_2_saying_why(tmp_path, capsys):
    code = cli.main(["fit", "demo", "-o", str(tmp_path / "r.rig"), "--sparsity", "1"])

    assert code == 2
    assert "clamp" in capsys.readouterr().err


def test_fit_json_prints_the_fit_report(tmp_path, capsys):
    code = cli.main(["fit", "demo", "-o", str(tmp_path / "r.rig"), "--json"])

    payload = json.loads(capsys.readouterr().out)
    assert code == 0
    assert payload["fit_report"]["num_examples"] == 13
    assert len(payload["fit_report"]["nearest_name"]) == 13


def test_fit_prints_both_systems_condition_numbers_and_no_warning_on_the_demo(tmp_path, capsys):
    code = cli.main(["fit", "demo", "-o", str(tmp_path / "r.rig")])

    captured = capsys.readouterr()
    assert code == 0
    assert "radial system condition number" in captured.out
    assert "hyperplane system [1, p] condition number: 66" in captured.out
    assert "landmark noise that moves the weights 0.05 RMS" in captured.out
    assert "warning" not in captured.err


def test_fit_says_which_stable_points_align_uses(tmp_path, capsys):
    code = cli.main(["fit", "demo", "-o", str(tmp_path / "r.rig")])

    assert code == 0
    assert "head-pose alignment (align): on stable points 6, 7, 12, 13" in capsys.readouterr().out


def test_fit_of_a_set_without_stable_points_says_align_uses_all(tmp_path, capsys):
    from facecast.rig.demo import demo_example_set

    path = tmp_path / "set.npz"
    dataclasses.replace(demo_example_set(), stable_points=None).save_npz(path)
    code = cli.main(["fit", str(path), "-o", str(tmp_path / "r.rig")])

    assert code == 0
    assert "on all 21 feature points" in capsys.readouterr().out
    assert load_rig(tmp_path / "r.rig").stable_points is None


def test_fit_stable_points_flag_overrides_the_sets(tmp_path, capsys):
    code = cli.main(["fit", "demo", "-o", str(tmp_path / "r.rig"), "--stable-points", "0,1,2"])

    assert code == 0
    assert "on stable points 0, 1, 2" in capsys.readouterr().out
    assert load_rig(tmp_path / "r.rig").stable_points.tolist() == [0, 1, 2]


@pytest.fixture(scope="module")
def ict_npz(tmp_path_factory):
    from facecast.rig.sources.ict import ict_example_set

    path = tmp_path_factory.mktemp("ict") / "ict.npz"
    ict_example_set(locate_ict()).save_npz(path)
    return path


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_exact_fit_of_ict_warns_that_the_rig_amplifies_landmark_noise(ict_npz, tmp_path, capsys):
    code = cli.main(["fit", str(ict_npz), "-o", str(tmp_path / "ict.rig")])

    err = capsys.readouterr().err
    assert code == 0
    assert "warning: the rig amplifies landmark noise" in err
    assert "--noise SIGMA --clamp nonneg" in err


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_fit_of_ict_for_tracker_noise_does_not_warn_about_amplification(ict_npz, tmp_path, capsys):
    argv = ["fit", str(ict_npz), "-o", str(tmp_path / "ict.rig"), "--noise", "0.01"]

    code = cli.main([*argv, "--clamp", "nonneg"])

    assert code == 0
    assert "amplifies" not in capsys.readouterr().err


def test_fit_kernel_choices_match_the_engine():
    assert KERNEL_CHOICES == KERNELS


@pytest.mark.parametrize("output", ["clone.npz", "clone.glb", "frames"])
def test_clone_demo_writes_each_output_format(demo_rig, tmp_path, output):
    out = tmp_path / output

    code = cli.main(["clone", str(demo_rig), "demo", "-o", str(out), "--seconds", "0.5"])

    assert code == 0
    if output.endswith(".npz"):
        with np.load(out) as archive:
            assert archive["weights"].shape == (30, 13)
            assert archive["vertices"].shape[0] == 30
    elif output.endswith(".glb"):
        assert out.read_bytes()[:4] == b"glTF"
    else:
        assert len(list(out.glob("*.obj"))) == 30


def test_clone_of_a_saved_animation_matches_the_rig(demo_rig, tmp_path):
    rig = load_rig(demo_rig)
    points = rig.source_neutral + np.random.default_rng(0).normal(0, 0.01, (7, rig.num_points, 3))
    source = tmp_path / "perf.npz"
    np.savez(source, points=points, fps=30.0)
    out = tmp_path / "clone.npz"

    assert cli.main(["clone", str(demo_rig), str(source), "-o", str(out)]) == 0

    with np.load(out) as archive:
        np.testing.assert_allclose(archive["weights"], rig.weights(points), atol=1e-6)


def test_eval_demo_writes_json_and_plots(tmp_path, capsys):
    report_path = tmp_path / "report.json"

    code = cli.main([
        "eval", "--demo", "--seconds", "1", "--kernels", "bspline", "--json", str(report_path),
        "--plots", str(tmp_path / "plots"),
    ])  # fmt: skip

    assert code == 0
    assert "Cloning error" in capsys.readouterr().out
    report = json.loads(report_path.read_text())
    assert {"methods", "errors", "timing", "dataset"} <= set(report)
    assert (tmp_path / "plots" / "error_over_time.png").stat().st_size > 0
    assert (tmp_path / "plots" / "frames.png").stat().st_size > 0


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_eval_ict_reports_exact_clean_clones_and_the_noise_gap(tmp_path):
    report_path = tmp_path / "ict.json"

    code = cli.main([
        "eval", "--ict", "--seconds", "1", "--fps", "30", "--kernels", "bspline",
        "--no-timing", "--json", str(report_path),
    ])  # fmt: skip

    assert code == 0
    report = json.loads(report_path.read_text())
    assert report["dataset"] == "ict" and report["num_examples"] == 56
    assert report["num_vertices"] == 26719 and report["num_frames"] == 30
    clean, noisy = report["errors"]["clean"], report["errors"]["noisy"]
    assert max(clean["rig noise=0"]["eq41_percent"].values()) < 0.01
    assert (
        noisy["rig clamp=none noise=0.02"]["eq41_percent"]["y"] * 10
        < (noisy["least squares"]["eq41_percent"]["y"])
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["fit", "{tmp}/missing_set", "-o", "{tmp}/r.rig"],
        ["clone", "{tmp}/missing.rig", "demo", "-o", "{tmp}/c.npz"],
        ["eval", "{tmp}/missing_set", "{tmp}/missing_source"],
    ],
)
def test_missing_files_exit_2_naming_the_file(argv, tmp_path, capsys):
    code = cli.main([a.format(tmp=tmp_path) for a in argv])

    err = capsys.readouterr().err
    assert code == 2
    assert "missing" in err and "Traceback" not in err


def test_clone_with_a_missing_source_exits_2_naming_it(demo_rig, tmp_path, capsys):
    code = cli.main(
        ["clone", str(demo_rig), str(tmp_path / "nope.npz"), "-o", str(tmp_path / "c.npz")]
    )

    assert code == 2
    assert "nope.npz" in capsys.readouterr().err


def test_eval_of_files_with_a_truth_file_reports_errors(tmp_path, capsys):
    from facecast.rig.demo import (
        demo_activations,
        demo_animation,
        demo_example_set,
        demo_target_frames,
    )

    demo_example_set().save_npz(tmp_path / "set.npz")
    np.savez(tmp_path / "perf.npz", points=demo_animation(0.5, with_vertices=False).points)
    np.save(tmp_path / "truth.npy", demo_target_frames(demo_activations(0.5)))
    report_path = tmp_path / "r.json"

    code = cli.main([
        "eval", str(tmp_path / "set.npz"), str(tmp_path / "perf.npz"),
        "--truth", str(tmp_path / "truth.npy"), "--kernels", "bspline", "--noise", "0",
        "--no-timing", "--json", str(report_path),
    ])  # fmt: skip

    assert code == 0
    report = json.loads(report_path.read_text())
    assert set(report["errors"]) == {"clean"}
    assert report["errors"]["clean"]["rig noise=0"]["rms_percent"] < 1.0

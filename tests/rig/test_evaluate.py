"""Evaluation: eq. 4.1 and the other errors, the least-squares peers, the comparison report."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.rig import ExampleSet
from facecast.rig.errors import InputError
from facecast.rig.evaluation.evaluate import (
    cloning_error,
    default_settings,
    evaluate,
    least_squares_weights,
    nnls_weights,
)


def _linear_set(m: int = 6, k: int = 8, v: int = 40, seed: int = 0) -> ExampleSet:
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(k, 3)) + rng.normal(scale=0.3, size=(m, k, 3)) * (
        np.arange(m)[:, None, None] > 0
    )
    target = (
        rng.normal(size=(v, 3))
        + 5.0
        + rng.normal(scale=0.3, size=(m, v, 3)) * (np.arange(m)[:, None, None] > 0)
    )
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    return ExampleSet([f"e{i}" for i in range(m)], source, target, faces)


def _linear_mix(example_set: ExampleSet, frames: int, seed: int = 1):
    """Sparse activations (F, M) and the source points and target frames they make."""
    rng = np.random.default_rng(seed)
    m = example_set.num_examples
    act = rng.uniform(0, 1, size=(frames, m)) * (rng.random((frames, m)) < 0.4)
    act[:, 0] = 0.0
    src, tgt = example_set.source_points, example_set.target_vertices
    points = src[0] + np.einsum("fm,mkc->fkc", act[:, 1:], src[1:] - src[0])
    truth = tgt[0] + np.einsum("fm,mvc->fvc", act[:, 1:], tgt[1:] - tgt[0])
    return act, points, truth


def test_identical_frames_have_zero_error():
    truth = np.random.default_rng(0).normal(size=(3, 10, 3))

    error = cloning_error(truth, truth.copy())

    assert error["eq41_percent"] == {"x": 0.0, "y": 0.0, "z": 0.0}
    assert error["rms_percent"] == 0.0 and error["max_percent"] == 0.0


def test_eq41_is_the_summed_absolute_error_over_the_summed_magnitude_per_axis():
    truth = np.ones((2, 4, 3))
    truth[:, :, 1] = 2.0
    pred = truth.copy()
    pred[:, :, 0] += 0.1  # every x off by 0.1: sum |dv| / sum |v| = 0.4 / 4

    error = cloning_error(truth, pred)

    assert error["eq41_percent"]["x"] == pytest.approx(10.0)
    assert error["eq41_percent"]["y"] == 0.0
    assert len(error["per_frame"]["rms_percent"]) == 2


def test_rms_and_max_are_relative_to_the_truths_bounding_box_diagonal():
    truth = np.zeros((1, 2, 3))
    truth[0, 1] = [3.0, 4.0, 0.0]  # diagonal 5
    pred = truth.copy()
    pred[0, 0, 2] = 0.5

    error = cloning_error(truth, pred)

    assert error["max_percent"] == pytest.approx(10.0)
    assert error["rms_percent"] == pytest.approx(100 * np.sqrt(0.25 / 2) / 5)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(0.01, 100.0), seed=st.integers(0, 1000))
def test_errors_do_not_change_with_the_unit_of_length(scale, seed):
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(2, 5, 3))
    pred = truth + rng.normal(scale=0.1, size=truth.shape)

    base, scaled = cloning_error(truth, pred), cloning_error(truth * scale, pred * scale)

    for axis in "xyz":
        assert scaled["eq41_percent"][axis] == pytest.approx(base["eq41_percent"][axis])
    assert scaled["rms_percent"] == pytest.approx(base["rms_percent"])


def test_mismatched_shapes_are_an_input_error():
    with pytest.raises(InputError, match="truth's"):
        cloning_error(np.zeros((2, 5, 3)), np.zeros((2, 4, 3)))


@pytest.mark.parametrize("peer", [least_squares_weights, nnls_weights])
def test_peers_recover_the_weights_of_linear_mixes(peer):
    example_set = _linear_set()
    act, points, _ = _linear_mix(example_set, 12)
    expected = act.copy()
    expected[:, 0] = 1.0 - act[:, 1:].sum(axis=1)

    weights = peer(example_set, points)

    np.testing.assert_allclose(weights, expected, atol=1e-8)
    np.testing.assert_allclose(peer(example_set, points[0]), expected[0], atol=1e-8)


def test_nnls_weights_are_never_negative_even_on_noise():
    example_set = _linear_set()
    points = example_set.source_neutral + np.random.default_rng(2).normal(size=(20, 8, 3))

    weights = nnls_weights(example_set, points)

    assert weights[:, 1:].min() >= 0.0
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)


def test_peers_refuse_points_of_the_wrong_shape():
    with pytest.raises(InputError, match=r"\(8, 3\)"):
        least_squares_weights(_linear_set(), np.zeros((5, 3)))


def test_default_settings_bracket_the_input_noise_and_cover_the_kernels():
    chosen = default_settings(0.1, ["bspline", "gaussian"])

    unbounded = [s for s in chosen if "kernel" not in s and s.get("clamp") in (None, "none")]
    assert {s["noise"] for s in unbounded} == {
        0.0, 0.05, 0.1, 0.2,
    }  # fmt: skip
    assert {"kernel": "gaussian", "clamp": "nonneg", "noise": 0.1} in chosen  # fit's bound, named
    assert {"clamp": "unit", "noise": 0.1} in chosen


def test_default_settings_show_the_bounded_rig_with_and_without_the_sparsity_prior():
    chosen = default_settings(0.1, ["bspline"])

    assert {"clamp": "nonneg", "noise": 0.1} in chosen
    assert {"clamp": "nonneg", "sparsity": 1.0, "noise": 0.1} in chosen
    assert {"clamp": "nonneg", "sparsity": "stream", "noise": 0.1} in chosen
    assert not any("sparsity" in setting for setting in default_settings(0.0, ["bspline"]))


def test_sparsity_setting_is_fitted_and_named_in_the_report():
    example_set = _linear_set()
    _, points, truth = _linear_mix(example_set, 10)

    report = evaluate(
        example_set, points, truth, settings=[{"clamp": "nonneg", "sparsity": 0.0, "noise": 0.05}],
        noise=0.02, timing=False,
    )  # fmt: skip

    entry = report["methods"]["rig clamp=nonneg sparsity=0 noise=0.05"]
    assert entry["failed"] is None and entry["settings"]["sparsity"] == 0.0


def test_evaluate_reports_every_method_in_both_conditions_as_json():
    example_set = _linear_set()
    _, points, truth = _linear_mix(example_set, 30)

    report = evaluate(
        example_set, points, truth,
        settings=[{"noise": 0.0}, {"noise": 0.05}, {"kernel": "nope", "label": "broken"}],
        noise=0.02, timing=True,
    )  # fmt: skip

    json.dumps(report, allow_nan=False)
    assert set(report["errors"]) == {"clean", "noisy"}
    assert set(report["errors"]["clean"]) == {"rig noise=0", "rig noise=0.05", "least squares",
                                              "nnls"}  # fmt: skip
    assert report["methods"]["broken"]["failed"].startswith("fit_failed")
    assert (
        max(report["errors"]["clean"]["rig noise=0"]["eq41_percent"].values()) < 1e-4
    )  # float32 blend
    assert report["timing"]["num_frames"] == 30 and report["timing"]["frames_per_second"] > 0


def test_evaluate_without_truth_reports_timing_only():
    example_set = _linear_set()
    _, points, _ = _linear_mix(example_set, 5)

    report = evaluate(example_set, points, None, settings=[{"noise": 0.0}])

    assert report["errors"] is None and report["timing"] is not None


def test_evaluate_refuses_truth_of_the_wrong_frame_count():
    example_set = _linear_set()
    _, points, truth = _linear_mix(example_set, 5)

    with pytest.raises(InputError, match="truth"):
        evaluate(example_set, points, truth[:4], timing=False)


# -- jitter and the one-euro filter ------------------------------------------------------
def test_jitter_is_zero_at_constant_speed_and_grows_with_noise():
    from facecast.rig.evaluation.evaluate import jitter

    ramp = np.linspace(0.0, 1.0, 50)[:, None] * np.ones((1, 6))
    assert jitter(ramp) == pytest.approx(0.0, abs=1e-15)
    noisy = ramp + np.random.default_rng(0).normal(0.0, 0.01, ramp.shape)
    # White noise of std s has second differences of std s * sqrt(6).
    assert jitter(noisy) == pytest.approx(0.01 * np.sqrt(6.0), rel=0.15)


def test_one_euro_filter_reduces_the_jitter_of_a_noisy_clone():
    from facecast.rig import fit
    from facecast.rig.demo import (
        demo_activations,
        demo_animation,
        demo_example_set,
        demo_target_frames,
    )
    from facecast.rig.evaluation.evaluate import smoothing_report

    rig = fit(demo_example_set())
    animation = demo_animation(3.0, with_vertices=False)
    truth = demo_target_frames(demo_activations(3.0, 60.0))
    noisy = animation.points + np.random.default_rng(1).normal(0.0, 0.05, animation.points.shape)
    report = smoothing_report(rig, animation.points, noisy, truth, fps=60.0, min_cutoff=1.0)
    assert report["noisy"]["jitter"] > 3.0 * report["clean"]["jitter"]
    assert report["filtered"]["jitter"] < 0.25 * report["noisy"]["jitter"]


def test_default_settings_name_the_bound_of_every_kernel_row_with_noise():
    example_set = _linear_set()
    _, points, truth = _linear_mix(example_set, 10)
    settings = default_settings(0.01, ("bspline", "gaussian", "linear"))

    report = evaluate(example_set, points, truth, settings=settings, noise=0.01)
    clean = evaluate(
        example_set, points, truth, settings=default_settings(0.0, ("bspline", "gaussian"))
    )

    assert "rig gaussian clamp=nonneg noise=0.01" in report["methods"]
    assert "rig linear clamp=nonneg noise=0.01" in report["methods"]
    assert report["methods"]["rig gaussian clamp=nonneg noise=0.01"]["settings"]["clamp"] == (
        "nonneg"
    )
    assert "rig gaussian noise=0" in clean["methods"]

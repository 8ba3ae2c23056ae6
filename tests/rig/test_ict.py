"""ICT-FaceKit as an example set: the rig of its expressions, and cloning its mixes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facecast.rig import fit
from facecast.rig.bounds import project_box, weight_metric
from facecast.rig.errors import ExampleSetError
from facecast.rig.evaluation.evaluate import cloning_error, evaluate, least_squares_weights
from facecast.rig.sources.ict import (
    DEFAULT_LANDMARKS,
    ict_animation,
    ict_example_set,
    ict_target_frames,
    locate_ict,
)

ARCHIVE = locate_ict()
SKIP_REASON = "ICT-FaceKit not found (../shared/data/ict-facekit or $FACECAST_ICT)"


@pytest.fixture(scope="module")
def example_set():
    return ict_example_set(ARCHIVE)


@pytest.fixture(scope="module")
def rig(example_set):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(example_set)


@pytest.fixture(scope="module")
def performance(example_set):
    activations, animation = ict_animation(example_set, seconds=2.0, fps=30.0, seed=3)
    return activations, animation, ict_target_frames(example_set, activations)


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_default_set_leaves_out_only_the_pupil_shapes(example_set):
    assert example_set.names[0] == "neutral"
    assert len(example_set.names) == 56
    assert "PupilDilate_L" not in example_set.names
    assert "PupilDilate_R" not in example_set.names
    assert example_set.num_points == len(DEFAULT_LANDMARKS) == 24


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_rig_of_ict_expressions_keeps_every_component(rig):
    assert rig.fit_report["components_kept"] == 55
    assert rig.fit_report["condition_number"] < 100


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_weights_are_cardinal_at_the_examples(rig, example_set):
    weights = rig.weights(example_set.source_points)

    np.testing.assert_allclose(weights, np.eye(56), atol=1e-8)


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_clean_expression_mixes_clone_with_eq41_error_below_a_hundredth_percent(rig, performance):
    _, animation, truth = performance

    error = cloning_error(truth, rig.clone(animation.points))

    assert max(error["eq41_percent"].values()) < 0.01


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_regularised_rig_beats_plain_least_squares_on_noisy_points(example_set, rig, performance):
    _, animation, truth = performance
    noisy = animation.points + np.random.default_rng(0).normal(0.0, 0.01, animation.points.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        regularised = fit(example_set, noise=0.02)

    rig_error = cloning_error(truth, regularised.clone(noisy))["eq41_percent"]
    ls_error = cloning_error(truth, rig.blend(least_squares_weights(example_set, noisy)))

    for axis in "xyz":
        assert rig_error[axis] * 10 < ls_error["eq41_percent"][axis]


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
@pytest.mark.parametrize("noise", [0.01, 0.05])  # 0.1 mm and 0.5 mm
def test_bounded_noise_rig_beats_nnls_and_least_squares_on_every_axis(
    example_set, performance, noise
):
    # On synthetic sparse mixes with the sparsity prior made for them (rate 1; the default,
    # none, is chosen on real takes: tests/rig/test_takes.py).
    _, animation, truth = performance

    report = evaluate(
        example_set, animation, truth,
        settings=[{"clamp": "nonneg", "sparsity": 1.0, "noise": noise}],
        noise=noise, timing=False, series=False,
    )  # fmt: skip

    errors = {label: e["eq41_percent"] for label, e in report["errors"]["noisy"].items()}
    rig = errors[f"rig clamp=nonneg sparsity=1 noise={noise:g}"]
    for axis in "xyz":
        assert rig[axis] < errors["nnls"][axis]
        assert rig[axis] < errors["least squares"][axis]


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_sparse_projection_of_noisy_ict_weights_terminates_at_the_optimum(example_set):
    # The take and noise of `facecast eval --ict --noise 0.01`: on two of its frames
    # exchanging every infeasible weight at once cycles for ever; the single-exchange
    # fallback must end there at a KKT point.
    _, animation = ict_animation(example_set, seconds=10.0, fps=60.0, seed=0)
    noisy = animation.points + np.random.default_rng(0).normal(0.0, 0.01, animation.points.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        unbounded = fit(example_set, noise=0.01)
    weights = unbounded.weights(noisy)[:, 1:]
    metric = weight_metric(unbounded.model.params, unbounded.model.ridge)
    penalty = unbounded.model.sparsity_penalty

    x = project_box(weights, metric, None, penalty=penalty)

    gradient = 2.0 * (x - weights) @ metric + penalty
    assert x.min() >= 0.0
    assert np.abs(np.where(x > 0, gradient, np.minimum(gradient, 0.0))).max() < 1e-8


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_identity_target_carries_the_generic_expression_deltas(example_set):
    person = ict_example_set(ARCHIVE, expressions=["jawOpen", "eyeBlink_L"], identity="person03")
    generic = example_set.subset(["jawOpen", "eyeBlink_L"])

    target_deltas = person.target_vertices - person.target_vertices[0]
    source_deltas = generic.source_vertices - generic.source_vertices[0]

    np.testing.assert_allclose(target_deltas, source_deltas, atol=1e-5)
    assert np.abs(person.target_vertices[0] - generic.target_vertices[0]).max() > 0.1


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_animation_keeps_activations_in_unit_range_with_mouth_close_under_jaw_open(
    example_set,
):
    activations, animation = ict_animation(example_set, seconds=20.0, fps=30.0, seed=1)
    names = example_set.names

    assert activations.shape == (600, 56) and animation.points.shape == (600, 24, 3)
    assert activations.min() >= 0.0 and activations.max() <= 1.0
    assert np.all(activations[:, 0] == 0.0)
    close, jaw = names.index("mouthClose"), names.index("jawOpen")
    assert np.all(activations[:, close] <= activations[:, jaw])
    assert 1.0 < (activations[:, 1:] > 0.05).sum(axis=1).mean() < 6.0


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_explicit_expression_that_moves_no_feature_point_is_refused():
    with pytest.raises(ExampleSetError, match="PupilDilate_L"):
        ict_example_set(ARCHIVE, expressions=["jawOpen", "PupilDilate_L"])


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_unknown_identity_and_expression_are_named_in_the_error():
    with pytest.raises(ExampleSetError, match="person99"):
        ict_example_set(ARCHIVE, expressions=["jawOpen"], identity="person99")
    with pytest.raises(ExampleSetError, match="smileWide"):
        ict_example_set(ARCHIVE, expressions=["smileWide"])


def test_missing_archive_is_an_error_naming_the_path(tmp_path):
    with pytest.raises(ExampleSetError, match="nowhere"):
        ict_example_set(tmp_path / "nowhere")


def _amplification_warnings(example_set, **settings) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit(example_set, **settings)
    return [str(w.message) for w in caught if "amplifies landmark noise" in str(w.message)]


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_exact_rig_warns_that_it_amplifies_landmark_noise(example_set, rig):
    (message,) = _amplification_warnings(example_set)

    tolerance = rig.fit_report["noise_tolerance"]
    assert tolerance < 1e-4  # a micrometre (ICT is in cm): far below any tracker's noise
    assert f"{tolerance:.2g} source units" in message
    assert "--noise SIGMA --clamp nonneg" in message
    assert message in rig.fit_report["warnings"]


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_rig_fitted_for_a_tenth_of_a_millimetre_of_noise_does_not_warn(example_set):
    assert _amplification_warnings(example_set, noise=0.01) == []

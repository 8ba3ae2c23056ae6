"""Cloning quality on real takes: exact defaults, and the bundled Live Link Face take."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from facecast.rig import fit
from facecast.rig.evaluation.evaluate import cloning_error, least_squares_weights, nnls_weights
from facecast.rig.evaluation.takes import take_experiment
from facecast.rig.examples import ExampleSet
from facecast.rig.fit import resolution_threshold
from facecast.rig.sources.ict import ict_example_set, locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set
from facecast.rig.sources.trackers import read_livelink_csv

ARCHIVE = locate_ict()
SKIP_REASON = "ICT-FaceKit not found (../shared/data/ict-facekit or $FACECAST_ICT)"
TAKE = Path(__file__).parents[1] / "data" / "livelink" / "llv_dao.csv"
needs_ict = [pytest.mark.ict, pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)]


def _quiet_fit(example_set, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(example_set, **kwargs)


def _max_axis(truth, vertices) -> float:
    return max(cloning_error(truth, vertices)["eq41_percent"].values())


@pytest.fixture(scope="module")
def thin_set():
    """ICT plus an example barely off the midpoint of two others, along a direction of its own.

    Its eigenvalue is ~4e-11 of the largest: below the old fixed threshold (1e-10), but its
    singular value stands ~2.5 times above the points' float32 resolution.
    """
    ict = ict_example_set(ARCHIVE)
    names = ict.names
    a, b, z = names.index("eyeWide_L"), names.index("eyeLookUp_L"), names.index("jawOpen")
    m, k = ict.num_examples, ict.num_points
    source = ict.source_points
    deltas = (source - source[0]).reshape(m, -1)
    # A unit direction no example moves along: the last right singular vector of the
    # displacements (3K = 60 > 55 of them).
    direction = np.linalg.svd(deltas, full_matrices=True)[2][-1]
    step = 2.5 * resolution_threshold(source)
    new_source = source[0] + 0.5 * (source[a] - source[0] + source[b] - source[0])
    new_source = new_source + (step * direction).reshape(k, 3)
    target = ict.target_vertices
    # Its target is something else than the midpoint, so telling it apart matters.
    new_target = (
        target[0] + 0.5 * (target[a] + target[b]) - target[0] + 0.5 * (target[z] - target[0])
    )
    return ExampleSet(
        names=(*names, "thin"),
        source_points=np.concatenate([source, new_source[None]]),
        target_vertices=np.concatenate([target, new_target[None]]),
        target_faces=ict.target_faces,
    )


def _thin_take(example_set):
    rng = np.random.default_rng(5)
    m = example_set.num_examples
    activations = rng.uniform(0, 1, (40, m)) * (rng.random((40, m)) < 0.1)
    activations[:, 0] = 0.0
    activations[::2, -1] = rng.uniform(0.3, 1.0, 20)
    src, tgt = example_set.source_points, example_set.target_vertices
    points = src[0] + np.einsum("fm,mkc->fkc", activations[:, 1:], src[1:] - src[0])
    truth = tgt[0] + np.einsum("fm,mvc->fvc", activations[:, 1:], tgt[1:] - tgt[0])
    return points, truth.astype(np.float32)


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_default_threshold_keeps_a_direction_above_the_points_resolution(thin_set):
    rig = _quiet_fit(thin_set)
    assert rig.fit_report["components_kept"] == thin_set.num_examples - 1
    assert rig.fit_report["pca_threshold"] < 1e-10


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_clean_input_with_defaults_is_as_exact_as_least_squares(thin_set):
    points, truth = _thin_take(thin_set)
    ls = _max_axis(truth, _quiet_fit(thin_set).blend(least_squares_weights(thin_set, points)))
    default = _max_axis(truth, _quiet_fit(thin_set).clone(points))
    # The old fixed threshold drops the thin direction and misreads the thin example.
    dropped = _max_axis(truth, _quiet_fit(thin_set, pca_threshold=1e-10).clone(points))
    assert dropped > 0.05
    assert default <= 1.01 * ls + 1e-4  # 1e-4 %: float32 blending's rounding


def test_resolution_threshold_scales_with_the_points_extent():
    points = np.random.default_rng(0).normal(size=(10, 4, 3))
    assert resolution_threshold(10.0 * points) == pytest.approx(10.0 * resolution_threshold(points))
    assert resolution_threshold(points) == pytest.approx(
        np.finfo(np.float32).eps * np.abs(points).max() * (np.sqrt(10) + np.sqrt(12))
    )


@pytest.fixture(scope="module")
def take():
    examples = arkit_example_set(ARCHIVE)
    livelink = read_livelink_csv(TAKE)
    return take_experiment(examples, livelink.weights, livelink.fps)


def test_bundled_take_is_a_real_capture_of_many_small_weights():
    livelink = read_livelink_csv(TAKE)
    assert livelink.weights.shape == (180, 52)
    assert livelink.head is not None
    # Real ARKit captures carry many small weights at once (synthetic mixes: ~1.3).
    assert livelink.weights.sum(axis=1).mean() > 5.0


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_arkit_example_set_names_follow_arkit_without_tongue(take):
    assert take.examples.num_examples == 52
    assert take.examples.names[1] == "eyeBlinkLeft"
    assert "tongueOut" not in take.examples.names
    assert take.truth.shape == (180, 9409, 3)


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_real_take_clean_defaults_within_one_percent_of_least_squares(take):
    rig = _quiet_fit(take.examples)
    ls = _max_axis(take.truth, rig.blend(least_squares_weights(take.examples, take.points)))
    assert _max_axis(take.truth, rig.clone(take.points)) <= 1.01 * ls + 1e-4


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
@pytest.mark.parametrize("sigma", [0.01, 0.05])  # cm: 0.1 mm and 0.5 mm
def test_real_take_noise_rig_with_its_defaults_beats_nnls_on_every_axis(take, sigma):
    noisy = take.points + np.random.default_rng(0).normal(0.0, sigma, take.points.shape)
    rig = _quiet_fit(take.examples, noise=sigma)  # bounded (nonneg) by default, no prior
    assert rig.model.clamp == "nonneg" and rig.model.sparsity_penalty == 0.0
    ours = cloning_error(take.truth, rig.clone(noisy))["eq41_percent"]
    nnls = cloning_error(take.truth, rig.blend(nnls_weights(take.examples, noisy)))["eq41_percent"]
    for axis in ("x", "y", "z"):
        assert ours[axis] < nnls[axis], axis
    assert max(ours.values()) <= 1.0


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason=SKIP_REASON)
def test_real_take_bounded_noise_rig_beats_the_unbounded_one(take):
    # Why the default bounds a noise rig: the bounds are part of the prior (w >= 0).
    sigma = 0.05
    noisy = take.points + np.random.default_rng(0).normal(0.0, sigma, take.points.shape)
    unbounded = _quiet_fit(take.examples, noise=sigma, clamp="none")
    bounded = _quiet_fit(take.examples, noise=sigma)
    assert unbounded.model.clamp is None
    assert _max_axis(take.truth, bounded.clone(noisy)) < _max_axis(
        take.truth, unbounded.clone(noisy)
    )


def test_fit_report_splits_its_time_into_math_and_the_blend_basis():
    report = _quiet_fit(_small_set()).fit_report
    assert 0.0 < report["basis_seconds"] <= report["fit_seconds"]


def test_clamp_default_bounds_noise_rigs_only():
    examples = _small_set()
    assert _quiet_fit(examples).model.clamp is None
    assert _quiet_fit(examples, noise=0.1).model.clamp == "nonneg"
    assert _quiet_fit(examples, noise=0.1, clamp="none").model.clamp is None
    assert _quiet_fit(examples, noise=0.1, clamp="unit").model.clamp == "unit"


def _small_set() -> ExampleSet:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(6, 5, 3))
    return ExampleSet(
        names=tuple(f"e{i}" for i in range(6)),
        source_points=points,
        target_vertices=rng.normal(size=(6, 7, 3)),
        target_faces=np.array([[0, 1, 2]]),
    )

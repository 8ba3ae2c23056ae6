"""Behaviour of fit and Rig evaluation: the thesis's invariants and the engine's errors."""

from __future__ import annotations

import dataclasses
import io
import json
import warnings

import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.rig import (
    ExampleSet,
    ExampleSetError,
    FitError,
    IdentifiabilityWarning,
    InputError,
    Rig,
    align_points,
    fit,
    rig_from_bytes,
)
from facecast.rig.examples import MIN_NEUTRAL_RADIUS
from facecast.rig.fit import NOISE_MAX_RELATIVE
from facecast.rig.radial import bspline
from facecast.rig.rig import CALIBRATION_RANGE, POINT_RANGE

M, K, V = 9, 6, 40


def make_set(m=M, k=K, v=V, seed=0) -> ExampleSet:
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(k, 3))
    source = neutral + np.concatenate([np.zeros((1, k, 3)), rng.normal(size=(m - 1, k, 3))])
    target_neutral = rng.normal(size=(v, 3))
    target = target_neutral + np.concatenate([np.zeros((1, v, 3)), rng.normal(size=(m - 1, v, 3))])
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    return ExampleSet([f"e{i}" if i else "neutral" for i in range(m)], source, target, faces)


@pytest.fixture(scope="module")
def example_set():
    return make_set()


@pytest.fixture(scope="module")
def rig(example_set):
    return fit(example_set)


def test_bspline_cross_section_matches_the_thesis():
    t = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 3.0])
    expected = [2 / 3, 2 / 3 - 0.25 + 0.0625, 1 / 6, 0.5**3 / 6, 0.0, 0.0]
    np.testing.assert_allclose(bspline(t), expected, atol=1e-15)


@pytest.mark.parametrize("kernel", ["bspline", "gaussian", "thin_plate", "linear"])
def test_cardinal_property_at_every_example(example_set, kernel):
    rig = fit(example_set, kernel=kernel)
    weights = rig.weights(example_set.source_points)
    np.testing.assert_allclose(weights, np.eye(M), atol=1e-8)


def test_cardinal_property_with_more_examples_than_parameters():
    # 3K = 6 < M - 1 = 19, so the hyperplanes cannot interpolate and the radial part must.
    example_set = make_set(m=20, k=2, seed=3)
    rig = fit(example_set)
    assert rig.fit_report["components_kept"] == 6
    weights = rig.weights(example_set.source_points)
    np.testing.assert_allclose(weights, np.eye(20), atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.integers(min_value=0, max_value=2**31 - 1), st.floats(min_value=0.01, max_value=5.0))
def test_partition_of_unity_at_random_points(seed, scale):
    example_set = make_set(m=12, k=2, seed=7)
    rig = fit(example_set)
    points = np.random.default_rng(seed).normal(scale=scale, size=(16, 2, 3))
    np.testing.assert_allclose(rig.weights(points).sum(axis=1), 1.0, atol=1e-9)


def test_every_example_is_reproduced_exactly(example_set, rig):
    cloned = rig.clone(example_set.source_points)
    np.testing.assert_allclose(cloned, example_set.target_vertices, atol=1e-5)


def test_neutral_frame_reproduces_target_neutral(example_set, rig):
    np.testing.assert_array_equal(
        rig.clone(example_set.source_neutral), example_set.target_neutral.astype(np.float32)
    )


def test_single_frame_equals_batch_of_one(example_set, rig):
    points = example_set.source_points[3] + 0.1
    np.testing.assert_array_equal(rig.weights(points), rig.weights(points[None])[0])


def test_weights_follow_equation_3_8_directly(example_set, rig):
    points = np.random.default_rng(1).normal(size=(5, K, 3))
    flat = (points - example_set.source_neutral).reshape(5, -1)
    params = (flat - rig.model.mean) @ rig.model.features.T
    np.testing.assert_allclose(
        rig.weights(points), rig.model.weights_from_params(params), atol=1e-10
    )


def test_blend_with_preallocated_output(rig):
    weights = np.random.default_rng(2).random((3, M))
    out = np.empty((3, V, 3), np.float32)
    result = rig.blend(weights, out=out)
    assert result is out
    np.testing.assert_allclose(out, rig.blend(weights), rtol=1e-6)


def test_save_load_round_trip(tmp_path, example_set, rig):
    path = tmp_path / "rig.npz"
    rig.save(path)
    from facecast.rig import load_rig

    loaded = load_rig(path)
    points = np.random.default_rng(4).normal(size=(7, K, 3))
    np.testing.assert_array_equal(loaded.weights(points), rig.weights(points))
    np.testing.assert_array_equal(loaded.blend_basis, rig.blend_basis)
    assert loaded.names == rig.names
    assert loaded.checksum == rig.checksum


def test_noise_regularisation_keeps_unity_and_lowers_noise_gain(example_set):
    exact = fit(example_set)
    smooth = fit(example_set, noise=0.5)
    points = np.random.default_rng(5).normal(size=(20, K, 3))
    np.testing.assert_allclose(smooth.weights(points).sum(axis=1), 1.0, atol=1e-9)
    assert smooth.fit_report["noise_gain"] < exact.fit_report["noise_gain"]


def _ridge_system(example_set, points, noise):
    """Example displacements D (M-1, 3K), frame displacements (B, 3K), ridge M noise^2."""
    m = example_set.num_examples
    neutral = example_set.source_neutral
    displacements = (example_set.source_points[1:] - neutral).reshape(m - 1, -1)
    frames = (points - neutral).reshape(len(points), -1)
    return displacements, frames, m * noise * noise


def test_noise_rig_maps_the_neutral_to_the_neutral(example_set):
    # The ridge is a prior centred on the face at rest, not on the average example.
    rig = fit(example_set, noise=0.5, clamp="none")
    expected = np.eye(example_set.num_examples)[0]
    np.testing.assert_allclose(rig.weights(example_set.source_neutral), expected, atol=1e-12)


def test_noise_rig_weights_are_ridge_regression_on_the_example_displacements(example_set):
    noise = 0.5
    rig = fit(example_set, noise=noise, clamp="none")
    points = np.random.default_rng(6).normal(size=(12, K, 3))
    displacements, frames, ridge = _ridge_system(example_set, points, noise)
    gram = displacements @ displacements.T + ridge * np.eye(len(displacements))
    expected = np.linalg.solve(gram, displacements @ frames.T).T  # eq. of the MAP weights
    np.testing.assert_allclose(rig.weights(points)[:, 1:], expected, atol=1e-9)


def test_bounded_noise_rig_is_nonnegative_ridge_regression(example_set):
    noise = 0.5
    rig = fit(example_set, noise=noise)  # nonneg by default
    points = np.random.default_rng(7).normal(size=(12, K, 3))
    displacements, frames, ridge = _ridge_system(example_set, points, noise)
    n = len(displacements)
    system = np.vstack([displacements.T, np.sqrt(ridge) * np.eye(n)])
    expected = np.array(
        [scipy.optimize.nnls(system, np.concatenate([f, np.zeros(n)]))[0] for f in frames]
    )
    assert (expected == 0).any()  # the bounds are active somewhere
    np.testing.assert_allclose(rig.weights(points)[:, 1:], expected, atol=1e-8)


@pytest.mark.parametrize("mode,low,high", [("nonneg", 0.0, np.inf), ("unit", 0.0, 1.0)])
def test_clamped_weights_stay_in_range_and_sum_to_one(example_set, mode, low, high):
    rig = fit(example_set, clamp=mode)
    points = np.random.default_rng(6).normal(scale=3.0, size=(50, K, 3))
    weights = rig.weights(points)
    assert weights[:, 1:].min() >= low
    assert weights[:, 1:].max() <= high
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(rig.weights(example_set.source_points), np.eye(M), atol=1e-8)


def _turned(points: np.ndarray, angle: float = 0.4) -> np.ndarray:
    rotation = np.array(
        [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    )
    return points @ rotation.T + np.array([3.0, -1.0, 2.0])


def test_aligned_weights_of_a_rigidly_moved_example_are_that_example(example_set):
    # Stable points that the examples move too: alignment on them alone is off, and the
    # pose refinement against the examples' span removes the rest.
    rig = fit(example_set, stable_points=[0, 1, 2])
    moved = _turned(example_set.source_points)
    assert rig.pose_refinement() is not None
    assert np.abs(rig.weights(moved) - np.eye(M)).max() > 0.1
    np.testing.assert_allclose(rig.weights(moved, align=True), np.eye(M), atol=1e-8)


def test_aligned_weights_of_a_mix_under_motion_equal_the_unmoved_mix(example_set):
    rig = fit(example_set, stable_points=[0, 1, 2])
    mix = np.random.default_rng(3).dirichlet(np.ones(M), size=5)
    neutral = example_set.source_neutral
    points = neutral + np.einsum("fm,mkj->fkj", mix, example_set.source_points - neutral)
    np.testing.assert_allclose(
        rig.weights(_turned(points), align=True), rig.weights(points), atol=1e-8
    )


def test_without_free_directions_align_uses_the_stable_points_alone():
    # 3 points, 8 examples: 9 coordinates hold no direction that no expression makes.
    example_set = make_set(k=3)
    rig = fit(example_set, stable_points=[0, 1, 2])
    moved = _turned(example_set.source_points[2])
    assert rig.pose_refinement() is None
    assert rig.fit_report["pose_condition"] == float("inf")
    np.testing.assert_allclose(
        rig.weights(moved, align=True),
        rig.weights(align_points(moved[None], example_set.source_neutral)[0]),
        atol=1e-10,
    )


def test_fit_takes_the_example_sets_stable_points_unless_given_others(example_set):
    named = dataclasses.replace(example_set, stable_points=np.array([1, 3, 5]))
    assert fit(named).stable_points.tolist() == [1, 3, 5]
    assert fit(named).fit_report["stable_points"] == [1, 3, 5]
    assert fit(named, stable_points=[0, 2, 4]).fit_report["stable_points"] == [0, 2, 4]
    assert fit(example_set).fit_report["stable_points"] is None


@pytest.mark.parametrize("stable", [[0, 1], [0, 1, K], [0, 0, 1], [0.5, 1, 2]])
def test_example_set_refuses_bad_stable_points(example_set, stable):
    with pytest.raises(ExampleSetError) as info:
        dataclasses.replace(example_set, stable_points=np.array(stable))
    assert info.value.code == "bad_stable_points"


@pytest.mark.parametrize("stable", [[0, 1], [0, 1, K], [0, 0, 1], [0.5, 1, 2]])
def test_fit_refuses_the_bad_stable_points_an_example_set_refuses(example_set, stable):
    # One check for both ways stable points reach a rig (examples.check_stable_points).
    with pytest.raises(ExampleSetError) as info:
        fit(example_set, stable_points=stable)
    assert info.value.code == "bad_stable_points"


def _with_neutral(example_set, neutral):
    source = example_set.source_points.copy()
    source[0] = neutral
    return dataclasses.replace(example_set, source_points=source)


@pytest.mark.parametrize(
    "neutral",
    [
        np.full((K, 3), 0.25),  # K equal points
        np.zeros((K, 3)),  # at the origin too
        np.full((K, 3), 1e3) + np.arange(K)[:, None] * 1e-6,  # apart by 1e-9 of it
    ],
)
def test_example_set_refuses_a_neutral_without_extent(example_set, neutral):
    with pytest.raises(ExampleSetError) as info:
        _with_neutral(example_set, neutral)
    assert info.value.code == "degenerate_neutral"
    assert "no extent" in str(info.value)


def test_example_set_of_one_feature_point_is_refused():
    # One point has no extent, however far its examples move it: the rig would refuse
    # every frame but the neutral (its point range is a multiple of that extent).
    source = np.zeros((3, 1, 3))
    source[:, 0, 0] = [0.5, 1.0, 2.0]
    with pytest.raises(ExampleSetError) as info:
        ExampleSet(["neutral", "a", "b"], source, np.zeros((3, 4, 3)), np.zeros((0, 3)))
    assert info.value.code == "degenerate_neutral"


def test_example_set_takes_a_neutral_just_above_the_extent_bound(example_set):
    # Two points apart along x: radius d / 2, largest coordinate 1.
    neutral = np.zeros((K, 3))
    neutral[:, 1] = 1.0
    neutral[: K // 2, 0] = 2.01 * MIN_NEUTRAL_RADIUS
    above = _with_neutral(example_set, neutral)
    assert above.source_points[0, 0, 0] == neutral[0, 0]
    neutral[: K // 2, 0] = 1.99 * MIN_NEUTRAL_RADIUS
    with pytest.raises(ExampleSetError, match="no extent"):
        _with_neutral(example_set, neutral)


def test_weights_that_overflow_for_finite_points_are_an_input_error(example_set, rig):
    # A rig file need only be finite: hyperplane coefficients at float64's largest load,
    # and take finite, in-range points to infinite weights, refused rather than returned.
    coeffs = rig.model.linear_coeffs
    huge_coeffs = coeffs / np.abs(coeffs).max() * np.finfo(np.float64).max
    assert np.isfinite(huge_coeffs).all()
    with np.errstate(over="ignore", invalid="ignore"):
        huge = Rig(
            names=rig.names,
            model=dataclasses.replace(rig.model, linear_coeffs=huge_coeffs),
            target_neutral=rig.target_neutral,
            blend_basis=rig.blend_basis.copy(),
            target_faces=rig.target_faces,
            feature_indices=None,
            source_preview=None,
            stable_points=None,
            align_scale=False,
            report={},
        )
        loaded = rig_from_bytes(huge.to_bytes())
        frames = example_set.source_points[[0, 3]] * 1.5
        with pytest.raises(
            InputError, match=r"weights of finite feature points \(frame 0\)"
        ) as batch:
            loaded.weights(frames)
        with pytest.raises(InputError, match="not finite") as single:
            loaded.weights(frames[1])
    assert batch.value.code == single.value.code == "non_finite"


def test_with_align_scale_leaves_the_rig_it_came_from_unchanged(example_set):
    rig = fit(example_set, stable_points=[0, 1, 2, 3])
    frame = example_set.source_points[2] * 1.7 + 0.3

    scaled = rig.with_align_scale(True)

    assert scaled.align_scale and not rig.align_scale
    assert rig.with_align_scale(False) is rig
    np.testing.assert_allclose(
        scaled.weights(frame, align=True),
        scaled.weights(example_set.source_points[2], align=True),
        atol=1e-8,
    )
    assert not np.allclose(rig.weights(frame, align=True), scaled.weights(frame, align=True))


def test_aligned_non_finite_points_are_an_input_error(example_set):
    rig = fit(example_set, stable_points=[0, 1, 2])
    points = np.repeat(example_set.source_points[None, 1], 3, axis=0)
    points[1, 4, 0] = np.nan
    with pytest.raises(InputError, match="frame 1"):
        rig.weights(points, align=True)


def test_uniform_scale_is_removed_with_align_scale():
    frames = np.random.default_rng(8).normal(size=(4, 10, 3))
    reference = frames[0]
    scaled = frames * 1.7 + 0.3
    aligned = align_points(scaled, reference, scale=True)
    np.testing.assert_allclose(aligned[0], reference, atol=1e-10)


def test_calibration_rebases_on_another_performers_neutral(example_set, rig):
    performer_neutral = example_set.source_neutral * 1.2 + np.array([0.5, 0.0, -0.2])
    calibrated = rig.calibrated(performer_neutral)
    np.testing.assert_allclose(calibrated.weights(performer_neutral), np.eye(M)[0], atol=1e-9)
    # The performer's own expression: the same displacement, scaled with the face.
    happy = performer_neutral + 1.2 * (example_set.source_points[4] - example_set.source_neutral)
    np.testing.assert_allclose(calibrated.weights(happy), np.eye(M)[4], atol=1e-8)


def test_calibrated_rig_survives_save_and_load(example_set, rig):
    calibrated = rig.calibrated(example_set.source_neutral + 0.3)
    loaded = rig_from_bytes(calibrated.to_bytes())
    points = example_set.source_points + 0.3
    np.testing.assert_allclose(loaded.weights(points), np.eye(M), atol=1e-8)


# -- bad input ---------------------------------------------------------------------------
def test_fewer_than_two_examples_is_refused():
    with pytest.raises(Exception, match="at least 2 examples"):
        make_set(m=1)


def test_coinciding_examples_are_named_with_advice():
    example_set = make_set()
    source = example_set.source_points.copy()
    source[5] = source[2]
    bad = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )
    with pytest.raises(FitError, match=r"'e2' and 'e5'.*(add feature points|drop one)") as info:
        fit(bad)
    assert info.value.code == "examples_coincide"


def test_nearly_collapsing_examples_warn_naming_both():
    example_set = make_set()
    source = example_set.source_points.copy()
    source[5] = source[2] + 1e-3
    near = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )
    with pytest.warns(IdentifiabilityWarning, match="'e5' and 'e2'|'e2' and 'e5'"):
        rig = fit(near)
    assert rig.fit_report["nearest_name"][5] == "e2"


def test_examples_that_move_no_feature_point_are_refused():
    example_set = make_set()
    source = np.repeat(example_set.source_points[:1], M, axis=0)
    flat = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )
    with pytest.raises(FitError, match="no example moves any feature point"):
        fit(flat)


def test_near_singular_radial_system_is_reported_with_its_condition_number():
    # Thin-plate terms vanish at t = 0 and t = 1: on three evenly spaced examples the radial
    # matrix has a zero row.
    # Point 1 stays put (a neutral needs extent): the examples differ by point 0 alone.
    source = np.zeros((3, 2, 3))
    source[:, 0, 0] = [0.0, 1.0, 2.0]
    source[:, 1, 1] = 1.0
    example_set = ExampleSet(
        ["neutral", "a", "b"],
        source,
        np.random.default_rng(0).normal(size=(3, 4, 3)),
        np.zeros((0, 3)),
    )
    with pytest.raises(FitError, match="condition number") as info:
        fit(example_set, kernel="thin_plate")
    assert info.value.code == "singular_system"


@pytest.mark.parametrize(
    "points,code",
    [
        (np.zeros((K + 1, 3)), "wrong_point_count"),
        (np.zeros((K, 2)), "wrong_point_count"),
        (np.zeros((2, 3, K, 3)), "wrong_point_count"),
        (np.full((K, 3), np.nan), "non_finite"),
        (np.full((K, 3), np.inf), "non_finite"),
    ],
)
def test_bad_runtime_points_raise_input_error(rig, points, code):
    with pytest.raises(InputError) as info:
        rig.weights(points)
    assert info.value.code == code


def _at_rms(neutral: np.ndarray, factor: float) -> np.ndarray:
    """``neutral`` scaled about its centroid so its RMS distance from it is ``factor`` x its radius."""
    centre = neutral.mean(axis=0)
    return centre + (neutral - centre) * factor


def _bspline_and_clamped_rigs(example_set, rig):
    # The compiled single-frame path and the numpy path (taken with clamp) check alike.
    return [rig, fit(example_set, clamp="nonneg", noise=0.01)]


@pytest.mark.parametrize("which", [0, 1])
def test_points_at_the_range_bound_are_accepted_and_beyond_it_refused(example_set, rig, which):
    model = _bspline_and_clamped_rigs(example_set, rig)[which]
    neutral = example_set.source_neutral

    model.weights(_at_rms(neutral, POINT_RANGE * 0.999))
    with pytest.raises(InputError, match="in the rig's units") as info:
        model.weights(_at_rms(neutral, POINT_RANGE * 1.001))
    assert info.value.code == "out_of_range"


def test_points_in_other_units_are_refused_naming_the_frame_of_a_batch(example_set, rig):
    frames = example_set.source_points.copy()
    frames[3] *= 1000.0  # mm for m

    with pytest.raises(InputError, match=r"\(frame 3\)") as info:
        rig.weights(frames)
    assert info.value.code == "out_of_range"


def test_check_range_refuses_what_weights_refuses(example_set, rig):
    rig.check_range(example_set.source_points)
    with pytest.raises(InputError) as info:
        rig.check_range(example_set.source_neutral * 1e5)
    assert info.value.code == "out_of_range"


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize("factor", [0.0, 0.5, 0.999, 1.001, 2.0, np.nan])
def test_check_range_of_one_frame_answers_as_the_exact_check(example_set, rig, dtype, factor):
    # The one-frame shortcut (a dot product) may only accept what the exact check accepts.
    frame = _at_rms(example_set.source_neutral, POINT_RANGE * factor).astype(dtype)
    exact = InputError if not factor <= 1.0 else None

    if exact is None:
        rig.check_range(frame)
        rig.check_range(frame[None])
    else:
        with pytest.raises(exact):
            rig.check_range(frame)
        with pytest.raises(exact):
            rig.check_range(frame[None])


def test_calibrated_rig_measures_the_range_from_the_performers_neutral(example_set, rig):
    # A performer tracked 1000x larger (other units), far from the origin: legitimate once
    # calibrated, while the same points are out of range for the uncalibrated rig.
    performer = example_set.source_neutral * 1000.0 + 3e3
    calibrated = rig.calibrated(performer)

    np.testing.assert_allclose(calibrated.weights(performer), np.eye(M)[0], atol=1e-6)
    with pytest.raises(InputError):
        rig.weights(performer)
    calibrated.weights(_at_rms(performer, POINT_RANGE * 0.999))
    with pytest.raises(InputError):
        calibrated.weights(_at_rms(performer, POINT_RANGE * 1.001))


@pytest.mark.parametrize(
    "neutral_of",
    [
        lambda n: n * 0 + 1e300,  # the absurd neutral of issue 13: every later frame NaN
        lambda n: n + 2 * CALIBRATION_RANGE * np.abs(n).max() * 10,  # too far
        lambda n: _at_rms(n, 2 * CALIBRATION_RANGE),  # too large
        lambda n: _at_rms(n, 0.5 / CALIBRATION_RANGE),  # too small
    ],
    ids=["1e300", "far", "large", "small"],
)
def test_calibration_with_an_absurd_neutral_is_refused(example_set, rig, neutral_of):
    with pytest.raises(InputError, match="calibration neutral") as info:
        rig.calibrated(neutral_of(example_set.source_neutral))
    assert info.value.code == "out_of_range"


@pytest.mark.filterwarnings("ignore::facecast.rig.IdentifiabilityWarning")
def test_noise_up_to_ten_times_the_feature_points_extent_is_fitted_beyond_refused(example_set):
    flat = example_set.source_points.reshape(-1, 3)
    extent = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))

    rig = fit(example_set, noise=NOISE_MAX_RELATIVE * extent * 0.999, clamp="unit")
    with pytest.raises(FitError) as info:
        fit(example_set, noise=NOISE_MAX_RELATIVE * extent * 1.001, clamp="unit")

    assert np.isfinite(rig.weights(example_set.source_points)).all()
    assert info.value.code == "noise_too_large"


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"kernel": "cubic"}, "unknown kernel"),
        ({"noise": -1.0}, "noise"),
        ({"noise": float("nan")}, "noise"),
        ({"noise": 1e300}, "extent"),  # its square overflows: a 500 over REST before
        ({"pca_threshold": 2.0}, "pca_threshold"),
        ({"clamp": "yes"}, "clamp"),
        ({"sparsity": 1.0}, "sparsity"),
        ({"clamp": "nonneg", "sparsity": -1.0}, "sparsity"),
        ({"clamp": "nonneg", "sparsity": float("inf")}, "sparsity"),
    ],
)
def test_bad_fit_settings_are_refused(example_set, kwargs, match):
    with pytest.raises(FitError, match=match):
        fit(example_set, **kwargs)


def test_bounded_noise_rig_holds_the_sparsity_penalty_of_its_noise(example_set):
    rig = fit(example_set, noise=0.3, clamp="nonneg", sparsity=1.0)
    report = rig.fit_report

    assert report["sparsity"] == 1.0 and report["clamp"] == "nonneg"
    assert rig.model.sparsity_penalty == pytest.approx(2 * 0.3**2 * (M - 1))
    assert report["sparsity_penalty"] == rig.model.sparsity_penalty


def test_sparsity_prior_zeroes_more_weights_than_the_plain_projection(example_set):
    points = example_set.source_points[None, 1:4].mean(axis=1) + np.random.default_rng(7).normal(
        scale=0.3, size=(200, K, 3)
    )
    plain = fit(example_set, noise=0.3, clamp="nonneg", sparsity=0.0).weights(points)
    sparse = fit(example_set, noise=0.3, clamp="nonneg", sparsity=1.0).weights(points)

    assert (sparse[:, 1:] > 0).sum() < (plain[:, 1:] > 0).sum()
    np.testing.assert_allclose(sparse.sum(axis=1), 1.0, atol=1e-9)


def test_sparsity_prior_survives_the_rig_file(example_set):
    rig = fit(example_set, noise=0.3, clamp="unit", sparsity=2.0)
    points = np.random.default_rng(8).normal(size=(30, K, 3))

    loaded = rig_from_bytes(rig.to_bytes())

    assert loaded.model.sparsity_penalty == rig.model.sparsity_penalty > 0
    np.testing.assert_array_equal(loaded.weights(points), rig.weights(points))
    assert loaded.checksum == rig.checksum


def test_rig_without_the_prior_writes_no_sparsity_record_and_reads_back_without_it(
    example_set,
):
    # Older facecast wrote no such record: its files must read as rigs without the prior.
    rig = fit(example_set, noise=0.3, clamp="nonneg", sparsity=0.0)
    data = rig.to_bytes()
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        meta = json.loads(npz["meta"].tobytes())

    assert "sparsity_penalty" not in meta
    assert rig_from_bytes(data).model.sparsity_penalty == 0.0


def test_no_warning_on_well_separated_examples(example_set):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit(example_set)


def test_radial_terms_vanish_when_the_hyperplanes_interpolate(example_set, rig):
    # M - 1 = 8 examples in 8 kept dimensions: affine interpolation is already exact.
    assert rig.fit_report["components_kept"] == M - 1
    assert not np.any(rig.model.radial_coeffs)
    np.testing.assert_allclose(rig.weights(example_set.source_points), np.eye(M), atol=1e-10)


def test_radial_terms_remain_when_examples_outnumber_the_dimensions():
    rig = fit(make_set(m=20, k=2, seed=3))
    assert np.abs(rig.model.radial_coeffs).max() > 1e-3


def test_nearly_collapsing_examples_show_in_the_hyperplane_condition_number(rig):
    example_set = make_set()
    source = example_set.source_points.copy()
    source[5] = source[2] + 1e-3
    near = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        near_rig = fit(near)

    clean = rig.fit_report["hyperplane_condition_number"]
    assert near_rig.fit_report["hyperplane_condition_number"] > 100 * clean


def _nearly_affinely_dependent_set(offset: float) -> ExampleSet:
    # e8 sits almost at the midpoint of e1 and e2: no two examples are close, but the
    # examples barely span one direction of parameter space.
    example_set = make_set()
    source = example_set.source_points.copy()
    source[8] = (source[1] + source[2]) / 2
    source[8, 0, 0] += offset
    return ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )


def test_near_singular_hyperplane_system_is_refused_with_its_condition_number():
    example_set = _nearly_affinely_dependent_set(1e-11)

    with pytest.raises(
        FitError, match=r"hyperplane system .*condition number [\d.]+e\+\d+ > 1e\+10"
    ) as info:
        fit(example_set, pca_threshold=1e-30)
    assert info.value.code == "singular_system"


def test_near_singular_hyperplane_system_is_fitted_with_noise_and_reported():
    example_set = _nearly_affinely_dependent_set(1e-11)

    rig = fit(example_set, pca_threshold=1e-30, noise=0.01)

    assert rig.fit_report["hyperplane_condition_number"] > 1e10
    assert np.isfinite(rig.fit_report["noise_gain"])


def test_hyperplane_condition_number_does_not_depend_on_the_length_unit(example_set, rig):
    in_mm = ExampleSet(
        example_set.names,
        example_set.source_points * 1000.0,
        example_set.target_vertices,
        example_set.target_faces,
    )
    scaled = fit(in_mm)

    assert scaled.fit_report["hyperplane_condition_number"] == pytest.approx(
        rig.fit_report["hyperplane_condition_number"], rel=1e-9
    )
    np.testing.assert_allclose(
        scaled.weights(in_mm.source_points * 1.0001),
        rig.weights(example_set.source_points * 1.0001),
        atol=1e-9,
    )


def test_strong_noise_amplification_warns_with_the_tolerable_noise_and_the_remedy():
    example_set = _nearly_affinely_dependent_set(1e-6)

    with pytest.warns(IdentifiabilityWarning, match="amplifies landmark noise") as caught:
        rig = fit(example_set, pca_threshold=1e-20)

    report = rig.fit_report
    message = next(str(w.message) for w in caught if "amplifies" in str(w.message))
    assert f"{report['noise_tolerance']:.2g} source units" in message
    assert "--noise SIGMA --clamp nonneg" in message
    assert report["noise_tolerance"] == pytest.approx(0.05 / report["noise_gain"])

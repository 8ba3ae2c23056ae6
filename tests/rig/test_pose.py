"""Head-pose refinement (rig/pose.py): its Jacobian, its fixed point, its degenerate cases."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from facecast.rig import ExampleSet, fit
from facecast.rig.pose import expression_basis, pose_condition, pose_jacobian, refine_pose

K = 8


def _basis(seed: int, k: int = K, rank: int = 10) -> np.ndarray:
    return expression_basis(np.random.default_rng(seed).normal(size=(rank, 3 * k)))


def test_basis_is_orthonormal_and_spans_every_direction():
    directions = np.random.default_rng(0).normal(size=(10, 3 * K))
    directions[9] = directions[0] + 2 * directions[1]  # rank 9

    basis = expression_basis(directions)

    assert basis.shape == (9, 3 * K)
    np.testing.assert_allclose(basis @ basis.T, np.eye(9), atol=1e-12)
    np.testing.assert_allclose(directions @ basis.T @ basis, directions, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.booleans())
def test_pose_jacobian_matches_finite_differences(seed, scale):
    points = np.random.default_rng(seed).normal(size=(K, 3))
    centred = points - points.mean(axis=0)
    jacobian = pose_jacobian(centred[None], scale=scale)[0]

    def moved(theta: np.ndarray) -> np.ndarray:
        rotation = Rotation.from_rotvec(theta[:3]).as_matrix()
        return ((1 + theta[6]) * centred @ rotation.T + theta[3:6]).reshape(-1)

    h = 1e-6
    for column in range(jacobian.shape[1]):
        theta = np.zeros(7)
        theta[column] = h
        numeric = (moved(theta) - moved(-theta)) / (2 * h)
        np.testing.assert_allclose(jacobian[:, column], numeric, atol=1e-7)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_refinement_undoes_a_small_rigid_motion_of_any_expression(seed):
    rng = np.random.default_rng(seed)
    reference = rng.normal(size=(K, 3))
    directions = rng.normal(size=(10, 3 * K))
    expression = reference + (rng.normal(size=10) @ directions).reshape(K, 3) * 0.1
    rotation = Rotation.from_rotvec(rng.uniform(-0.05, 0.05, 3)).as_matrix()
    centre = expression.mean(axis=0)
    moved = (expression - centre) @ rotation.T + centre + rng.uniform(-0.2, 0.2, 3)

    refined = refine_pose(moved[None], reference, expression_basis(directions))[0]

    np.testing.assert_allclose(refined, expression, atol=1e-9)


def test_refinement_passes_non_finite_and_degenerate_frames_through():
    reference = np.random.default_rng(4).normal(size=(K, 3))
    frames = np.stack([reference, reference, np.ones((K, 3))])
    frames[1, 2, 1] = np.inf

    refined = refine_pose(frames, reference, _basis(4))

    np.testing.assert_allclose(refined[0], reference, atol=1e-12)
    assert np.isinf(refined[1, 2, 1])
    assert np.isfinite(refined[2]).all()  # all points at one place: no rotation to find


def test_too_few_free_directions_have_no_pose_condition():
    reference = np.random.default_rng(5).normal(size=(K, 3))
    assert pose_condition(_basis(5, rank=3 * K - 5), reference) == float("inf")
    assert pose_condition(_basis(5, rank=3 * K - 6), reference, scale=True) == float("inf")
    assert np.isfinite(pose_condition(_basis(5, rank=3 * K - 6), reference))


def _random_rig(seed: int, m: int = 6):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(K, 3))
    source = neutral + np.concatenate([np.zeros((1, K, 3)), rng.normal(size=(m - 1, K, 3))])
    target = rng.normal(size=(m, 5, 3))
    names = ["neutral", *(f"e{i}" for i in range(1, m))]
    example_set = ExampleSet(names, source, target, np.array([[0, 1, 2]]))
    return fit(example_set, stable_points=[0, 1, 2]), source


def test_aligned_weights_with_scale_remove_a_uniform_scale_too():
    rig, source = _random_rig(6)
    rig.align_scale = True
    rotation = Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix()
    moved = 1.3 * source @ rotation.T + [2.0, 0.0, -1.0]

    assert np.abs(rig.weights(moved) - np.eye(6)).max() > 0.1
    np.testing.assert_allclose(rig.weights(moved, align=True), np.eye(6), atol=1e-8)


def test_calibrated_rig_refines_pose_in_the_performers_space():
    rig, source = _random_rig(7)
    turn = Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix()
    performer = 1.2 * source @ turn.T + [0.5, 0.0, -0.2]  # another face, the same expressions
    calibrated = rig.calibrated(performer[0])
    head = Rotation.from_rotvec([-0.1, 0.3, 0.05]).as_matrix()
    moved = performer @ head.T + [1.0, 2.0, 0.0]

    np.testing.assert_allclose(calibrated.weights(performer), np.eye(6), atol=1e-8)
    np.testing.assert_allclose(calibrated.weights(moved, align=True), np.eye(6), atol=1e-8)

"""Head-pose refinement (rig/pose.py): its Jacobian, its fixed point, its degenerate cases."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from facecast.rig import ExampleSet, fit
from facecast.rig.pose import (
    expression_complement,
    pose_condition,
    projected_pose_jacobian,
    refine_pose,
)

K = 8


def _complement(seed: int, k: int = K, rank: int = 10) -> np.ndarray:
    directions = np.random.default_rng(seed).normal(size=(rank, 3 * k))
    return expression_complement(directions)


def test_complement_is_orthonormal_and_orthogonal_to_every_direction():
    directions = np.random.default_rng(0).normal(size=(10, 3 * K))
    complement = expression_complement(directions)

    assert complement.shape == (3 * K - 10, 3 * K)
    np.testing.assert_allclose(complement @ complement.T, np.eye(3 * K - 10), atol=1e-12)
    np.testing.assert_allclose(directions @ complement.T, 0.0, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.booleans())
def test_projected_jacobian_matches_finite_differences(seed, scale):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(K, 3))
    complement = _complement(seed)
    centred = points - points.mean(axis=0)
    jacobian = projected_pose_jacobian(centred[None], complement.reshape(-1, K, 3), scale=scale)

    h = 1e-6

    def seen(theta: np.ndarray) -> np.ndarray:
        rotation = Rotation.from_rotvec(theta[:3]).as_matrix()
        out = (1 + theta[6]) * centred @ rotation.T + theta[3:6]
        return complement @ out.reshape(-1)

    for column in range(jacobian.shape[2]):
        theta = np.zeros(7)
        theta[column] = h
        numeric = (seen(theta) - seen(-theta)) / (2 * h)
        np.testing.assert_allclose(jacobian[0, :, column], numeric, atol=1e-7)


def test_refinement_undoes_a_small_rigid_motion_outside_the_expressions():
    rng = np.random.default_rng(3)
    reference = rng.normal(size=(K, 3))
    directions = rng.normal(size=(10, 3 * K))
    complement = expression_complement(directions)
    expression = reference + (rng.normal(size=10) @ directions).reshape(K, 3) * 0.1
    rotation = Rotation.from_rotvec([0.05, -0.03, 0.02]).as_matrix()
    moved = (expression - expression.mean(0)) @ rotation.T + expression.mean(0) + [0.1, 0, -0.2]

    refined = refine_pose(moved[None], reference, complement)[0]

    np.testing.assert_allclose(refined, expression, atol=1e-9)


def test_refinement_passes_non_finite_and_degenerate_frames_through():
    reference = np.random.default_rng(4).normal(size=(K, 3))
    complement = _complement(4)
    frames = np.stack([reference, reference, np.ones((K, 3))])
    frames[1, 2, 1] = np.inf

    refined = refine_pose(frames, reference, complement)

    np.testing.assert_allclose(refined[0], reference, atol=1e-12)
    assert np.isinf(refined[1, 2, 1])
    assert np.isfinite(refined[2]).all()  # all points at one place: no rotation to find


def test_too_few_free_directions_have_no_pose_condition():
    reference = np.random.default_rng(5).normal(size=(K, 3))
    assert pose_condition(_complement(5, rank=3 * K - 5), reference) == float("inf")
    assert pose_condition(_complement(5, rank=3 * K - 6), reference, scale=True) == float("inf")
    assert np.isfinite(pose_condition(_complement(5, rank=3 * K - 6), reference))


def test_aligned_weights_with_scale_remove_a_uniform_scale_too():
    rng = np.random.default_rng(6)
    neutral = rng.normal(size=(K, 3))
    m = 6
    source = neutral + np.concatenate([np.zeros((1, K, 3)), rng.normal(size=(m - 1, K, 3))])
    target = rng.normal(size=(m, 5, 3))
    names = ["neutral", *(f"e{i}" for i in range(1, m))]
    rig = fit(ExampleSet(names, source, target, np.array([[0, 1, 2]])), stable_points=[0, 1, 2])
    rig.align_scale = True
    rotation = Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix()
    moved = 1.3 * source @ rotation.T + [2.0, 0.0, -1.0]

    assert np.abs(rig.weights(moved) - np.eye(m)).max() > 0.1
    np.testing.assert_allclose(rig.weights(moved, align=True), np.eye(m), atol=1e-8)

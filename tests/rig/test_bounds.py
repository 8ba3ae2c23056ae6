"""Bounded weights are the exact metric projection (with an optional sparsity term).

They agree with SciPy's solvers, meet the QP's KKT conditions, and without the sparsity
term are the projection the rig made before it existed.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear, nnls

from facecast.rig.bounds import BoxProjection, project_box, sparsity_penalty
from facecast.rig.kernel import DISABLE_ENV, compiled


def _problem(seed, n=12, frames=40):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n + 5, n))
    metric = a.T @ a + 1e-3 * np.eye(n)
    return metric, rng.normal(scale=0.6, size=(frames, n))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_nonneg_projection_equals_nnls_in_the_metric(seed):
    metric, weights = _problem(seed)
    factor = np.linalg.cholesky(metric).T  # metric = factor.T @ factor
    expected = np.array([nnls(factor, factor @ w)[0] for w in weights])
    np.testing.assert_allclose(project_box(weights, metric, None), expected, atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_unit_box_projection_equals_bounded_least_squares(seed):
    metric, weights = _problem(seed, frames=10)
    factor = np.linalg.cholesky(metric).T
    expected = np.array(
        [lsq_linear(factor, factor @ w, bounds=(0, 1), tol=1e-13).x for w in weights]
    )
    np.testing.assert_allclose(project_box(weights, metric, 1.0), expected, atol=1e-6)


def test_feasible_weights_are_left_unchanged():
    metric, _ = _problem(1)
    weights = np.random.default_rng(2).uniform(0.05, 0.95, size=(8, 12))
    np.testing.assert_allclose(project_box(weights, metric, 1.0), weights, atol=1e-12)


@pytest.mark.parametrize("upper", [None, 1.0])
def test_projection_is_vectorised_frame_by_frame(upper):
    metric, weights = _problem(3)
    together = project_box(weights, metric, upper)
    alone = np.vstack([project_box(w[None], metric, upper) for w in weights])
    np.testing.assert_allclose(together, alone, atol=1e-12)


def _kkt_violation(x, weights, metric, upper, penalty):
    """Largest violation of the KKT conditions of min (x-w) H (x-w) + penalty 1^T x, bounds."""
    gradient = 2.0 * (x - weights) @ metric + penalty  # (B, N)
    scale = 1.0 + np.abs(2.0 * weights @ metric).max() + penalty
    at_low = x <= 0.0
    at_high = np.zeros_like(at_low) if upper is None else x >= upper
    free = ~(at_low | at_high)
    return max(
        float(-x.min()),  # x >= 0
        0.0 if upper is None else float((x - upper).max()),  # x <= upper
        float(np.abs(np.where(free, gradient, 0.0)).max()) / scale,  # stationary where free
        float(-np.where(at_low, gradient, 0.0).min()) / scale,  # pushing below 0 costs
        float(np.where(at_high, gradient, 0.0).max()) / scale,  # pushing above upper costs
    )


def _hard_problem(seed, n=30, frames=25):
    """An ill-conditioned metric (condition ~1e8) like a rig's with many close examples."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n + 2, n)) * np.logspace(0, -4, n)
    metric = a.T @ a + 1e-9 * np.eye(n)
    return metric, rng.normal(scale=0.3, size=(frames, n))


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from([None, 1.0]),
    st.floats(0.0, 3.0),
    st.booleans(),
)
def test_sparse_projection_meets_the_kkt_conditions(seed, upper, penalty, hard):
    metric, weights = (_hard_problem if hard else _problem)(seed)

    x = project_box(weights, metric, upper, penalty=penalty)

    assert _kkt_violation(x, weights, metric, upper, penalty) < 1e-9


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 5.0))
def test_sparse_projection_is_the_projection_of_the_shifted_weights(seed, penalty):
    # (x - w) H (x - w) + lambda 1^T x = (x - v) H (x - v) + const, H v = H w - lambda / 2.
    metric, weights = _problem(seed)
    factor = np.linalg.cholesky(metric).T
    shifted = weights - 0.5 * penalty * np.linalg.solve(metric, np.ones(len(metric)))
    expected = np.array([nnls(factor, factor @ v)[0] for v in shifted])

    np.testing.assert_allclose(project_box(weights, metric, None, penalty=penalty), expected,
                               atol=1e-9)  # fmt: skip


def _projection_before_the_sparsity_term(weights, metric, upper, max_iter=64):
    """project_box as it was before the sparsity term (commit f3690ae), kept as a reference."""
    n = weights.shape[1]
    target = weights @ metric
    at_low = weights < 0.0
    at_high = np.zeros_like(at_low) if upper is None else weights > upper
    eye = np.eye(n)
    x = weights
    for _ in range(max_iter):
        free = ~(at_low | at_high)
        both = free[:, :, None] & free[:, None, :]
        system = np.where(both, metric, 0.0) + np.where(free, 0.0, 1.0)[:, :, None] * eye
        fixed = np.where(at_high, upper if upper is not None else 0.0, 0.0)
        rhs = np.where(free, target - fixed @ metric, fixed)
        x = np.linalg.solve(system, rhs[:, :, None])[:, :, 0]
        gradient = (x - weights) @ metric
        tol = 1e-12 * (1.0 + np.abs(target))
        new_low = (free & (x < 0.0)) | (at_low & (gradient >= -tol))
        new_high = np.zeros_like(new_low)
        if upper is not None:
            new_high = (free & (x > upper)) | (at_high & (gradient <= tol))
            new_low &= ~new_high
        if np.array_equal(new_low, at_low) and np.array_equal(new_high, at_high):
            break
        at_low, at_high = new_low, new_high
    return np.clip(x, 0.0, upper)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_without_sparsity_the_projection_is_the_one_before_it_bit_for_bit(seed):
    metric, weights = _problem(seed)

    nonneg = project_box(weights, metric, None, penalty=0.0)

    np.testing.assert_array_equal(
        nonneg, _projection_before_the_sparsity_term(weights, metric, None)
    )
    # With an upper bound, a matrix product over the frames still pivoting rounds apart
    # from one over the whole batch by an ulp, so frame by frame is the exact comparison.
    for w in weights[:10, None]:
        np.testing.assert_array_equal(
            project_box(w, metric, 1.0, penalty=0.0),
            _projection_before_the_sparsity_term(w, metric, 1.0),
        )


@pytest.mark.parametrize("upper", [None, 1.0])
def test_sparse_projection_is_vectorised_frame_by_frame(upper):
    metric, weights = _hard_problem(4)
    together = project_box(weights, metric, upper, penalty=0.5)
    alone = np.vstack([project_box(w[None], metric, upper, penalty=0.5) for w in weights])
    np.testing.assert_allclose(together, alone, atol=1e-12)


def test_a_large_enough_penalty_zeroes_every_weight():
    metric, weights = _problem(5)
    # At x = 0 the gradient is -2 H w + lambda, non-negative once lambda >= 2 max(H w).
    penalty = 2.0 * float((weights @ metric).max()) + 1e-6

    assert not project_box(weights, metric, None, penalty=penalty).any()


def test_sparsity_penalty_is_twice_the_noise_variance_times_the_prior_rate():
    # Rate beta = sparsity * (M - 1) on each of the M - 1 weights: lambda = 2 s^2 beta.
    assert sparsity_penalty(0.1, 1.0, 56) == pytest.approx(2 * 0.01 * 55)
    assert sparsity_penalty(0.0, 3.0, 56) == 0.0
    assert sparsity_penalty(0.1, 0.0, 56) == 0.0


needs_kernel = pytest.mark.skipif(
    not compiled(), reason="facecast.rig._kernel is not built (no C compiler at install)"
)


@needs_kernel
@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from([None, 1.0]),
    st.floats(0.0, 3.0),
    st.booleans(),
)
def test_compiled_projection_meets_the_kkt_conditions_and_agrees_with_numpy(
    seed, upper, penalty, hard
):
    metric, weights = (_hard_problem if hard else _problem)(seed)
    box = BoxProjection(metric, upper, penalty)

    x = box(weights)

    assert box._solve is not None  # the compiled path ran
    assert _kkt_violation(x, weights, metric, upper, penalty) < 1e-9
    reference = project_box(weights, metric, upper, penalty=penalty)
    np.testing.assert_allclose(x, reference, rtol=0, atol=1e-8 * (1 + np.abs(reference).max()))


@needs_kernel
def test_compiled_projection_of_a_single_frame_equals_its_row_of_a_batch():
    metric, weights = _hard_problem(11)
    box = BoxProjection(metric, None, 0.5)

    together = box(weights)
    alone = np.vstack([box(w[None]) for w in weights])

    np.testing.assert_array_equal(together, alone)


def test_without_the_kernel_the_projection_is_numpys(monkeypatch):
    monkeypatch.setenv(DISABLE_ENV, "1")
    metric, weights = _problem(3)
    box = BoxProjection(metric, 1.0, 0.2)

    assert box._solve is None
    np.testing.assert_array_equal(box(weights), project_box(weights, metric, 1.0, penalty=0.2))

"""Bounded weights are the exact metric projection: they agree with SciPy's solvers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear, nnls

from facecast.rig.bounds import project_box


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

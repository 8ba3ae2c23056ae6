"""Bounded blend weights: the cardinal weights projected onto w >= 0 (or 0 <= w <= 1).

Batched block principal pivoting on a small convex QP, vectorised over frames; no fitting.
"""

from __future__ import annotations

import numpy as np

__all__ = ["project_box", "weight_metric"]


def weight_metric(params: np.ndarray, ridge: float) -> np.ndarray:
    """(M-1, M-1) metric on the non-neutral weights: how far a weight change moves p.

    Near the examples, sum_i w_i (p_i - p_0) ~ p - p_0, so a weight change dw moves the
    parameters by dw @ D (D the examples' displacements from the neutral) and costs
    |dw @ D|^2 = dw G dw with G = D D^T; the fit's ridge keeps it positive definite (and is
    the same noise prior the linear part was regularised with).
    """
    displacement = params[1:] - params[0]
    gram = displacement @ displacement.T
    floor = 1e-12 * max(float(np.trace(gram)), 1e-300)
    return gram + max(ridge, floor) * np.eye(len(gram))


def project_box(
    weights: np.ndarray, metric: np.ndarray, upper: float | None, *, max_iter: int = 64
) -> np.ndarray:
    """argmin_x (x - w) H (x - w) subject to 0 <= x (<= upper), for each row of ``weights``.

    Block principal pivoting (Judice & Pires 1994) batched over frames: every frame keeps its
    own free / at-zero / at-upper sets and all frames solve their reduced systems in one
    batched ``np.linalg.solve`` per iteration. Frames converge independently; the loop ends
    when none changes its sets (or after ``max_iter``, a bound no test has reached).

    Parameters
    ----------
    weights : (B, N) float
    metric : (N, N) symmetric positive definite H
    upper : float or None

    Returns
    -------
    (B, N) float
    """
    n = weights.shape[1]
    target = weights @ metric  # H w for each frame (H symmetric)
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

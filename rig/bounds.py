"""Bounded blend weights: the cardinal weights projected onto w >= 0 (or 0 <= w <= 1).

Batched block principal pivoting on a small convex QP, vectorised over frames (the numpy
reference), and ``BoxProjection``, a rig's fixed projection that runs it compiled; no fitting.
"""

from __future__ import annotations

import numpy as np

from .kernel import box_kernel

__all__ = [
    "BoxProjection",
    "project_box",
    "sparsity_penalty",
    "stream_sparsity",
    "weight_metric",
]

# Full exchanges a frame may make without reducing its count of infeasible variables before
# it falls back to single exchanges (Judice & Pires 1994's p; Kim & Park 2011 use 3).
_BACKUP_CHANCES = 3
#: The largest rate stream_sparsity gives (a still neutral face would otherwise make it
#: unbounded): the prior then expects a thousandth of an expression a frame.
MAX_STREAM_SPARSITY = 1e3
#: Pivoting steps a frame may take (a safety bound; no test has come near it).
_MAX_ITER = 200


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
    metric: np.ndarray = gram + max(ridge, floor) * np.eye(len(gram))
    return metric


def sparsity_penalty(noise: float, sparsity: float, num_examples: int) -> float:
    """The linear term lambda of the bounded projection for a sparsity prior on the weights.

    With landmark noise of variance s^2 per coordinate the projection's quadratic term is
    |dw @ D|^2 / (2 s^2) in log-likelihood units. An exponential prior of rate beta on each
    non-neutral weight (w_i >= 0, mean 1/beta) adds beta * sum_i w_i; scaled like the
    quadratic term that is lambda = 2 s^2 beta. ``sparsity`` is beta in units of the M - 1
    non-neutral examples, beta = sparsity * (M - 1): the prior expects a frame's non-neutral
    weights to add up to 1 / sparsity. No noise, no penalty: exact points need no prior.

    Parameters
    ----------
    noise : float
        Landmark noise standard deviation s (source units), >= 0.
    sparsity : float
        >= 0; 0 is no prior.
    num_examples : int
        M, the neutral included.

    Returns
    -------
    float
        lambda >= 0, in the units of the metric (source units squared).
    """
    return 2.0 * noise * noise * sparsity * (num_examples - 1)


def project_box(
    weights: np.ndarray,
    metric: np.ndarray,
    upper: float | None,
    *,
    penalty: float = 0.0,
    max_iter: int = _MAX_ITER,
) -> np.ndarray:
    """argmin_x (x - w) H (x - w) + penalty 1^T x subject to 0 <= x (<= upper), for each row.

    With ``penalty`` 0 this is the metric projection of ``w`` onto the bounds; with
    ``penalty`` lambda > 0 it is the MAP weights under Gaussian noise (the quadratic term)
    and an exponential sparsity prior on w >= 0 (the linear term; see ``sparsity_penalty``).
    The same QP either way: the linear term only shifts H w to H w - lambda / 2.

    Block principal pivoting (Judice & Pires 1994) batched over frames: every frame keeps its
    own free / at-zero / at-upper sets, exchanges all its infeasible variables at once, and
    falls back to exchanging one (the last) when that has not reduced their number for
    ``_BACKUP_CHANCES`` steps, which guarantees termination. Frames still pivoting solve
    their reduced systems in one batched ``np.linalg.solve`` per iteration; frames that
    have converged drop out. ``max_iter`` is a safety bound no test has reached.

    Parameters
    ----------
    weights : (B, N) float
        The unbounded weights w.
    metric : (N, N) symmetric positive definite H
    upper : float or None
    penalty : float
        lambda >= 0.
    max_iter : int

    Returns
    -------
    (B, N) float
    """
    n = weights.shape[1]
    target = weights @ metric  # H w for each frame (H symmetric)
    half = 0.5 * penalty
    start = weights
    if penalty:
        target = target - half
        # Start from the signs of the unbounded minimiser w - (lambda / 2) H^-1 1.
        start = weights - half * np.linalg.solve(metric, np.ones(n))
    low = start < 0.0
    high = None if upper is None else start > upper
    eye = np.eye(n)
    out = np.empty_like(target)
    # The frames still pivoting, and their rows of everything below; compacted only when
    # some finish, so a single frame never pays for indexing.
    rows = np.arange(len(weights))
    tol = 1e-12 * (1.0 + np.abs(target))
    best = np.full(len(weights), n + 1)  # fewest infeasible variables seen, per frame
    chances = np.full(len(weights), _BACKUP_CHANCES)
    # high is None exactly when upper is; the bound's value where high is used.
    top = 0.0 if upper is None else upper
    for _ in range(max_iter):
        free = ~low if high is None else ~(low | high)
        both = free[:, :, None] & free[:, None, :]
        system = np.where(both, metric, 0.0) + np.where(free, 0.0, 1.0)[:, :, None] * eye
        if high is None:
            rhs = np.where(free, target, 0.0)
        else:
            fixed = np.where(high, top, 0.0)
            rhs = np.where(free, target - fixed @ metric, fixed)
        x = np.linalg.solve(system, rhs[:, :, None])[:, :, 0]
        # Half the objective's gradient, H (x - w) + lambda / 2: >= 0 where x sits at 0,
        # <= 0 where it sits at the upper bound, 0 where it is free (KKT).
        gradient = (x - weights) @ metric
        if penalty:
            gradient += half
        to_low = free & (x < 0.0)
        infeasible = to_low | (low & (gradient < -tol))
        if high is not None:
            to_high = free & (x > top)
            infeasible |= to_high | (high & (gradient > tol))
        count = infeasible.sum(axis=1)
        done = count == 0
        if done.all():
            out[rows] = x
            break
        if done.any():
            out[rows[done]] = x[done]
            keep = ~done
            rows, weights, target, tol, low, best, chances = (
                a[keep] for a in (rows, weights, target, tol, low, best, chances)
            )
            x, infeasible, count, to_low = x[keep], infeasible[keep], count[keep], to_low[keep]
            if high is not None:
                high, to_high = high[keep], to_high[keep]
        improved = count < best
        best = np.minimum(best, count)
        chances = np.where(improved, _BACKUP_CHANCES, chances - 1)
        stalled = chances <= 0
        if stalled.any():
            # Murty's rule for the stalled frames: exchange only the last infeasible index.
            last = n - 1 - np.argmax(infeasible[:, ::-1], axis=1)
            only = np.arange(n) == last[:, None]
            infeasible = np.where(stalled[:, None], infeasible & only, infeasible)
        # Infeasible free variables go to the bound they cross; infeasible bound ones go free.
        low = (low & ~infeasible) | (to_low & infeasible)
        if high is not None:
            high = (high & ~infeasible) | (to_high & infeasible)
    else:
        out[rows] = x
    bounded: np.ndarray = np.clip(out, 0.0, upper)
    return bounded


class BoxProjection:
    """A rig's bounded-weights step, fixed at fit: ``project_box`` with its metric and bounds.

    Computes once what does not depend on the frame (the start's shift (lambda / 2) H^-1 1)
    and solves with the compiled kernel (``_kernel.project_box``: the same pivoting on the
    free variables only, ~100x faster for one frame) when it is built, else with
    `project_box`. The two agree to rounding.

    Parameters
    ----------
    metric : (N, N) float, symmetric positive definite
    upper : float or None
    penalty : float, >= 0
    """

    def __init__(self, metric: np.ndarray, upper: float | None, penalty: float) -> None:
        self.metric = np.ascontiguousarray(metric, dtype=np.float64)
        self.upper = upper
        self.penalty = float(penalty)
        self._half = 0.5 * self.penalty
        n = len(self.metric)
        self._shift = self._half * np.linalg.solve(self.metric, np.ones(n)) if penalty else None
        self._solve = box_kernel()

    def __call__(self, weights: np.ndarray) -> np.ndarray:
        """(B, N) bounded weights for the (B, N) unbounded ``weights``."""
        if self._solve is None:
            return project_box(weights, self.metric, self.upper, penalty=self.penalty)
        w = np.ascontiguousarray(weights, dtype=np.float64)
        out = np.empty_like(w)
        self._solve(self.metric, w, self._shift, self._half, out, self.upper, _MAX_ITER)
        return out


def stream_sparsity(weights: np.ndarray, window: int) -> np.ndarray:
    """Empirical-Bayes rates of the sparsity prior, read off the stream itself.

    The exponential prior's rate that maximises the likelihood of the recent frames'
    weights is one over their mean: for each frame, ``sparsity`` (in ``sparsity_penalty``'s
    units) = 1 / the mean over the ``window`` frames before it of the sum of the non-neutral
    weights. Causal, so a live session could run it; the first frame, with no past, gets 0.

    Parameters
    ----------
    weights : (F, N) float
        Bounded non-neutral weights of the stream (e.g. the plain projection's).
    window : int
        >= 1 frames.

    Returns
    -------
    (F,) float in [0, ``MAX_STREAM_SPARSITY``].
    """
    totals = np.clip(np.asarray(weights, dtype=np.float64), 0.0, None).sum(axis=1)
    cumulative = np.concatenate([[0.0], np.cumsum(totals)])
    index = np.arange(len(totals))
    start = np.maximum(index - int(window), 0)
    count = index - start
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = (cumulative[index] - cumulative[start]) / count
        rate = np.where((count > 0) & (mean > 0), 1.0 / mean, 0.0)
    return np.minimum(rate, MAX_STREAM_SPARSITY)

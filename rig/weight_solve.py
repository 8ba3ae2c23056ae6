"""Solving the cardinal weight functions (thesis eq. 3.2-3.13): PCA, hyperplanes, radial terms.

The math of ``fit`` on options already sanitised (fit_options.py): from the examples'
feature points to the coefficients a ``WeightModel`` holds. No rig, no report, no warnings.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg

from .errors import FitError
from .radial import evaluate_kernel, kernel_slope

__all__ = [
    "COINCIDE_RELATIVE",
    "EXACT_LINEAR",
    "MAX_CONDITION",
    "POINT_PRECISION",
    "check_separation",
    "fit_hyperplanes",
    "nearest_neighbours",
    "pca",
    "resolution_threshold",
    "solve_weights",
]

# Parameter vectors closer than this, relative to the spread of all examples, are taken
# to coincide: the radial system is singular there whatever the kernel.
COINCIDE_RELATIVE = 1e-4
# Points reach a rig as float32 (the protocol's frames, rig and example files): a coordinate
# x is known to eps32 |x|, so a difference of two to about eps32 * max|x| per coordinate.
POINT_PRECISION = float(np.finfo(np.float32).eps)
# Residuals of the hyperplanes below this are rounding: the radial part is then zero.
EXACT_LINEAR = 1e-10
# A radial or hyperplane system worse conditioned than this is not solved unregularised.
MAX_CONDITION = 1e10


def resolution_threshold(source_points: np.ndarray) -> float:
    """The smallest singular value of the centred displacements that is signal, not rounding.

    Each coordinate is known to ``POINT_PRECISION * max|x|`` (float32); rounding of that
    size on the (M, 3K) displacement matrix has singular values up to about that times
    sqrt(M) + sqrt(3K) (the edge of the Marchenko-Pastur law), so a principal axis whose
    singular value is above it stands above the input's numerical resolution.

    Parameters
    ----------
    source_points : (M, K, 3) float

    Returns
    -------
    float, in source units.
    """
    m, k, _ = source_points.shape
    step = POINT_PRECISION * float(np.abs(source_points).max())
    return step * float(np.sqrt(m) + np.sqrt(3 * k))


def pca(
    displacements: np.ndarray, relative_threshold: float | None, resolution: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Eq. 3.2-3.7: centre, eigen-decompose the covariance, keep the significant axes.

    ``relative_threshold`` None keeps every axis whose singular value is above
    ``resolution`` (``resolution_threshold``); a number keeps eigenvalues above that
    fraction of the largest. Returns mean (3K,), feature matrix F (n, 3K), eigenvalues (all,
    descending) and the relative eigenvalue threshold applied.
    """
    mean = displacements.mean(axis=0)  # eq. 3.4
    centred = displacements - mean
    # The SVD of the centred data gives the covariance's eigenvectors (eq. 3.5) without
    # forming the 3K x 3K matrix, and more accurately.
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    eigenvalues = singular**2 / max(len(displacements) - 1, 1)
    if eigenvalues[0] <= 0 or singular[0] <= resolution:
        raise FitError(
            "no example moves any feature point beyond the points' float precision: every "
            "source example equals the neutral; choose feature points that the expressions move"
        )
    if relative_threshold is None:
        relative_threshold = float((resolution / singular[0]) ** 2)
    keep = eigenvalues > relative_threshold * eigenvalues[0]
    return mean, vt[keep], eigenvalues, relative_threshold


def nearest_neighbours(params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    diff = params[:, None, :] - params[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    masked = dist + np.diag(np.full(len(params), np.inf))
    nearest = masked.argmin(axis=1)
    return dist, masked[np.arange(len(params)), nearest], nearest


def check_separation(
    names: Sequence[str], nearest_distance: np.ndarray, nearest: np.ndarray, spread: float
) -> None:
    tol = COINCIDE_RELATIVE * spread
    bad = np.flatnonzero(nearest_distance <= tol)
    if bad.size:
        i = int(bad[0])
        j = int(nearest[i])
        raise FitError(
            f"examples {names[i]!r} and {names[j]!r} have coinciding feature-point parameters "
            f"(distance {nearest_distance[i]:.3g}, {nearest_distance[i] / spread:.2g} of the "
            "examples' spread): no feature point tells them apart, so the radial system is "
            "singular. Add feature points that these expressions move, or drop one of them.",
            code="examples_coincide",
        )


def fit_hyperplanes(
    params: np.ndarray, lam: float, largest_singular: float
) -> tuple[np.ndarray, float, bool]:
    """Eq. 3.10: least-squares hyperplanes over [1, p] with w_i(p_j) = delta_ij, ridge ``lam``.

    Returns the coefficients (n + 1, M), the system's condition number, and whether the
    unregularised hyperplanes interpolate every example (the design [1, p] has full row
    rank M and is not near-singular). The parameters are scaled by one factor so that their
    largest singular value (``largest_singular``, the PCA's) equals the constant column's
    norm: the solution is the same, but the condition number (and the solver's accuracy) no
    longer depends on the source's length unit. Refused when near-singular without a
    ridge, as the radial system is. One SVD of the design gives both the condition number
    and, without a ridge, the solution.

    With a ridge the hyperplanes are anchored at the neutral, w(p) = e_0 + (p - p_0) C with
    lam |C|^2: the prior the ridge stands for is then "the face at rest" (weights near 0,
    the neutral's near 1), not "the average example" (every weight 1 / M) that an
    intercept left free shrinks towards. On linear data this is the MAP weights under
    landmark noise and a Gaussian prior on the weights (ridge regression on the example
    displacements), which the bounded projection's metric (``bounds.weight_metric``, the
    same ridge) then bounds exactly. The weights still sum to 1: C 1 = 0.
    """
    m, n = params.shape
    scale = np.sqrt(m) / largest_singular
    design = np.hstack([np.ones((m, 1)), params * scale])
    u, singular, vt = np.linalg.svd(design, full_matrices=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    well_posed = bool(np.isfinite(condition) and condition <= MAX_CONDITION)
    exact = well_posed and m <= n + 1
    identity = np.eye(m)
    if lam > 0:
        # lam |C|^2 on the unscaled slopes C = scale * C_scaled, fitted to e_j - e_0 at the
        # examples' displacements from the neutral (the neutral's own row is exact).
        displacement = (params[1:] - params[0]) * scale
        reg = np.sqrt(lam) * scale * np.eye(n)
        steps = identity[1:] - identity[0]
        slopes = scipy.linalg.lstsq(
            np.vstack([displacement, reg]), np.vstack([steps, np.zeros((n, m))])
        )[0]
        slopes *= scale
        return np.vstack([identity[0] - params[0] @ slopes, slopes]), condition, exact
    if not well_posed:
        raise FitError(
            f"the hyperplane system [1, p] is near-singular (condition number "
            f"{condition:.3g} > {MAX_CONDITION:.0e}): the examples barely span some kept "
            "principal axis, so exact interpolation along it divides by almost nothing. "
            "Raise --pca-threshold (e.g. 1e-10), set --noise to regularise, or add "
            "feature points",
            code="singular_system",
        )
    coeffs = vt.T @ (u.T / singular[:, None])  # the least-squares solution for I
    coeffs[1:] *= scale
    return coeffs, condition, exact


def solve_weights(
    params: np.ndarray,
    dist: np.ndarray,
    alpha: np.ndarray,
    kernel: str,
    lam: float,
    largest_singular: float,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Eq. 3.10-3.13 at ridge ``lam``: hyperplane and radial coefficients, and the condition
    numbers of the hyperplane and radial systems.

    ``dist`` (M, M) are the examples' parameter distances, ``alpha`` (M,) the dilations.
    """
    m = params.shape[0]
    # Linear approximation, eq. 3.10: hyperplanes over [1, p] fitted to w_i(p_j) = delta_ij.
    # The ridge leaves the constant column free, so the hyperplanes still sum to 1.
    linear_coeffs, hyperplane_condition, linear_exact = fit_hyperplanes(
        params, lam, largest_singular
    )
    identity = np.eye(m)
    design = np.hstack([np.ones((m, 1)), params])
    residuals = identity - design @ linear_coeffs  # eq. 3.11, residuals[j, i] at example j

    # Radial part, eq. 3.12-3.13: R_j(p) = B(|p - p_j| / alpha_j), alpha_j = nearest distance,
    # so the B-spline's support radius (2 alpha_j) is twice that distance.
    basis = evaluate_kernel(kernel, dist / alpha[None, :])  # basis[j, l] = R_l(p_j)
    condition = float(np.linalg.cond(basis))
    if lam > 0:
        # Each radial term passes on noise in proportion to its slope / alpha_l.
        slope = kernel_slope(kernel) / alpha
        penalty = np.diag(lam * slope * slope)
        radial_coeffs = scipy.linalg.solve(
            basis.T @ basis + penalty, basis.T @ residuals, assume_a="pos"
        )
    else:
        if not np.isfinite(condition) or condition > MAX_CONDITION:
            raise FitError(
                f"the radial system is near-singular (condition number {condition:.3g} > "
                f"{MAX_CONDITION:.0e}) with kernel {kernel!r}; use the cubic B-spline, set "
                "--noise to regularise, or add feature points",
                code="singular_system",
            )
        radial_coeffs = scipy.linalg.solve(basis, residuals)
    if np.abs(residuals).max() <= EXACT_LINEAR or (lam > 0 and linear_exact):
        # The hyperplanes already interpolate every example (M - 1 <= n and the examples are
        # affinely independent): the radial terms would only fit rounding noise, and with a
        # ridge the residuals are its deliberate shrinkage, which radial terms fitted to them
        # would undo near each example (they cloned every real take and ICT's mixes worse,
        # README "Real takes"). Exact zeros let evaluation skip them.
        radial_coeffs = np.zeros_like(radial_coeffs)

    return linear_coeffs, radial_coeffs, hyperplane_condition, condition

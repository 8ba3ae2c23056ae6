"""Fitting a rig: parameterization, PCA and cardinal-basis weight functions (thesis ch. 3).

Everything that does not depend on a frame is computed here, once; evaluation lives in
``rig.Rig``. No file I/O.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.linalg

from .basis import BasisBuild
from .bounds import sparsity_penalty
from .errors import FitError
from .examples import ExampleSet
from .radial import KERNELS, evaluate_kernel, kernel_derivative, kernel_slope
from .rig import Rig, WeightModel

__all__ = [
    "CLAMP_MODES",
    "FitReport",
    "IdentifiabilityWarning",
    "fit",
    "fit_weight_model",
    "refit_noise",
    "resolution_threshold",
]

CLAMP_MODES = (None, "none", "nonneg", "unit")
# clamp None (the default) chooses: bounded ("nonneg") when fitted for noise, where every
# unbounded noise rig cloned real takes worse than NNLS (README "Real takes"); unbounded
# without noise, where exact interpolation needs no bounds. "none" asks for unbounded.
NOISE_CLAMP = "nonneg"
# The sparsity prior's default: none, the plain metric projection. Chosen on real takes
# (tests/data/livelink, README "Real takes"): an iPhone's ARKit weights hold 4-10
# expressions' worth a frame, many small weights at once, and every exponential prior tried
# (1, the take's own rate, per-shape rates) cloned them worse than none at sigma = 0.5 mm.
# On synthetic sparse mixes the prior helps; --sparsity 1 asks for it.
DEFAULT_SPARSITY = 0.0

# Parameter vectors closer than this, relative to the spread of all examples, are taken
# to coincide: the radial system is singular there whatever the kernel.
COINCIDE_RELATIVE = 1e-4
# Examples whose nearest neighbour is closer than this fraction of the median nearest
# distance collapse together: distinguishable only in the absence of any noise.
COLLAPSE_RELATIVE = 0.05
# Points reach a rig as float32 (the protocol's frames, rig and example files): a coordinate
# x is known to eps32 |x|, so a difference of two to about eps32 * max|x| per coordinate.
POINT_PRECISION = float(np.finfo(np.float32).eps)
# Residuals of the hyperplanes below this are rounding: the radial part is then zero.
EXACT_LINEAR = 1e-10
# A radial or hyperplane system worse conditioned than this is not solved unregularised.
MAX_CONDITION = 1e10
# The noise-gain check: the landmark noise that moves the weights by NOISE_WEIGHT_CHANGE
# (RMS) is the rig's noise tolerance. Below NOISE_FLOOR_RELATIVE of the feature points'
# extent (2 um on a 20 cm face, 50 times finer than marker-based capture's ~0.1 mm) no real
# tracker can feed the rig, so fit warns. ICT-FaceKit fitted exactly sits at 5e-7, the demo
# at 2e-4, ICT at --noise 0.1 mm at 1e-4: a decade or more either side.
NOISE_WEIGHT_CHANGE = 0.05
NOISE_FLOOR_RELATIVE = 1e-5
# Landmark noise above this many times the feature points' extent is refused: it could not
# be told from no tracking at all, and its square overflows the regularised fit.
NOISE_MAX_RELATIVE = 10.0


class IdentifiabilityWarning(UserWarning):
    """Some examples lie so close in parameter space that noise makes them indistinguishable.

    Two examples collapsing together, or the examples barely spanning some direction, so
    that landmark noise far below any tracker's swings the weights (the noise-gain check).
    """


@dataclass
class FitReport:
    """What ``fit`` found: the numbers ``facecast fit`` prints and the rig file keeps."""

    num_examples: int
    num_points: int
    num_vertices: int
    kernel: str
    noise: float
    pca_threshold: float
    eigenvalues: list[float]
    components_kept: int
    condition_number: float
    linear_ridge: float
    fit_seconds: float
    # The bounds on the weights, and the sparsity prior on bounded weights
    # (bounds.sparsity_penalty): its setting and the linear term lambda it gives at this
    # noise (used only with a clamp).
    clamp: str | None = None
    sparsity: float = 0.0
    sparsity_penalty: float = 0.0
    # Per example: distance to the nearest other example in the kept space, and its name.
    nearest_distance: list[float] = field(default_factory=list)
    nearest_name: list[str] = field(default_factory=list)
    # Per example: nearest distance / noise (inf without noise): how many noise standard
    # deviations separate the example from its nearest neighbour.
    separation_snr: list[float] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    # How much landmark noise of unit standard deviation moves the weights (RMS over the
    # examples): the cost of the kept components.
    noise_gain: float = 0.0
    # The landmark noise (source units) that moves the weights by NOISE_WEIGHT_CHANGE RMS,
    # NOISE_WEIGHT_CHANGE / noise_gain, and the feature points' extent it is judged against
    # (the diagonal of their bounding box over all source examples).
    noise_tolerance: float = float("inf")
    feature_extent: float = 0.0
    # Condition number of the hyperplanes' least-squares system [1, s p] (eq. 3.10), the
    # parameters scaled by one factor s so their largest singular value matches the constant
    # column's: unit-free, and sqrt(largest / smallest kept PCA eigenvalue) since p is centred.
    # Without the ridge: it is what --noise has to tame.
    hyperplane_condition_number: float = 1.0
    # Head-pose removal (Rig.weights(align=True)): the feature points it aligns on first
    # (None: the set named none, so all of them, jaw and lips included) and the condition
    # number of the pose refinement against the examples' span (inf: not possible, the
    # stable-point alignment stands alone).
    stable_points: list[int] | None = None
    pose_condition: float = float("inf")
    # The fit's two parts by their own clocks: the math of this module (wall time of the
    # fitting thread), and building the (M, 3V) float32 blend basis (memory-bound,
    # proportional to the target's vertices; the CPU time of the threads that built it,
    # summed: BasisBuild.seconds). With basis_overlapped a worker thread built the basis
    # beside the math and the caller finished it, so fit_seconds (wall) is about the longer
    # of the math and half the two parts' sum; without, about their sum.
    math_seconds: float = 0.0
    basis_seconds: float = 0.0
    basis_overlapped: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _sanitize(
    example_set: object,
    kernel: str,
    noise: float,
    pca_threshold: float | None,
    ridge: float | None,
    clamp: str | None,
    sparsity: float | None,
) -> tuple[str, float, float | None, float | None, str | None, float]:
    """Checked and normalised ``fit`` options: kernel, noise, pca_threshold, ridge, clamp
    (None or a bound), sparsity."""
    if not isinstance(example_set, ExampleSet):
        raise TypeError(f"expected an ExampleSet, got {type(example_set).__name__}")
    if kernel not in KERNELS:
        raise FitError(f"unknown kernel {kernel!r}; expected one of {', '.join(KERNELS)}")
    noise = float(noise)
    if not np.isfinite(noise) or noise < 0:
        raise FitError(f"noise must be a finite number >= 0, got {noise}")
    extent = _extent(example_set.source_points)
    if noise > NOISE_MAX_RELATIVE * extent:
        # Noise beyond the face itself means nothing, and its square overflows the fit.
        raise FitError(
            f"noise {noise:g} is more than {NOISE_MAX_RELATIVE:g}x the feature points' extent "
            f"{extent:.3g}: give the landmark noise in the source's units",
            code="noise_too_large",
        )
    if pca_threshold is not None:
        pca_threshold = float(pca_threshold)
    if pca_threshold is not None and not (0.0 <= pca_threshold < 1.0):
        raise FitError(
            f"pca_threshold is relative to the largest eigenvalue: expected [0, 1), got "
            f"{pca_threshold}"
        )
    if ridge is not None:
        ridge = float(ridge)
        if not np.isfinite(ridge) or ridge < 0:
            raise FitError(f"ridge must be a finite number >= 0, got {ridge}")
    if clamp not in CLAMP_MODES:
        raise FitError(f"clamp must be one of {CLAMP_MODES}, got {clamp!r}")
    explicit_clamp = clamp
    if clamp is None:
        clamp = NOISE_CLAMP if noise > 0 else None
    elif clamp == "none":
        clamp = None
    if sparsity is None:
        sparsity = DEFAULT_SPARSITY
    else:
        sparsity = float(sparsity)
        if not np.isfinite(sparsity) or sparsity < 0:
            raise FitError(f"sparsity must be a finite number >= 0, got {sparsity}")
        if sparsity > 0 and explicit_clamp in (None, "none"):
            raise FitError(
                "sparsity is a prior on bounded weights: it needs clamp 'nonneg' or 'unit'",
                code="sparsity_without_clamp",
            )
    return kernel, noise, pca_threshold, ridge, clamp, sparsity


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


def _pca(
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


def _nearest(params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    diff = params[:, None, :] - params[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    masked = dist + np.diag(np.full(len(params), np.inf))
    nearest = masked.argmin(axis=1)
    return dist, masked[np.arange(len(params)), nearest], nearest


def _check_separation(
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


def _fit_hyperplanes(
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


def fit(
    example_set: ExampleSet,
    *,
    pca_threshold: float | None = None,
    noise: float = 0.0,
    kernel: str = "bspline",
    ridge: float | None = None,
    clamp: str | None = None,
    sparsity: float | None = None,
    stable_points: npt.ArrayLike | None = None,
    align_scale: bool = False,
    basis_thread: bool = True,
) -> Rig:
    """Fit the cardinal-basis weight functions of an example set (thesis section 3).

    Parameters
    ----------
    example_set : ExampleSet
        M paired examples, the neutral first.
    pca_threshold : float, optional
        Drop principal axes whose eigenvalue is below this fraction of the largest (the
        thesis's threshold, made scale-free). Default: keep every axis that stands above
        the input's numerical resolution (``resolution_threshold``: float32 precision of
        the feature points' coordinates), so clean input is as exact as least squares;
        robustness to tracker noise is ``noise``'s job. The report keeps the fraction used.
    noise : float
        Expected landmark noise (standard deviation per coordinate, source units). 0 is
        exact interpolation, the thesis's behaviour. Above 0 the linear and radial parts are
        regularised for the error they would pass on from noise of that size (a ridge of
        M * noise^2 on the hyperplanes; on each radial term, scaled by its slope), trading
        exactness at the examples for stability between them. Whatever the noise, when
        landmark noise below 1e-5 of the feature points' extent (``NOISE_FLOOR_RELATIVE``)
        already moves the fitted weights by 0.05 RMS, fit warns (``IdentifiabilityWarning``)
        that the rig amplifies noise; the report keeps that noise as ``noise_tolerance``.
    kernel : {"bspline", "gaussian", "thin_plate", "linear"}
        Radial cross-section; the thesis's cubic B-spline by default.
    ridge : float, optional
        Override the regularisation strength derived from ``noise`` (finer knob).
    clamp : {None, "none", "nonneg", "unit"}
        Bound the non-neutral weights to >= 0 or to [0, 1] at evaluation. Default (None):
        "nonneg" when ``noise`` is above 0 (unbounded noise rigs cloned real takes worse
        than NNLS; bounded ones better), unbounded without noise; "none" is unbounded
        whatever the noise. Bounding projects the cardinal weights onto the bounds in the metric of the examples' parameter
        displacements (plus the noise ridge), i.e. the nearest bounded weights as the feature
        points see them, not a plain clip. The neutral's weight keeps the sum at 1.
        With ``noise`` above 0 the projection is the MAP weights under that landmark noise and
        a sparsity prior (see ``sparsity``).
    sparsity : float, optional
        Rate of an exponential prior on each bounded non-neutral weight, in units of the
        M - 1 non-neutral examples: the prior expects a frame's non-neutral weights to add
        up to 1 / sparsity (faces show few expressions at once). The bounded projection
        then minimises (x - w) H (x - w) + lambda 1^T x with lambda = 2 noise^2 sparsity
        (M - 1) (``bounds.sparsity_penalty``), so it vanishes without noise. Default 0,
        the plain metric projection (``DEFAULT_SPARSITY``: real performances carry many
        small weights at once; 1 suits sparse mixes). Giving it without ``clamp`` is an
        error.
    stable_points : (S,) int, optional
        Feature points (positions among the K) that head-pose alignment
        (``Rig.weights(align=True)``) fits the head's rigid motion on first; default the
        example set's ``stable_points``, else all K points. The report says which
        (``stable_points``) and whether the pose refinement against the examples' span
        that follows is possible (``pose_condition``).
    align_scale : bool
        Whether head-pose alignment also removes uniform scale.
    basis_thread : bool
        Build the blend basis in a worker thread while the math runs (the basis depends
        only on the target examples, the math only on the sources, and both release the
        GIL in their array code); the caller, done with the math, builds the rows the
        worker has not reached (``basis.BasisBuild``). On two free cores the fit then takes
        about the longer of the math and half the two parts' sum. False builds it after the
        math in the caller's thread. The rig is the same bit for bit either way; an exception from
        either part reaches the caller.
    """
    started = time.perf_counter()
    kernel, noise, pca_threshold, ridge, clamp, sparsity = _sanitize(
        example_set, kernel, noise, pca_threshold, ridge, clamp, sparsity
    )
    building = BasisBuild(example_set.target_vertices, thread=basis_thread)
    try:
        model, report = _fit_weights(
            example_set.names,
            example_set.source_points,
            example_set.num_vertices,
            kernel=kernel,
            noise=noise,
            pca_threshold=pca_threshold,
            ridge=ridge,
            clamp=clamp,
            sparsity=sparsity,
        )
        report.math_seconds = time.perf_counter() - started
        building.help()  # the rows the worker has not reached yet, from the other end
    finally:
        # Joined whatever happened: no fit leaves a thread behind.
        building.wait()
    blend_basis = building.result()
    report.basis_seconds = building.seconds
    report.basis_overlapped = basis_thread

    tail_started = time.perf_counter()
    rig = Rig.from_fit(
        names=example_set.names,
        model=model,
        target_vertices=example_set.target_vertices,
        target_faces=example_set.target_faces,
        feature_indices=example_set.feature_indices,
        source_preview=(
            None
            if example_set.source_vertices is None or example_set.source_faces is None
            else (example_set.source_vertices[0], example_set.source_faces)
        ),
        stable_points=example_set.stable_points if stable_points is None else stable_points,
        align_scale=align_scale,
        report={},
        blend_basis=blend_basis,
    )
    if rig.stable_points is not None:
        report.stable_points = [int(i) for i in rig.stable_points]
    # The head-pose refinement's span and condition number: math of the fit, not basis.
    report.pose_condition = rig.pose_condition(scale=align_scale)
    finished = time.perf_counter()
    report.math_seconds += finished - tail_started
    report.fit_seconds = finished - started
    rig.fit_report = report.to_dict()
    return rig


def fit_weight_model(
    names: Sequence[str],
    source_points: np.ndarray,
    *,
    noise: float,
    kernel: str,
    clamp: str | None,
    sparsity: float = DEFAULT_SPARSITY,
) -> tuple[WeightModel, FitReport]:
    """The weight model alone of M source examples (K, 3), the neutral first, and its report.

    ``fit``'s math without target examples, options already valid (``clamp`` None or a
    bound), warnings kept in the report rather than issued: for refitting a rig's weights
    on other source examples (``rebase``) where no caller is there to see a warning.
    """
    points = np.ascontiguousarray(source_points, dtype=np.float64)
    return _fit_weights(
        tuple(names), points, 0, kernel=kernel, noise=float(noise), pca_threshold=None,
        ridge=None, clamp=clamp, sparsity=float(sparsity), emit=False,
    )  # fmt: skip


def _fit_weights(
    names: Sequence[str],
    source_points: np.ndarray,
    num_vertices: int,
    *,
    kernel: str,
    noise: float,
    pca_threshold: float | None,
    ridge: float | None,
    clamp: str | None,
    sparsity: float,
    emit: bool = True,
) -> tuple[WeightModel, FitReport]:
    """The fit's math on sanitised options: the weight model and its report (no basis).

    ``emit``: issue the report's warnings (``IdentifiabilityWarning``) as well as keep them.
    """
    m, k, _ = source_points.shape

    source_neutral = source_points[0]
    displacements = (source_points - source_neutral).reshape(m, 3 * k)  # eq. 3.1
    mean, features, eigenvalues, pca_threshold = _pca(
        displacements, pca_threshold, resolution_threshold(source_points)
    )
    params = (displacements - mean) @ features.T  # eq. 3.7, (M, n)
    n = params.shape[1]

    dist, nearest_distance, nearest = _nearest(params)
    spread = float(dist.max())
    _check_separation(names, nearest_distance, nearest, spread)

    noise_var = noise * noise
    lam = m * noise_var if ridge is None else ridge
    alpha = nearest_distance.copy()
    largest_singular = float(np.sqrt(eigenvalues[0] * max(m - 1, 1)))
    linear_coeffs, radial_coeffs, hyperplane_condition, condition = _solve_weights(
        params, dist, alpha, kernel, lam, largest_singular
    )

    model = WeightModel(
        kernel=kernel,
        source_neutral=source_neutral,
        mean=mean,
        features=features,
        params=params,
        linear_coeffs=linear_coeffs,
        radial_coeffs=radial_coeffs,
        alpha=alpha,
        clamp=clamp,
        ridge=float(lam),
        sparsity_penalty=sparsity_penalty(noise, sparsity, m),
    )

    report = FitReport(
        num_examples=m,
        num_points=k,
        num_vertices=num_vertices,
        kernel=kernel,
        noise=noise,
        pca_threshold=pca_threshold,
        eigenvalues=[float(e) for e in eigenvalues],
        components_kept=n,
        condition_number=condition,
        hyperplane_condition_number=hyperplane_condition,
        linear_ridge=float(lam),
        fit_seconds=0.0,
        clamp=clamp,
        sparsity=sparsity,
        sparsity_penalty=model.sparsity_penalty,
        nearest_distance=[float(d) for d in nearest_distance],
        nearest_name=[names[int(j)] for j in nearest],
        separation_snr=[float(d / noise) if noise > 0 else float("inf") for d in nearest_distance],
    )
    _warn_collapsing(report, names, noise, emit)
    report.noise_gain = _noise_gain(model, dist)
    _warn_noise_gain(report, source_points, noise, clamp, emit)
    return model, report


def refit_noise(rig: Rig, noise: float) -> Rig:
    """``rig`` regularised for another landmark noise, from what the rig keeps.

    The weight functions depend on the examples only through their parameters, which the
    rig stores, so the hyperplanes and radial terms are solved again at the ridge
    ``M * noise^2`` (as ``fit(..., noise=noise)`` with no ``ridge`` override would) and
    the sparsity prior's penalty follows the noise; the targets, bounds, calibration and
    head pose stay. ``facecast clone`` uses it for points that a smoother left less noisy
    than the rig was fitted for (``rig.smoothing``).

    Parameters
    ----------
    rig : Rig
    noise : float
        > 0, the std left in the points the new rig will see (source units).

    Returns
    -------
    Rig, with ``fit_report["noise"]`` the new noise and ``fitted_noise`` the old one.
    """
    sigma = float(noise)
    if not (np.isfinite(sigma) and sigma > 0):
        raise FitError(f"refit noise must be a finite number > 0, got {noise}")
    report = dict(rig.fit_report or {})
    sparsity = report.get("sparsity", DEFAULT_SPARSITY)
    models = []
    for model in rig.models:
        params = model.params
        m = params.shape[0]
        lam = m * sigma * sigma
        dist, _, _ = _nearest(params)
        largest_singular = float(np.linalg.svd(params, compute_uv=False)[0])
        linear_coeffs, radial_coeffs, _, _ = _solve_weights(
            params, dist, model.alpha, model.kernel, lam, largest_singular
        )
        models.append(
            replace(
                model,
                linear_coeffs=linear_coeffs,
                radial_coeffs=radial_coeffs,
                ridge=lam,
                sparsity_penalty=sparsity_penalty(sigma, sparsity, m),
            )
        )
    report["fitted_noise"] = report.get("fitted_noise", report.get("noise", 0.0))
    report["noise"] = sigma
    report["linear_ridge"] = float(rig.models[0].params.shape[0] * sigma * sigma)
    return rig.with_weight_models(tuple(models), report)


def _solve_weights(
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
    linear_coeffs, hyperplane_condition, linear_exact = _fit_hyperplanes(
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


def _warn_collapsing(report: FitReport, names: Sequence[str], noise: float, emit: bool) -> None:
    nearest = np.asarray(report.nearest_distance)
    median = float(np.median(nearest))
    for i, d in enumerate(nearest):
        other = report.nearest_name[i]
        if d < COLLAPSE_RELATIVE * median:
            msg = (
                f"examples {names[i]!r} and {other!r} nearly collapse together: distance "
                f"{d:.3g} is {d / median:.2g} of the median nearest distance; landmark noise "
                "will swap their weights. Add feature points that tell them apart, or drop one."
            )
        elif noise > 0 and d < 3.0 * noise * np.sqrt(2.0):
            msg = (
                f"example {names[i]!r} is within {d / noise:.2g} noise standard deviations of "
                f"{other!r}: at --noise {noise:g} the two cannot be told apart reliably"
            )
        else:
            continue
        _warn(report, msg, emit)


def _warn(report: FitReport, message: str, emit: bool) -> None:
    if message not in report.warnings:
        report.warnings.append(message)
        if emit:
            # Past _warn, its check, _fit_weights and fit: the line that called fit.
            warnings.warn(message, IdentifiabilityWarning, stacklevel=5)


def _extent(source_points: np.ndarray) -> float:
    """The diagonal of the feature points' bounding box over every example."""
    flat = source_points.reshape(-1, 3)
    return float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))


def _warn_noise_gain(
    report: FitReport, source_points: np.ndarray, noise: float, clamp: str | None, emit: bool
) -> None:
    """Warn when landmark noise far below any tracker's already moves the weights.

    Judged on the rig as fitted, whatever ``noise`` was: at 0 (exact interpolation) this is
    the usual cause; above 0 it means the given noise is far below any tracker's.
    """
    extent = _extent(source_points)
    tolerance = NOISE_WEIGHT_CHANGE / report.noise_gain if report.noise_gain > 0 else np.inf
    report.noise_tolerance = float(tolerance)
    report.feature_extent = extent
    if not tolerance < NOISE_FLOOR_RELATIVE * extent:
        return
    fitted = "--noise 0, exact interpolation" if noise == 0 else f"--noise {noise:g}"
    advice = "--noise SIGMA" if clamp is not None else "--noise SIGMA --clamp nonneg"
    _warn(
        report,
        f"the rig amplifies landmark noise (noise gain {report.noise_gain:.4g} at {fitted}): "
        f"noise of only {tolerance:.2g} source units, {tolerance / extent:.1g} of the feature "
        f"points' extent {extent:.3g} and far below any tracker's, moves the weights by "
        f"{NOISE_WEIGHT_CHANGE:g} RMS. For tracked input fit with {advice}, SIGMA the "
        "tracker's landmark noise in source units",
        emit,
    )


def _noise_gain(model: WeightModel, dist: np.ndarray) -> float:
    """RMS over the examples of |dw/dp|_F: how far unit landmark noise moves the weights.

    F has orthonormal rows, so isotropic noise of standard deviation s on the points is
    isotropic noise s on p, and the weights move by s |dw/dp|_F to first order.
    ``dist`` (M, M) holds |p_k - p_j| between the model's examples (``_nearest``'s).
    """
    slopes = model.linear_coeffs[1:]  # (n, M): the hyperplanes' part of every Jacobian
    if not np.any(model.radial_coeffs):
        # No radial terms (the hyperplanes interpolate): the Jacobian is the slopes at every
        # example, and its RMS over them the slopes' norm.
        return float(np.sqrt(np.vdot(slopes, slopes)))
    params = model.params
    m = len(params)
    # diff[k, :, j] = p_k - p_j, laid out (M, n, M) so the radial part below is one product.
    diff = params[:, :, None] - params.T[None, :, :]
    t = dist / model.alpha[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(dist > 0, kernel_derivative(model.kernel, t) / (model.alpha * dist), 0.0)
    # d R_j / d p at p_k = B'(t_kj) (p_k - p_j) / (alpha_j |p_k - p_j|), summed over j
    # against the radial coefficients for every k at once: one (M n, M) @ (M, M) product.
    diff *= scale[:, None, :]
    jacobian = (diff.reshape(-1, m) @ model.radial_coeffs).reshape(m, -1, m)
    jacobian += slopes[None, :, :]  # (M, n, M)
    return float(np.sqrt(np.vdot(jacobian, jacobian) / m))

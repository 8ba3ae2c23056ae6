"""Fitting a rig: parameterization, PCA and cardinal-basis weight functions (thesis ch. 3).

Everything that does not depend on a frame is computed here, once; evaluation lives in
``rig.Rig``. No file I/O. The options are checked in fit_options.py, the weight functions
solved in weight_solve.py, the report and its warnings made in fit_report.py.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from .basis import BasisBuild
from .bounds import sparsity_penalty
from .errors import FitError
from .examples import ExampleSet
from .fit_options import CLAMP_MODES, DEFAULT_SPARSITY, NOISE_MAX_RELATIVE, sanitize_fit_options
from .fit_report import (
    NOISE_WEIGHT_CHANGE,
    FitReport,
    IdentifiabilityWarning,
    noise_gain,
    warn_collapsing,
    warn_noise_gain,
)
from .rig import Rig, WeightModel
from .weight_solve import (
    check_separation,
    nearest_neighbours,
    pca,
    resolution_threshold,
    solve_weights,
)

__all__ = [
    "CLAMP_MODES",
    "NOISE_MAX_RELATIVE",
    "NOISE_WEIGHT_CHANGE",
    "FitReport",
    "IdentifiabilityWarning",
    "fit",
    "fit_weight_model",
    "refit_noise",
    "resolution_threshold",
]


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
    kernel, noise, pca_threshold, ridge, clamp, sparsity = sanitize_fit_options(
        example_set, kernel, noise, pca_threshold, ridge, clamp, sparsity
    )
    building = BasisBuild(example_set.targets, thread=basis_thread)
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
    mean, features, eigenvalues, pca_threshold = pca(
        displacements, pca_threshold, resolution_threshold(source_points)
    )
    params = (displacements - mean) @ features.T  # eq. 3.7, (M, n)
    n = params.shape[1]

    dist, nearest_distance, nearest = nearest_neighbours(params)
    spread = float(dist.max())
    check_separation(names, nearest_distance, nearest, spread)

    noise_var = noise * noise
    lam = m * noise_var if ridge is None else ridge
    alpha = nearest_distance.copy()
    largest_singular = float(np.sqrt(eigenvalues[0] * max(m - 1, 1)))
    linear_coeffs, radial_coeffs, hyperplane_condition, condition = solve_weights(
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
    warn_collapsing(report, names, noise, emit)
    report.noise_gain = noise_gain(model, dist)
    warn_noise_gain(report, source_points, noise, clamp, emit)
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
        dist, _, _ = nearest_neighbours(params)
        largest_singular = float(np.linalg.svd(params, compute_uv=False)[0])
        linear_coeffs, radial_coeffs, _, _ = solve_weights(
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

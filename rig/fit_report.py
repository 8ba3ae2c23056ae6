"""What a fit reports: `FitReport`, the identifiability warnings and the noise gain.

The numbers ``facecast fit`` prints and the rig file keeps, judged after the solve: examples
that collapse together, and landmark noise far below any tracker's that moves the weights.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .fit_options import feature_extent
from .radial import kernel_derivative
from .weight_model import WeightModel

__all__ = [
    "COLLAPSE_RELATIVE",
    "NOISE_FLOOR_RELATIVE",
    "NOISE_WEIGHT_CHANGE",
    "FitReport",
    "IdentifiabilityWarning",
    "noise_gain",
    "warn_collapsing",
    "warn_noise_gain",
]

# Examples whose nearest neighbour is closer than this fraction of the median nearest
# distance collapse together: distinguishable only in the absence of any noise.
COLLAPSE_RELATIVE = 0.05
# The noise-gain check: the landmark noise that moves the weights by NOISE_WEIGHT_CHANGE
# (RMS) is the rig's noise tolerance. Below NOISE_FLOOR_RELATIVE of the feature points'
# extent (2 um on a 20 cm face, 50 times finer than marker-based capture's ~0.1 mm) no real
# tracker can feed the rig, so fit warns. ICT-FaceKit fitted exactly sits at 5e-7, the demo
# at 2e-4, ICT at --noise 0.1 mm at 1e-4: a decade or more either side.
NOISE_WEIGHT_CHANGE = 0.05
NOISE_FLOOR_RELATIVE = 1e-5


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


def warn_collapsing(report: FitReport, names: Sequence[str], noise: float, emit: bool) -> None:
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


def warn_noise_gain(
    report: FitReport, source_points: np.ndarray, noise: float, clamp: str | None, emit: bool
) -> None:
    """Warn when landmark noise far below any tracker's already moves the weights.

    Judged on the rig as fitted, whatever ``noise`` was: at 0 (exact interpolation) this is
    the usual cause; above 0 it means the given noise is far below any tracker's.
    """
    extent = feature_extent(source_points)
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


def noise_gain(model: WeightModel, dist: np.ndarray) -> float:
    """RMS over the examples of |dw/dp|_F: how far unit landmark noise moves the weights.

    F has orthonormal rows, so isotropic noise of standard deviation s on the points is
    isotropic noise s on p, and the weights move by s |dw/dp|_F to first order.
    ``dist`` (M, M) holds |p_k - p_j| between the model's examples (``weight_solve.nearest_neighbours``').
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

"""A fitted rig: feature points -> blend weights -> target vertices (thesis eq. 3.8, 3.14).

The per-frame hot path: array code end to end, a single frame is a batch of one, and every
frame-independent product is folded into matrices at construction. No fitting, no file I/O.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
import numpy.typing as npt

from .basis import build_blend_basis
from .blend import Placement, blend_into, moving_vertices
from .bounds import BoxProjection, weight_metric
from .errors import InputError
from .examples import check_stable_points
from .io.rigformat import content_checksum, rig_to_bytes, save_rig
from .kernel import bspline_kernel
from .pose import (
    POSE_REFINE_MAX_CONDITION,
    align_points,
    expression_basis,
    pose_condition,
    refine_pose,
    similarity_transform,
)
from .radial import evaluate_kernel

if TYPE_CHECKING:
    from ._kernel import BsplineKernel

__all__ = ["CALIBRATION_RANGE", "POINT_RANGE", "Rig", "RigSummary", "WeightModel"]

#: float64 arrays: what a weight model holds (its constructor converts to them).
Floats = npt.NDArray[np.float64]

#: A frame's feature points are refused (``InputError`` code ``out_of_range``) when their
#: root-mean-square distance from the reference neutral's centroid is more than this many
#: times that neutral's radius (its own RMS distance from its centroid). The reference is
#: the rig's source neutral, or the performer's neutral once calibrated. Far looser than
#: any real face (a head 2 m from the origin of a 10 cm rig is 20x), it catches points in
#: other units than the rig (mm for m is 1000x), whose weights mean nothing and overflow.
POINT_RANGE = 100.0
#: A calibration neutral is refused (``out_of_range``) when its RMS distance from the source
#: neutral's centroid is more than this many times the source neutral's radius, or when its
#: own radius is more than this factor larger or smaller: calibration absorbs a performer's
#: position and units, not an absurd scale (a 1e300 neutral makes every later frame NaN).
CALIBRATION_RANGE = 1e4


class RigSummary(TypedDict):
    """``Rig.summary()``: what the REST API and ``facecast info`` show of a rig."""

    names: list[str]
    num_examples: int
    num_points: int
    num_vertices: int
    num_faces: int
    kernel: str
    clamp: str | None
    sparsity_penalty: float
    components: int
    regions: list[str] | None
    noise: float
    condition_number: float | None
    feature_indices: list[int] | None
    checksum: str


@dataclass(frozen=True, eq=False)
class WeightModel:
    """The M cardinal weight functions w_i(p) of eq. 3.8, with p computed from raw points.

    Attributes hold the fitted quantities in the thesis's terms; the underscored ones are the
    same maps folded together for evaluation.
    """

    kernel: str
    source_neutral: Floats  # (K, 3) S_B
    mean: Floats  # (3K,) mean displacement, eq. 3.4
    features: Floats  # (n, 3K) feature matrix F, eq. 3.6
    params: Floats  # (M, n) example parameters p_j, eq. 3.7
    linear_coeffs: Floats  # (n + 1, M) a_il, eq. 3.10
    radial_coeffs: Floats  # (M, M) r_ji, eq. 3.13
    alpha: Floats  # (M,) dilation factors
    clamp: str | None
    # Noise prior (ridge) of the fit; sets the metric bounded weights are projected in.
    ridge: float = 0.0
    # Linear term lambda of the bounded projection (bounds.sparsity_penalty): the sparsity
    # prior on the bounded weights; 0 is the plain metric projection. Unused without clamp.
    sparsity_penalty: float = 0.0
    # Input map x' = x @ input_matrix + input_offset on flattened points (calibration);
    # identity when not calibrated.
    input_matrix: Floats | None = None
    input_offset: Floats | None = None
    # Folded evaluation matrices, made by __post_init__ (see _fold).
    _project: Floats = field(init=False, repr=False)  # (3K, M + n + 2M)
    _offset: Floats = field(init=False, repr=False)  # (M + n + 2M,)
    _inv_alpha2: Floats = field(init=False, repr=False)  # (2M,)
    _knots: Floats = field(init=False, repr=False)  # (2M,) 2 then 1
    _radial2: Floats = field(init=False, repr=False)  # (2M, M)
    _metric: Floats = field(init=False, repr=False)  # (M-1, M-1) for bounded weights
    # The bounded-weights step; None without clamp.
    _box: BoxProjection | None = field(init=False, repr=False)
    _has_radial: bool = field(init=False, repr=False)
    _project_linear: Floats = field(init=False, repr=False)  # (3K, M): hyperplanes on raw points
    # Compiled single-frame evaluator (facecast.rig.kernel); None: numpy does every frame.
    _kernel: BsplineKernel | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # C-contiguous float64 everywhere, so a rig and its reloaded copy take the same BLAS
        # paths and give bit-identical weights.
        for f in fields(self):
            value = getattr(self, f.name) if f.init else None
            if isinstance(value, np.ndarray):
                object.__setattr__(self, f.name, np.ascontiguousarray(value, dtype=np.float64))
        self._fold()

    @property
    def num_examples(self) -> int:
        return int(self.params.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.source_neutral.shape[0])

    def _fold(self) -> None:
        """Fold eq. 3.1, 3.7, 3.10 and the distance expansion into one affine map.

        For flattened points x: p = x F^T - c (c = (S_B + mean) F^T), the hyperplanes are
        a_0 + p A, and |p - p_j|^2 = |p|^2 - 2 p.p_j + |p_j|^2. One product x @ G + g then
        gives [linear weights | p | -2 p.p_j + |p_j|^2 (twice, for the two B-spline knots)].
        """
        m = self.num_examples
        ft = self.features.T  # (3K, n)
        c = (self.source_neutral.reshape(-1) + self.mean) @ ft  # (n,)
        a0, a1 = self.linear_coeffs[0], self.linear_coeffs[1:]
        cross = -2.0 * self.params.T  # (n, M)
        pp = np.einsum("ij,ij->i", self.params, self.params)
        project = np.hstack([ft @ a1, ft, ft @ cross, ft @ cross])
        offset = np.concatenate([a0 - c @ a1, -c, pp - c @ cross, pp - c @ cross])
        if self.input_matrix is not None:
            if self.input_offset is None:
                raise ValueError("a weight model's input_matrix needs its input_offset")
            offset = self.input_offset @ project + offset
            project = self.input_matrix @ project
        inv_alpha = 1.0 / self.alpha
        set_ = object.__setattr__
        set_(self, "_project", np.ascontiguousarray(project))
        set_(self, "_offset", offset)
        set_(self, "_inv_alpha2", np.concatenate([inv_alpha, inv_alpha]) ** 2)
        set_(self, "_metric", weight_metric(self.params, self.ridge))
        box = None
        if self.clamp is not None:
            upper = 1.0 if self.clamp == "unit" else None
            box = BoxProjection(self._metric, upper, self.sparsity_penalty)
        set_(self, "_box", box)
        set_(self, "_has_radial", bool(np.any(self.radial_coeffs)))
        set_(self, "_project_linear", np.ascontiguousarray(project[:, :m]))
        set_(self, "_knots", np.concatenate([np.full(m, 2.0), np.ones(m)]))
        # B(t) = ((2 - t)_+^3 - 4 (1 - t)_+^3) / 6, so B(t) @ r = [(2-t)_+^3, (1-t)_+^3] @ R2.
        set_(
            self,
            "_radial2",
            np.vstack([self.radial_coeffs / 6.0, self.radial_coeffs * (-4.0 / 6.0)]),
        )
        kernel = None
        if self.kernel == "bspline":
            # One frame through numpy is ~13 calls of ~1 us overhead each; the compiled kernel
            # does the same sums in ~1 us. It agrees with the numpy path to rounding.
            n = self.params.shape[1]
            kernel = bspline_kernel(
                project[:, m : m + n],
                offset[m : m + n],
                self.linear_coeffs,
                self.params,
                self.alpha,
                self.radial_coeffs,
            )
        set_(self, "_kernel", kernel)

    # -- evaluation ---------------------------------------------------------------------
    def evaluate(self, flat: np.ndarray) -> np.ndarray:
        """Weights for flattened points (B, 3K) -> (B, M)."""
        m = self.num_examples
        if self._kernel is not None:
            # Every frame, alone or in a batch, through the same compiled sums: a frame's
            # weights do not depend on the batch it came in (streamed == offline, exactly).
            weights = np.empty((flat.shape[0], m))
            x = np.ascontiguousarray(flat, dtype=np.float64)
            if flat.shape[0] == 1:
                self._kernel.evaluate(x[0], weights[0])
            else:
                self._kernel.evaluate_rows(x, weights)
            return self._bounded(weights)
        if not self._has_radial:
            # The hyperplanes interpolate (see fit): no distances, no radial terms.
            weights = flat @ self._project_linear
            weights += self._offset[:m]
            return self._bounded(weights)
        n = self.params.shape[1]
        z = flat @ self._project
        z += self._offset
        p = z[:, m : m + n]
        if self.kernel == "bspline":
            d2 = z[:, m + n :]
            d2 += np.einsum("ij,ij->i", p, p)[:, None]
            np.maximum(d2, 0.0, out=d2)
            d2 *= self._inv_alpha2
            np.sqrt(d2, out=d2)  # now t = |p - p_j| / alpha_j
            np.subtract(self._knots, d2, out=d2)
            np.maximum(d2, 0.0, out=d2)
            cubed = d2 * d2
            cubed *= d2
            weights = cubed @ self._radial2
        else:
            d2 = z[:, m + n : m + n + m]
            d2 += np.einsum("ij,ij->i", p, p)[:, None]
            np.maximum(d2, 0.0, out=d2)
            t = np.sqrt(d2 * self._inv_alpha2[:m])
            weights = evaluate_kernel(self.kernel, t) @ self.radial_coeffs
        weights += z[:, :m]
        return self._bounded(weights)

    def _bounded(self, weights: np.ndarray) -> np.ndarray:
        if self._box is not None:
            rest = self._box(weights[:, 1:])
            weights[:, 1:] = rest
            weights[:, 0] = 1.0 - rest.sum(axis=1)
        return weights

    def weights_from_params(self, params: np.ndarray) -> np.ndarray:
        """Unclamped weights at reduced parameters (B, n), straight from eq. 3.8 (for analysis)."""
        lin = self.linear_coeffs[0] + params @ self.linear_coeffs[1:]
        diff = params[:, None, :] - self.params[None, :, :]
        t = np.sqrt(np.einsum("bjk,bjk->bj", diff, diff)) / self.alpha
        weights: np.ndarray = lin + evaluate_kernel(self.kernel, t) @ self.radial_coeffs
        return weights

    def project(self, flat: np.ndarray) -> np.ndarray:
        """Reduced parameters p (B, n) of flattened points (B, 3K) (eq. 3.7)."""
        m, n = self.num_examples, self.params.shape[1]
        return (flat @ self._project[:, m : m + n]) + self._offset[m : m + n]

    def with_input_map(self, matrix: Floats, offset: Floats) -> WeightModel:
        # replace() builds a new model, so __post_init__ folds the map in afresh.
        return replace(self, input_matrix=matrix, input_offset=offset)

    def with_clamp(self, clamp: str | None) -> WeightModel:
        return replace(self, clamp=clamp)


class Rig:
    """A fitted rig. Build with ``facecast.rig.fit`` or ``facecast.rig.load_rig``.

    ``weights`` maps source feature points to the M blend weights, ``blend`` maps weights to
    target vertices, ``clone`` does both. Single frames (K, 3) and batches (B, K, 3) take
    the same vectorised path.
    """

    def __init__(
        self,
        *,
        names: tuple[str, ...],
        model: WeightModel | tuple[WeightModel, ...],
        target_neutral: np.ndarray,
        blend_basis: np.ndarray,
        target_faces: np.ndarray,
        feature_indices: np.ndarray | None,
        source_preview: tuple[np.ndarray, np.ndarray] | None,
        stable_points: np.ndarray | None,
        align_scale: bool,
        report: dict[str, Any],
        calibration: np.ndarray | None = None,
        regions: tuple[tuple[str, np.ndarray], ...] | None = None,
        _moving: dict[str, np.ndarray] | None = None,
    ) -> None:
        self.names = tuple(names)
        # One weight model per face region (one for an ordinary rig). Region r's examples
        # 1.. land in the output columns regions[r][1]; column 0 is the shared neutral.
        self.models = tuple(model) if isinstance(model, tuple | list) else (model,)
        self.regions = regions
        self.target_neutral = target_neutral
        # Row 0 holds T_B and rows i > 0 hold T_i - T_B, so with w_0 := 1 eq. 3.14 is the one
        # contiguous product w @ basis.
        self._blend_basis = blend_basis
        self.target_faces = target_faces
        self.feature_indices = feature_indices
        self.source_preview = source_preview
        self.stable_points = stable_points
        self.align_scale = bool(align_scale)
        self.fit_report = report
        self.calibration = calibration
        reference = self.model.source_neutral if calibration is None else calibration
        self._centre, radius = _centre_radius(np.asarray(reference, dtype=np.float64))
        k = reference.shape[0]
        #: Bound on a frame's sum of squared distances from ``_centre`` (see POINT_RANGE).
        self._range2 = k * (POINT_RANGE * radius) ** 2
        #: A sum of squares of the points themselves up to this proves the bound without a
        #: subtraction (RMS |x - c| <= RMS |x| + |c|), with room for float32 rounding: one
        #: dot product for every ordinary frame instead of three calls. A float32 sum of
        #: 3K squares is within 3K units in the last place of the exact one (its rounding
        #: errors add up at most linearly); the room is four times that.
        slack = POINT_RANGE * radius - float(np.linalg.norm(self._centre))
        rounding = 4 * 3 * k * float(np.finfo(np.float32).eps)
        self._fast2 = k * max(slack, 0.0) ** 2 * (1.0 - max(rounding, 1e-5))
        self._radius = radius
        self._checksum: str | None = None
        # Derived from the models and the calibration at first use (see pose_refinement).
        self._pose_bases: dict[bool, tuple[np.ndarray, float]] = {}
        # The moving vertices and their basis columns, found on first use (a scan of the
        # basis) and shared with the rigs derived from this one (same basis).
        self._moving = {} if _moving is None else _moving

    @classmethod
    def from_fit(
        cls,
        *,
        names: tuple[str, ...],
        model: WeightModel,
        target_vertices: np.ndarray,
        target_faces: np.ndarray,
        feature_indices: np.ndarray | None,
        source_preview: tuple[np.ndarray, np.ndarray] | None,
        stable_points: npt.ArrayLike | None,
        align_scale: bool,
        report: dict[str, Any],
        blend_basis: np.ndarray | None = None,
    ) -> Rig:
        """A rig from a fitted weight model and the example set's targets (M, V, 3).

        ``stable_points`` are checked as an example set's are (``check_stable_points``):
        ``fit`` takes them from its caller as well as from the example set. ``blend_basis``
        is ``build_blend_basis(target_vertices)`` when the caller has built it already
        (``fit`` builds it beside its math); None builds it here.
        """
        m, v, _ = target_vertices.shape
        if blend_basis is not None and blend_basis.shape != (m, 3 * v):
            raise ValueError(
                f"Expected a blend basis of shape {(m, 3 * v)}, got {blend_basis.shape}"
            )
        neutral = np.ascontiguousarray(target_vertices[0], dtype=np.float32)
        basis = build_blend_basis(target_vertices) if blend_basis is None else blend_basis
        stable = (
            None if stable_points is None else check_stable_points(stable_points, model.num_points)
        )
        return cls(
            names=names,
            model=model,
            target_neutral=neutral,
            blend_basis=basis,
            target_faces=np.ascontiguousarray(target_faces, dtype=np.int32),
            feature_indices=feature_indices,
            source_preview=source_preview,
            stable_points=stable,
            align_scale=align_scale,
            report=report,
        )

    # -- sizes ---------------------------------------------------------------------------
    @property
    def model(self) -> WeightModel:
        """The weight model (the first region's, for a region rig)."""
        return self.models[0]

    @property
    def num_examples(self) -> int:
        return len(self.names)

    @property
    def num_points(self) -> int:
        return self.model.num_points

    @property
    def num_vertices(self) -> int:
        return int(self.target_neutral.shape[0])

    @property
    def source_neutral(self) -> np.ndarray:
        return self.model.source_neutral

    @property
    def target_deltas(self) -> np.ndarray:
        """(M, 3V) float32 T_i - T_B, row 0 zero (a copy; the rig stores them with T_B in row 0)."""
        deltas = self._blend_basis.copy()
        deltas[0] = 0.0
        return deltas

    @property
    def blend_basis(self) -> np.ndarray:
        """(M, 3V) float32: row 0 T_B, rows i > 0 T_i - T_B (read-only view)."""
        view = self._blend_basis.view()
        view.flags.writeable = False
        return view

    @property
    def moving_vertices(self) -> np.ndarray:
        """(N,) int64, increasing: the vertices some example moves (read-only).

        Every other vertex is the target neutral's in every blend, bit for bit, so
        ``blend(w, moving=True)`` (those N vertices only) loses nothing. Found once per
        basis on first use, with the basis columns every blend reads (ICT: ~15 ms).
        """
        return self._moving_basis()[1]

    def _moving_basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The moving vertices' basis columns (M, 3N) float32, their column and vertex indices."""
        if "basis" not in self._moving:
            indices = moving_vertices(self._blend_basis)
            indices.flags.writeable = False
            columns = (3 * indices[:, None] + np.arange(3)).reshape(-1)
            basis = np.ascontiguousarray(self._blend_basis[:, columns])
            runs = Placement.of(columns).runs
            # Filled last: another thread seeing "basis" sees the rest too.
            self._moving.update(vertices=indices, columns=columns, runs=runs)
            self._moving["basis"] = basis
        moving = self._moving
        return moving["basis"], moving["vertices"], moving["columns"]

    def _moving_placement(self) -> Placement:
        """Where the moving columns go in a full blend (found with the moving basis)."""
        _, _, columns = self._moving_basis()
        return Placement(columns, self._moving["runs"])

    # -- evaluation ----------------------------------------------------------------------
    def _points(self, points: npt.ArrayLike) -> tuple[np.ndarray, bool]:
        x = np.asarray(points, dtype=np.float64)
        single = x.ndim == 2
        k = self.model.num_points
        if x.shape[-2:] != (k, 3) or x.ndim not in (2, 3):
            raise InputError(
                f"expected feature points of shape ({k}, 3) or (B, {k}, 3), got {x.shape}",
                code="wrong_point_count",
            )
        return (x[None] if single else x), single

    def weights(self, points: npt.ArrayLike, *, align: bool = False) -> np.ndarray:
        """Blend weights of source frames (eq. 3.8).

        Parameters
        ----------
        points : (K, 3) or (B, K, 3) float
            Source feature points, in the source model's space.
        align : bool
            First remove head pose by aligning each frame to the (calibrated) neutral on the
            rig's stable points.

        Returns
        -------
        (M,) or (B, M) float64; the weights sum to 1.
        """
        kernel = self.models[0]._kernel
        if (
            kernel is not None
            and isinstance(points, np.ndarray)
            and not align
            and self.regions is None
        ):
            # One frame straight to the compiled kernel: the general path's conversions and
            # checks alone cost more than the kernel. The kernel takes only a C-contiguous
            # (K, 3) float array and returns None for non-finite weights and for points whose
            # sum of squares (float64) is past the range check's shortcut (``check_range``);
            # anything else (batches, lists, NaN, frames far out) goes the general way,
            # which converts, checks the range exactly or reports it. Bounded weights then
            # take the same projection as ``evaluate``'s.
            w: np.ndarray | None
            try:
                w = kernel.weights(points, self._fast2)
            except (TypeError, ValueError):
                w = None
            if w is not None:
                box = self.model._box
                return w if box is None else self.model._bounded(w[None])[0]
        x, single = self._points(points)
        self._check_range(x, single=single)
        if align:
            reference = self.source_neutral if self.calibration is None else self.calibration
            x = align_points(x, reference, stable=self.stable_points, scale=self.align_scale)
            basis = self.pose_refinement(scale=self.align_scale)
            if basis is not None:
                x = refine_pose(x, reference, basis, scale=self.align_scale)
        flat = x.reshape(x.shape[0], -1)
        if self.regions is None:
            w = self.model.evaluate(flat)
        else:
            w = np.empty((flat.shape[0], self.num_examples))
            for model, (_, columns) in zip(self.models, self.regions, strict=True):
                w[:, columns] = model.evaluate(flat)[:, 1:]
            w[:, 0] = 1.0 - w[:, 1:].sum(axis=1)
        if not np.isfinite(w.sum()):
            # _check_range refused every non-finite frame, so the points are finite here: the
            # weights overflowed (a rig file's finite but huge coefficients, or an alignment
            # scaling a frame up by ~1e150).
            bad = np.flatnonzero(~np.isfinite(w).all(axis=1))
            where = "" if single else f" (frame {int(bad[0])})"
            raise InputError(
                f"the weights of finite feature points{where} are not finite: the rig's "
                "coefficients or the head-pose alignment overflow float64",
                code="non_finite",
            )
        return w[0] if single else w

    def check_range(self, points: npt.ArrayLike) -> None:
        """Raise ``InputError`` unless frames (K, 3) or (B, K, 3) are within POINT_RANGE.

        ``weights`` checks this itself; for callers that pass frames on unevaluated.
        """
        if (
            isinstance(points, np.ndarray)
            and points.shape == (self.model.num_points, 3)
            and points.dtype.kind == "f"
            and points.itemsize >= 4
            and np.vdot(points, points) <= self._fast2
        ):
            # One ordinary frame: the dot product ``weights`` uses proves the bound (NaN and
            # Inf fail it, float16 squares could overflow: those take the exact check).
            return
        x, single = self._points(points)
        self._check_range(x, single=single)

    def _check_range(self, x: np.ndarray, *, single: bool) -> None:
        """Raise ``InputError`` for frames (B, K, 3) outside POINT_RANGE (or not finite)."""
        d = x - self._centre
        sums = np.einsum("bkc,bkc->b", d, d)
        bad = np.flatnonzero(~(sums <= self._range2))
        if not bad.size:
            return
        where = "" if single else f" (frame {int(bad[0])})"
        if not np.isfinite(x[bad[0]]).all():
            raise InputError(f"feature points hold NaN or Inf{where}", code="non_finite")
        rms = float(np.sqrt(sums[bad[0]] / x.shape[1]))
        raise InputError(
            f"feature points{where} lie {rms:.3g} (RMS) from the neutral's centre, more than "
            f"{POINT_RANGE:g}x its radius {self._radius:.3g}: are they in the rig's units?",
            code="out_of_range",
        )

    def pose_refinement(self, *, scale: bool = False) -> np.ndarray | None:
        """The expression span ``align`` refines head pose against, or None if it cannot.

        Head-pose removal first aligns each frame on the stable points, then
        (``pose.refine_pose``) removes the rigid motion left outside the span of the
        examples' displacements. That needs 3K to exceed the span's dimension by 6 (7 with
        ``scale``) and rigid motions of the neutral that are not nearly expressions
        (condition number <= ``POSE_REFINE_MAX_CONDITION``); otherwise the stable-point
        alignment stands alone.

        Returns
        -------
        (R, 3K) float64 or None
            Orthonormal rows spanning the expression displacements, in the space of the
            frames (the performer's, for a calibrated rig).
        """
        if scale not in self._pose_bases:
            directions = np.vstack([np.vstack([m.mean[None], m.features]) for m in self.models])
            basis = expression_basis(directions)
            matrix = self.model.input_matrix
            if matrix is not None:
                # calibrated() maps each frame point p to (s R) p (frames enter the models as
                # x @ kron(I, (s R)^T)), so a frame displacement is an expression when it lies
                # in (s R)^-1 of the span: rows e_k @ ((s R)^T)^-1 per point, made
                # orthonormal again.
                # The same for any invertible per-point map A (a re-base also scales z,
                # ``rebase``): frame point p enters as p @ A, so the rows are e_k @ A^-1.
                k = self.num_points
                inverse = np.linalg.inv(matrix[:3, :3])
                rows = (basis.reshape(-1, k, 3) @ inverse).reshape(basis.shape[0], -1)
                basis = np.linalg.qr(rows.T)[0].T
            reference = self.source_neutral if self.calibration is None else self.calibration
            self._pose_bases[scale] = (basis, pose_condition(basis, reference, scale=scale))
        basis, condition = self._pose_bases[scale]
        return basis if condition <= POSE_REFINE_MAX_CONDITION else None

    def pose_condition(self, *, scale: bool = False) -> float:
        """Condition number of the pose refinement (inf: too few feature points for it)."""
        self.pose_refinement(scale=scale)
        return self._pose_bases[scale][1]

    def blend(
        self, weights: npt.ArrayLike, *, out: np.ndarray | None = None, moving: bool = False
    ) -> np.ndarray:
        """Target vertices for blend weights (eq. 3.14): T_B + sum_i w_i (T_i - T_B).

        Only the basis columns of the ``moving_vertices`` are blended (the others are
        T_B), and only the rows of non-zero weights when that reads less of the basis
        (bounded weights; ``rig.blend.blend_plan``); the result equals the dense product
        ``w @ basis`` to float rounding.

        Parameters
        ----------
        weights : (M,) or (B, M) float
        out : (V, 3) or (B, V, 3) float32, optional
            Preallocated output, C-contiguous ((N, 3) or (B, N, 3) with ``moving``).
        moving : bool
            Blend and return only the ``moving_vertices`` (N of them), in that order:
            equal bit for bit to the full blend of the same weights at those vertices.

        Returns
        -------
        (V, 3) or (B, V, 3) float32; (N, 3) or (B, N, 3) with ``moving``
        """
        w = np.array(weights, dtype=np.float32, ndmin=1)
        m = self.num_examples
        if w.shape[-1] != m or w.ndim > 2:
            raise InputError(f"expected weights of shape ({m},) or (B, {m}), got {w.shape}")
        single = w.ndim == 1
        w2 = w.reshape(-1, m)
        w2[:, 0] = 1.0
        basis, _, columns = self._moving_basis()
        rows = w2.shape[0]
        size = basis.shape[1] if moving else self._blend_basis.shape[1]
        if out is None:
            flat = np.empty((rows, size), dtype=np.float32)
        elif out.dtype != np.float32 or not out.flags.c_contiguous or out.size != rows * size:
            raise InputError("out must be a C-contiguous float32 array of the output's size")
        else:
            flat = out.reshape(rows, size)
        if moving or columns.size == size:
            blend_into(w2, basis, flat)
        else:
            # Every vertex no example moves is T_B (row 0 of the basis); the others come
            # from the very product a moving blend makes, so both agree bit for bit.
            flat[:] = self._blend_basis[0]
            blend_into(w2, basis, flat, placement=self._moving_placement())
        if out is not None:
            return out
        return flat.reshape(size // 3, 3) if single else flat.reshape(-1, size // 3, 3)

    def clone(self, points: npt.ArrayLike, *, align: bool = False) -> np.ndarray:
        """Target vertices for source feature points: ``blend(weights(points))``.

        Every frame on its own; ``facecast.rig.smooth_take`` smooths a take in time first.
        """
        return self.blend(self.weights(points, align=align))

    # -- derived rigs --------------------------------------------------------------------
    def calibrated(self, neutral_points: npt.ArrayLike, *, scale: bool = True) -> Rig:
        """A rig re-based on another performer's captured neutral (K, 3).

        Frames are read as displacements from that neutral, rotated (and scaled, with
        ``scale``) into the source model's frame: x -> s R (x - N) + S_B, where (s, R) best
        maps the performer's neutral onto the source neutral. Costs nothing per frame: the
        map is folded into the rig's projection.
        """
        neutral = np.asarray(neutral_points, dtype=np.float64)
        k = self.num_points
        if neutral.shape != (k, 3):
            raise InputError(
                f"calibration neutral must have shape ({k}, 3), got {neutral.shape}",
                code="wrong_point_count",
            )
        if not np.isfinite(neutral).all():
            raise InputError("calibration neutral holds NaN or Inf", code="non_finite")
        self._check_calibration_range(neutral)
        rotation, scales, _ = similarity_transform(neutral[None], self.source_neutral, scale=scale)
        sr = scales[0] * rotation[0]  # x_row -> x_row @ sr.T
        matrix = np.kron(np.eye(k), sr.T)
        offset = (self.source_neutral - neutral @ sr.T).reshape(-1)
        # Replacing the input map (not composing it) re-calibrates from the original rig.
        return self._derive(
            tuple(m.with_input_map(matrix, offset) for m in self.models),
            calibration=neutral,
            align_scale=self.align_scale,
        )

    def _check_calibration_range(self, neutral: np.ndarray) -> None:
        """Refuse a neutral too far from, or too much larger or smaller than, the source's."""
        source_centre, source_radius = _centre_radius(self.model.source_neutral)
        _, radius = _centre_radius(neutral)
        d = neutral - source_centre
        distance = float(np.sqrt(np.vdot(d, d) / neutral.shape[0]))
        limit = CALIBRATION_RANGE
        if not distance <= limit * source_radius:
            why = f"lies {distance:.3g} (RMS) from the source neutral's centre"
        elif not source_radius / limit <= radius <= source_radius * limit:
            why = f"has radius {radius:.3g}"
        else:
            return
        raise InputError(
            f"calibration neutral {why}; it must lie within {limit:g}x the source neutral's "
            f"radius {source_radius:.3g} of its centre, with a radius within a factor {limit:g}",
            code="out_of_range",
        )

    def _derive(
        self,
        models: tuple[WeightModel, ...],
        *,
        calibration: np.ndarray | None,
        align_scale: bool,
    ) -> Rig:
        """This rig with other weight models, calibration or scale removal; shared arrays."""
        return Rig(
            names=self.names,
            model=models,
            target_neutral=self.target_neutral,
            blend_basis=self._blend_basis,
            target_faces=self.target_faces,
            feature_indices=self.feature_indices,
            source_preview=self.source_preview,
            stable_points=self.stable_points,
            align_scale=align_scale,
            report=self.fit_report,
            calibration=calibration,
            regions=self.regions,
            _moving=self._moving,
        )

    def with_models(
        self,
        models: tuple[WeightModel, ...],
        *,
        calibration: np.ndarray | None,
        report: dict[str, Any] | None = None,
    ) -> Rig:
        """This rig's targets with other weight models (one per region), e.g. refitted.

        ``calibration`` is the neutral the models read frames against (None: the source
        neutral); ``report`` replaces the fit report (None keeps it). Shares the arrays.
        """
        if len(models) != len(self.models) or any(
            m.num_examples != old.num_examples or m.num_points != old.num_points
            for m, old in zip(models, self.models, strict=False)
        ):
            raise ValueError("with_models needs one model per region, of the same sizes")
        rig = self._derive(tuple(models), calibration=calibration, align_scale=self.align_scale)
        if report is not None:
            rig.fit_report = report
        return rig

    def with_clamp(self, clamp: str | None) -> Rig:
        """The same rig with another weight-clamping mode (None, "nonneg", "unit").

        The sparsity penalty fit derived from its noise (``bounds.sparsity_penalty``) comes
        along: bounding an unbounded noise rig gives what ``fit(..., clamp=...)`` would.
        """
        return self._derive(
            tuple(m.with_clamp(clamp) for m in self.models),
            calibration=self.calibration,
            align_scale=self.align_scale,
        )

    def with_weight_models(self, models: tuple[WeightModel, ...], report: dict[str, Any]) -> Rig:
        """The same rig (targets, calibration, pose, regions) with other weight models.

        One model per region, in this rig's order, and the fit report that describes
        them (``fit.refit_noise``'s).
        """
        if len(models) != len(self.models):
            raise ValueError(f"Expected {len(self.models)} weight models, got {len(models)}")
        rig = self._derive(models, calibration=self.calibration, align_scale=self.align_scale)
        rig.fit_report = report
        return rig

    def with_align_scale(self, align_scale: bool) -> Rig:
        """The same rig, removing (or not) uniform scale with the head pose (``align``).

        A new rig sharing this one's arrays: a caller serving a client that asks for scale
        removal takes this rather than setting ``align_scale`` on a rig others share.
        """
        if bool(align_scale) == self.align_scale:
            return self
        rig = self._derive(self.models, calibration=self.calibration, align_scale=align_scale)
        # Same models and calibration: the pose bases (by ``scale``, not by this flag) too.
        rig._pose_bases = self._pose_bases
        return rig

    # -- description -----------------------------------------------------------------------
    @property
    def checksum(self) -> str:
        """SHA-256 of the rig's content (the arrays and settings the rig file stores)."""
        if self._checksum is None:
            self._checksum = content_checksum(self)
        return self._checksum

    def summary(self) -> RigSummary:
        """A JSON-able description: sizes, names, fit settings, checksum."""
        report = self.fit_report or {}
        return {
            "names": list(self.names),
            "num_examples": self.num_examples,
            "num_points": self.num_points,
            "num_vertices": self.num_vertices,
            "num_faces": int(self.target_faces.shape[0]),
            "kernel": self.model.kernel,
            "clamp": self.model.clamp,
            "sparsity_penalty": self.model.sparsity_penalty,
            "components": int(self.model.params.shape[1]),
            "regions": None if self.regions is None else [name for name, _ in self.regions],
            "noise": report.get("noise", 0.0),
            "condition_number": report.get("condition_number"),
            "feature_indices": None
            if self.feature_indices is None
            else self.feature_indices.tolist(),
            "checksum": self.checksum,
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the rig as one file (see ``facecast.rig.io.rigformat``)."""
        save_rig(self, path)

    def to_bytes(self) -> bytes:
        return rig_to_bytes(self)

    def __repr__(self) -> str:
        return (
            f"Rig(M={self.num_examples}, K={self.num_points}, V={self.num_vertices}, "
            f"kernel={self.model.kernel!r})"
        )


def _centre_radius(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (3,) of points (K, 3) and their RMS distance from it (never 0)."""
    centre = points.mean(axis=0)
    d = points - centre
    radius = float(np.sqrt(np.vdot(d, d) / points.shape[0]))
    return centre, max(radius, float(np.finfo(np.float64).tiny))

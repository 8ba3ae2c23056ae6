"""A fitted rig: feature points -> blend weights -> target vertices (thesis eq. 3.8, 3.14).

The per-frame hot path: array code end to end, a single frame is a batch of one, and every
frame-independent product is folded into matrices at construction. No fitting, no file I/O.
The weight functions are weight_model.py's, the frames a rig accepts point_range.py's.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, BinaryIO, TypedDict

import numpy as np
import numpy.typing as npt

from .basis import build_blend_basis
from .blend import Placement, blend_into, moving_vertices
from .closure import CLOSURE_NAMES, CLOSURE_REPORT_KEYS, ClosureMap, closure_ranges
from .errors import InputError
from .examples import check_stable_points
from .io.rigformat import content_checksum, rig_to_bytes, save_rig, write_rig
from .point_range import CALIBRATION_RANGE, POINT_RANGE, PointRange, check_calibration_range
from .pose import (
    POSE_REFINE_MAX_CONDITION,
    align_points,
    expression_basis,
    pose_condition,
    refine_pose,
    similarity_transform,
)
from .weight_model import WeightModel

__all__ = ["CALIBRATION_RANGE", "POINT_RANGE", "Rig", "RigSummary", "WeightModel"]


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
        self.fit_report = report  # also sets the blink weights' map (``closure``)
        self.calibration = calibration
        reference = self.model.source_neutral if calibration is None else calibration
        #: The frames this rig accepts (see POINT_RANGE); its bounds as plain attributes too,
        #: read on every frame.
        self._point_range = PointRange.around(reference)
        self._centre = self._point_range.centre
        self._range2 = self._point_range.range2
        self._fast2 = self._point_range.fast2
        self._checksum: str | None = None
        # Derived from the models and the calibration at first use (see pose_refinement).
        self._pose_bases: dict[bool, tuple[np.ndarray, float]] = {}
        # The moving vertices and their basis columns, found on first use (a scan of the
        # basis) and shared with the rigs derived from this one (same basis).
        self._moving = {} if _moving is None else _moving

    @property
    def fit_report(self) -> dict[str, Any]:
        """What the fit measured and chose (JSON-able); its ``"closure"`` entry, when there,
        maps the blink weights (``rig.closure``)."""
        return self._fit_report

    @fit_report.setter
    def fit_report(self, report: dict[str, Any]) -> None:
        self._fit_report = report
        self._closure = ClosureMap.from_report(report, self.names)

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
        (``fit`` builds it beside its math; then ``target_vertices`` may hold the neutral
        alone, (1, V, 3)); None builds it here. The rig's float32 neutral is the basis's
        row 0 (the same values), not a copy of it.
        """
        m, v = len(names), target_vertices.shape[1]
        if blend_basis is not None and blend_basis.shape != (m, 3 * v):
            raise ValueError(
                f"Expected a blend basis of shape {(m, 3 * v)}, got {blend_basis.shape}"
            )
        basis = build_blend_basis(target_vertices) if blend_basis is None else blend_basis
        neutral = basis[0].reshape(v, 3)
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
                if box is not None:
                    w = self.model._bounded(w[None])[0]
                return w if self._closure is None else self._closure.apply(w)
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
            # the range check refused every non-finite frame, so the points are finite here: the
            # weights overflowed (a rig file's finite but huge coefficients, or an alignment
            # scaling a frame up by ~1e150).
            bad = np.flatnonzero(~np.isfinite(w).all(axis=1))
            where = "" if single else f" (frame {int(bad[0])})"
            raise InputError(
                f"the weights of finite feature points{where} are not finite: the rig's "
                "coefficients or the head-pose alignment overflow float64",
                code="non_finite",
            )
        if self._closure is not None:
            self._closure.apply(w)
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
        self._point_range.check(x, single=single)

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
        check_calibration_range(self.model.source_neutral, neutral)
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

    def with_closed_eyes(
        self,
        neutral: npt.ArrayLike,
        closed: Mapping[str, npt.ArrayLike],
        contrast: tuple[float, float] | None = None,
    ) -> Rig:
        """This rig reading the performer's closed eyes as closed (``closure``): its
        ``"closure"`` entry set from its own readings (without any map it had) of ``neutral``
        and of each of ``closed`` ({name: (K, 3)}; names other than ``CLOSURE_NAMES`` are not
        read), and its ``"closure_contrast"`` to ``contrast`` (None: none, a linear map).
        This rig itself when no blink reads closed enough (``closure_ranges``). What
        ``fit_performer`` and ``rebase.calibrate`` both do.
        """
        k = self.num_points
        report = {n: v for n, v in self.fit_report.items() if n not in CLOSURE_REPORT_KEYS}
        plain = self if self._closure is None else self.with_weight_models(self.models, report)
        readings = {"neutral": plain.weights(np.asarray(neutral, dtype=np.float64)[:k])}
        for name, points in closed.items():
            if name in CLOSURE_NAMES:
                readings[name] = plain.weights(np.asarray(points, dtype=np.float64)[:k])
        ranges = closure_ranges(readings, self.names)
        if not ranges:
            return self
        report["closure"] = ranges
        if contrast is not None:
            report["closure_contrast"] = [float(contrast[0]), float(contrast[1])]
        return self.with_weight_models(self.models, report)

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

    def write(self, file: BinaryIO) -> None:
        """Write the rig's file to an open, seekable binary file, without a copy in memory."""
        write_rig(self, file)

    def __repr__(self) -> str:
        return (
            f"Rig(M={self.num_examples}, K={self.num_points}, V={self.num_vertices}, "
            f"kernel={self.model.kernel!r})"
        )

"""The M cardinal weight functions of one fitted rig (thesis eq. 3.8): points -> weights.

Holds the fitted quantities and folds them into the few matrices one frame's evaluation
reads; the compiled kernel runs them where it can. No fitting, no targets, no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from .bounds import BoxProjection, weight_metric
from .kernel import bspline_kernel
from .radial import evaluate_kernel

if TYPE_CHECKING:
    from ._kernel import BsplineKernel

__all__ = ["Floats", "WeightModel"]

#: float64 arrays: what a weight model holds (its constructor converts to them).
Floats = npt.NDArray[np.float64]


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

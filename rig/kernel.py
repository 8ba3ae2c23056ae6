"""The compiled single-frame weight kernel, small-batch blend and float16 cast (``rig._kernel``).

Builds a kernel from a fitted model's arrays when the extension is built and not disabled;
it must not change what the weights mean: the numpy path in ``weight_model.WeightModel`` stays
the reference, and the kernel agrees with it to rounding (about 1e-15 relative, not bit for bit:
the sums run in another order, and FMA rounds once where numpy rounds twice). The float16
cast must give numpy's bits exactly; without F16C it is numpy's own cast.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

try:
    # The extension by its own name: ``from . import _kernel`` reads as an import of the
    # package's ``__init__`` (which imports nearly every module) from the ground floor.
    import facecast.rig._kernel as _kernel
except ImportError:  # not built (no C compiler at install time): numpy does the work
    _kernel = None  # type: ignore[assignment]  # mypy types the name as the module only

__all__ = [
    "DISABLE_ENV",
    "blend_rows",
    "box_kernel",
    "bspline_kernel",
    "compiled",
    "description",
    "place_columns",
    "to_float16",
]

# Set to anything but "" or "0" to force the numpy path (read when a rig is built, and by
# blend_rows and to_float16 at each call).
DISABLE_ENV = "FACECAST_NO_KERNEL"


def compiled() -> bool:
    """Whether the extension is built and importable."""
    return _kernel is not None


def _disabled() -> bool:
    return os.environ.get(DISABLE_ENV, "") not in ("", "0")


def box_kernel() -> Callable[..., None] | None:
    """The compiled bounded-weights solver (``_kernel.project_box``), or None.

    None when the extension is not built or ``FACECAST_NO_KERNEL`` is set (read when a rig
    is built); ``bounds.project_box`` is then the solver, and always the reference.
    """
    return None if _kernel is None or _disabled() else _kernel.project_box


def blend_rows() -> Callable[..., None] | None:
    """The compiled small-batch blend ``blend_rows(weights, basis, out, runs=None)``, or None.

    ``out (B, C) = weights (B, M) @ basis (M, C)``, float32, C-contiguous, reading each basis
    row some frame weighs once per batch (``rig.blend.blend_plan`` says when it is cheaper
    than BLAS); with ``runs`` ((R, 3) int64: basis column, out column, count) the product's
    columns go to those columns of a wider ``out``. None when the extension is not built or ``FACECAST_NO_KERNEL`` is set (read
    at each call, as ``to_float16`` does: a blend takes hundreds of µs); ``blend_into`` then
    takes numpy's and scipy's products.
    """
    return None if _kernel is None or _disabled() else _kernel.blend_rows


def place_columns() -> Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None:
    """The compiled ``place_columns(src, out, runs)``, or None (as ``blend_rows``).

    Copies each run's columns of ``src`` (B, C) to its columns of ``out`` (B, W): where a
    BLAS product lands in a wider output, one copy per run, not numpy's scatter of every
    column (ICT's 62k moving columns of one frame: 6 µs against 91 µs).
    """
    return None if _kernel is None or _disabled() else _kernel.place_columns


def _fast_f16() -> bool:
    # The plain-C conversion is slower than numpy's loop: only F16C is worth the call.
    return _kernel is not None and _kernel.F16_ISA != "generic"


def to_float16(src: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Write ``src`` rounded to float16 into ``out`` and return ``out``.

    The same bits as ``np.copyto(out, src, casting="unsafe")`` (round to nearest, ties to
    even; overflow to infinity; NaN payloads as numpy truncates them), ~30x faster with the
    extension on a CPU with F16C (ICT's 80k coordinates: ~7 us instead of ~200 us).

    Parameters
    ----------
    src : (...) float32 (any float dtype takes numpy's path)
    out : (...) float16, the same shape, not overlapping ``src``
    """
    if (
        src.dtype == np.float32
        and out.dtype == np.float16
        and src.shape == out.shape
        and src.flags.c_contiguous
        and out.flags.c_contiguous
        and _fast_f16()
        and not _disabled()
    ):
        _kernel.f32_to_f16(src, out)
    else:
        np.copyto(out, src, casting="unsafe")
    return out


def description() -> str:
    """One line for reports: which single-frame path new rigs take, and why."""
    if _kernel is None:
        return "numpy (facecast.rig._kernel not built)"
    if _disabled():
        return f"numpy ({DISABLE_ENV} is set)"
    return f"compiled (facecast.rig._kernel, {_kernel.ISA})"


def bspline_kernel(
    project: np.ndarray,
    param_offset: np.ndarray,
    linear_coeffs: np.ndarray,
    params: np.ndarray,
    alpha: np.ndarray,
    radial_coeffs: np.ndarray,
) -> _kernel.BsplineKernel | None:
    """A compiled B-spline weight kernel for one model, or None (not built, or disabled).

    Parameters
    ----------
    project : (3K, n) float64
        Flattened points -> reduced parameters, any input map folded in (eq. 3.7).
    param_offset : (n,) float64
        Added to ``x @ project``.
    linear_coeffs : (n + 1, M) float64
        Hyperplanes a_il, constant row first (eq. 3.10).
    params : (M, n) float64
        The examples' parameters p_j.
    alpha : (M,) float64
        Dilation factors, > 0.
    radial_coeffs : (M, M) float64
        r_ji (eq. 3.13).

    Returns
    -------
    ``_kernel.BsplineKernel`` or None. Its ``evaluate(x, out)`` takes one frame's flattened
    points x (3K,) float64, writes the M weights into ``out`` (M,) float64 and returns
    their sum (non-finite when x holds NaN or Inf).
    """
    if _kernel is None or _disabled():
        return None

    def c(array: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(array, dtype=np.float64)

    return _kernel.BsplineKernel(
        c(project),
        c(param_offset),
        c(linear_coeffs[1:]),
        c(linear_coeffs[0]),
        c(params),
        c(alpha),
        c(radial_coeffs),
    )

"""Radial basis cross-sections for the weight functions (thesis section 3.4.2).

Pure elementwise functions of the scaled distance t = |p - p_j| / alpha_j; no fitting here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KERNELS", "evaluate_kernel", "kernel_derivative", "kernel_slope"]

KERNELS = ("bspline", "gaussian", "thin_plate", "linear")


def bspline(t: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline: B(0) = 2/3, support |t| < 2 (eq. 3.12).

    Written as ((2 - t)_+^3 - 4 (1 - t)_+^3) / 6, which is the usual piecewise form
    2/3 - t^2 + t^3/2 on [0, 1] and (2 - t)^3 / 6 on [1, 2].
    """
    u = np.clip(2.0 - t, 0.0, None)
    v = np.clip(1.0 - t, 0.0, None)
    return (u * u * u - 4.0 * v * v * v) / 6.0


def gaussian(t: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.exp(-(t * t))
    return out


def thin_plate(t: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        out = t * t * np.log(t)
    return np.where(t > 0.0, out, 0.0)


def linear(t: np.ndarray) -> np.ndarray:
    return np.asarray(t, dtype=np.float64).copy()


def bspline_slope(t: np.ndarray) -> np.ndarray:
    u = np.clip(2.0 - t, 0.0, None)
    v = np.clip(1.0 - t, 0.0, None)
    return (-3.0 * u * u + 12.0 * v * v) / 6.0


def gaussian_slope(t: np.ndarray) -> np.ndarray:
    out: np.ndarray = -2.0 * t * np.exp(-(t * t))
    return out


def thin_plate_slope(t: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        out = t * (2.0 * np.log(t) + 1.0)
    return np.where(t > 0.0, out, 0.0)


def linear_slope(t: np.ndarray) -> np.ndarray:
    return np.ones_like(t, dtype=np.float64)


_DERIVATIVES = {
    "bspline": bspline_slope,
    "gaussian": gaussian_slope,
    "thin_plate": thin_plate_slope,
    "linear": linear_slope,
}

_FUNCTIONS = {"bspline": bspline, "gaussian": gaussian, "thin_plate": thin_plate, "linear": linear}

# Largest |dB/dt| of each cross-section over the range that matters (t in [0, 2]); it sets how
# much landmark noise one radial term passes on, and so the regularisation it needs.
_SLOPES = {
    "bspline": 2.0 / 3.0,
    "gaussian": float(np.sqrt(2.0 / np.e)),
    "thin_plate": 2.0,
    "linear": 1.0,
}


def evaluate_kernel(kernel: str, t: np.ndarray) -> np.ndarray:
    """Cross-section ``kernel`` at scaled distances ``t`` (any shape, t >= 0)."""
    return _FUNCTIONS[kernel](t)


def kernel_derivative(kernel: str, t: np.ndarray) -> np.ndarray:
    """dB/dt of the cross-section ``kernel`` at scaled distances ``t``."""
    return _DERIVATIVES[kernel](t)


def kernel_slope(kernel: str) -> float:
    """Largest |dB/dt| of the cross-section on [0, 2]."""
    return _SLOPES[kernel]

"""A held expression's frames -> one source example and its spread (the landmark noise).

The robust average the calibration walk-through takes of about a second of tracked
frames; pure array code, no tracking, fitting or I/O.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..errors import InputError

__all__ = ["MAD_TO_SIGMA", "robust_example"]

#: Median absolute deviation -> standard deviation for normally distributed noise.
MAD_TO_SIGMA = 1.4826
#: A frame whose RMS distance to the median frame exceeds this many times the median such
#: distance is an outlier (a blink, a tracking slip) and is left out.
OUTLIER_FACTOR = 3.0


def robust_example(frames: npt.ArrayLike) -> tuple[np.ndarray, float, np.ndarray]:
    """The median frame of a held expression, outliers out, and the points' spread.

    Parameters
    ----------
    frames : (F, K, 3) float, F >= 3
        Normalised feature points of the frames captured while the expression was held.

    Returns
    -------
    points : (K, 3) float64
        Per-coordinate median of the frames kept.
    spread : float
        The landmark noise those frames show: the root mean square over coordinates of
        their robust standard deviation (1.4826 x median absolute deviation), in the
        points' units. This is the ``noise`` a fit on such captures should use.
    kept : (F,) bool
        Which frames were kept.

    Raises
    ------
    InputError
        ``wrong_point_count`` for another shape or fewer than 3 frames, ``non_finite``.
    """
    x = np.asarray(frames, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] < 3:
        raise InputError(
            f"expected frames of shape (F, K, 3) with F >= 3, got {x.shape}",
            code="wrong_point_count",
        )
    if not np.isfinite(x).all():
        raise InputError("the frames hold NaN or Inf", code="non_finite")
    median = np.median(x, axis=0)
    distance = np.sqrt(((x - median) ** 2).mean(axis=(1, 2)))
    typical = float(np.median(distance))
    kept = distance <= OUTLIER_FACTOR * typical if typical > 0 else np.ones(len(x), bool)
    held = x[kept]
    points = np.median(held, axis=0)
    mad = np.median(np.abs(held - points), axis=0)
    spread = float(np.sqrt(np.mean((MAD_TO_SIGMA * mad) ** 2)))
    return points, spread, kept

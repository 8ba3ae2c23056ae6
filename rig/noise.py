"""Landmark noise measured from the data: sigma from held frames or a take's still segment.

``fit``'s ``noise`` is the tracker's landmark noise; these functions estimate it where the
data says it (a performer's held calibration frames, the stillest stretch of a take). Pure
numpy; it must not fit, filter or do I/O.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .errors import InputError

__all__ = ["estimate_noise", "still_segment"]


def _sanitize_frames(frames: npt.ArrayLike, minimum: int) -> np.ndarray:
    try:
        x = np.asarray(frames, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("frames: not a numeric array", code="bad_noise_input") from None
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[1] < 1:
        raise InputError(
            f"frames: expected shape (F, K, 3) with K >= 1, got {x.shape}", code="bad_noise_input"
        )
    if x.shape[0] < minimum:
        raise InputError(
            f"frames: need at least {minimum} frames, got {x.shape[0]}", code="bad_noise_input"
        )
    if not np.isfinite(x).all():
        raise InputError("frames: NaN or Inf coordinates", code="non_finite")
    return x


def estimate_noise(frames: npt.ArrayLike) -> float:
    """The landmark noise sigma (std per coordinate) of frames of a held expression.

    Successive frames of a face held still differ by the tracker's noise only, twice its
    variance per coordinate for independent noise: sigma^2 = mean((x_t+1 - x_t)^2) / 2 over
    every frame pair, point and axis. Differences, not the spread about the mean, so a slow
    drift of the held face (a performer relaxing) does not count as noise. This is what
    ``fit(..., noise=...)`` takes, e.g. from the performer calibration's held frames.

    Parameters
    ----------
    frames : (F, K, 3) float
        F >= 2 consecutive frames of the same held expression, in source units.

    Returns
    -------
    float, >= 0, in the frames' units.

    Raises
    ------
    InputError
        ``bad_noise_input`` for a wrong shape or fewer than 2 frames, ``non_finite``.
    """
    x = _sanitize_frames(frames, 2)
    steps = np.diff(x, axis=0)
    return float(np.sqrt(np.mean(steps * steps) / 2.0))


def still_segment(frames: npt.ArrayLike, window: int) -> tuple[int, int]:
    """The ``window`` consecutive frames of a take that move least: [start, stop).

    Motion is the sum of squared frame-to-frame steps of every coordinate over the window;
    the first window of least motion wins. Estimating noise there (``estimate_noise``)
    reads the tracker's noise off a take without a calibration capture; the face is never
    perfectly still, so it is an upper bound.

    Parameters
    ----------
    frames : (F, K, 3) float
    window : int
        2 <= window <= F.
    """
    window = int(window)
    x = _sanitize_frames(frames, 2)
    if not 2 <= window <= x.shape[0]:
        raise InputError(
            f"window: expected 2 <= window <= {x.shape[0]} frames, got {window}",
            code="bad_noise_input",
        )
    steps = np.diff(x, axis=0).reshape(x.shape[0] - 1, -1)
    energy = np.concatenate([[0.0], np.cumsum(np.einsum("ij,ij->i", steps, steps))])
    # A window of `window` frames holds window - 1 steps.
    motion = energy[window - 1 :] - energy[: len(energy) - window + 1]
    start = int(np.argmin(motion))
    return start, start + window

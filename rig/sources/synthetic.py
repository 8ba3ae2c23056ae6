"""Building blocks of synthetic performances: checked frame counts and smooth bumps.

Shared by the procedural demo and the ICT performances; pure numpy, it must not know
any face model, read files or draw random numbers.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

__all__ = ["frame_count", "smooth_bump"]


def frame_count(seconds: float, fps: float, limit: int, *, code: str) -> int:
    """The number of frames of a performance ``seconds`` long at ``fps``, checked.

    Parameters
    ----------
    seconds, fps : float
        Length and frame rate; both finite and positive.
    limit : int
        The most frames allowed.
    code : str
        Error code for ``seconds`` or ``fps`` that are not finite positive numbers.

    Returns
    -------
    int
        ``round(seconds * fps)``, in [1, limit].

    Raises
    ------
    InputError
        With ``code`` for bad numbers, ``too_many_frames`` outside [1, limit].
    """
    try:
        seconds, fps = float(seconds), float(fps)
    except (TypeError, ValueError):
        raise InputError(
            f"seconds and fps must be numbers, got {seconds!r}, {fps!r}", code=code
        ) from None
    if not (math.isfinite(seconds) and seconds > 0 and math.isfinite(fps) and fps > 0):
        raise InputError(
            f"seconds and fps must be finite and positive, got {seconds}, {fps}", code=code
        )
    frames = round(seconds * fps)
    if not 1 <= frames <= limit:
        raise InputError(
            f"{seconds} s at {fps} fps is {frames} frames; allowed 1 to {limit}",
            code="too_many_frames",
        )
    return frames


def smooth_bump(
    t: np.ndarray, start: float, end: float, attack: float, release: float
) -> np.ndarray:
    """0 -> 1 -> 0 with raised-cosine ramps (C1 smooth), 1 on [start, end].

    Parameters
    ----------
    t : (F,) float64
        Times, seconds.
    start, end : float
        The plateau at 1.
    attack, release : float
        Lengths of the rise before ``start`` and of the fall after ``end``; positive.

    Returns
    -------
    (F,) float64
        The bump's value at each time, in [0, 1].
    """
    rise = np.clip((t - (start - attack)) / attack, 0.0, 1.0)
    fall = np.clip(((end + release) - t) / release, 0.0, 1.0)
    return (0.5 - 0.5 * np.cos(np.pi * rise)) * (0.5 - 0.5 * np.cos(np.pi * fall))

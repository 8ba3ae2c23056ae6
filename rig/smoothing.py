"""Offline temporal smoothing of a take's feature points before cloning (``facecast clone``).

The offline twin of a live session's default Kalman filter: the same model on the same
channels (the source points), with the same noise (the rig's fitted one) and acceleration,
but run over the whole take (``filters.RTSSmoother``). Pure computation; no I/O.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .filters import KALMAN_ACCELERATION, KalmanFilter, RTSSmoother
from .rig import Rig

__all__ = ["SMOOTHING_CHOICES", "smooth_points", "smoothing_method"]

#: ``smooth_points``' methods: "auto" is "rts" on a rig fitted with noise, else "none";
#: "kalman" is the live (causal) filter, for comparison with what a viewer sees.
SMOOTHING_CHOICES = ("auto", "rts", "kalman", "none")


def smoothing_method(rig: Rig, smoothing: str = "auto", *, noise: float | None = None) -> str:
    """The method ``smooth_points`` runs: "rts", "kalman" or "none" ("auto" resolved).

    "auto" is the RTS smoother where a noise is known (``noise``, else the one ``rig`` was
    fitted with), as a live session's "auto" is the Kalman filter there; else "none": a rig
    fitted exactly expects exact points, and a smoother needs the noise it weighs them by.
    """
    if smoothing not in SMOOTHING_CHOICES:
        raise InputError(
            f"smoothing must be one of {', '.join(SMOOTHING_CHOICES)}, got {smoothing!r}",
            code="bad_smoothing",
        )
    if smoothing != "auto":
        return smoothing
    return "rts" if _noise(rig, noise) > 0 else "none"


def smooth_points(
    rig: Rig,
    points: npt.ArrayLike,
    times: npt.ArrayLike,
    *,
    smoothing: str = "auto",
    noise: float | None = None,
    acceleration: float = KALMAN_ACCELERATION,
) -> np.ndarray:
    """A take's source points smoothed in time, ready for ``rig.weights`` / ``rig.clone``.

    Parameters
    ----------
    rig : Rig
        Whose fitted landmark noise is the measurement noise.
    points : (F, K, 3) float
        The take's feature points, finite.
    times : (F,) float
        Seconds of each frame, non-decreasing (``SourceAnimation.times``).
    smoothing : {"auto", "rts", "kalman", "none"}
        See ``SMOOTHING_CHOICES``; "none" returns the points as float64.
    noise : float, optional
        Measurement noise std in the points' units, instead of the rig's.
    acceleration : float
        Process noise: std of the acceleration in units of the noise per s^2, as
        ``hello.smoothing.acceleration`` (default 480, the live default).

    Returns
    -------
    (F, K, 3) float64

    Raises
    ------
    InputError
        ``bad_smoothing`` for an unknown method, ``no_noise`` for "rts" or "kalman" with no
        noise known, and the smoother's own errors for bad points or times.
    """
    method = smoothing_method(rig, smoothing, noise=noise)
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 3 or array.shape[2] != 3:
        raise InputError(
            f"smoothing: expected points of shape (F, K, 3), got {array.shape}", code="bad_input"
        )
    if method == "none":
        return array
    sigma = _noise(rig, noise)
    if not sigma > 0:
        raise InputError(
            f"smoothing {method!r} needs the landmark noise: the rig was fitted without one "
            "(fit with --noise SIGMA, give the noise, or use smoothing 'none')",
            code="no_noise",
        )
    channels = array.reshape(len(array), -1)  # as a live session filters them (K * 3)
    if method == "rts":
        flat = RTSSmoother(sigma, acceleration * sigma).smooth(channels, times)
    else:
        flat = KalmanFilter(sigma, acceleration * sigma).filter_series(channels, times)
    return flat.reshape(array.shape)


def _noise(rig: Rig, noise: float | None) -> float:
    if noise is not None:
        return float(noise)
    return float((rig.fit_report or {}).get("noise", 0.0))

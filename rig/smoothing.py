"""Offline temporal smoothing of a take's feature points before cloning (``facecast clone``).

The offline twin of a live session's default Kalman filter: the same model with the same
measurement noise (the rig's fitted one), run over the whole take (``smoother.RTSSmoother``)
along the take's principal directions of motion, each with the acceleration read off the
take; it hands back the rig regularised for the noise it leaves. Pure computation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .filters import KALMAN_ACCELERATION, KalmanFilter
from .fit import refit_noise
from .rig import Rig
from .smoother import RTSSmoother, estimate_acceleration

__all__ = ["SMOOTHING_CHOICES", "SmoothedTake", "smooth_take", "smoothing_method"]

#: ``smooth_take``'s methods: "auto" is "rts" on a rig fitted with noise, else "none";
#: "kalman" is the live (causal) filter, for comparison with what a viewer sees.
SMOOTHING_CHOICES = ("auto", "rts", "kalman", "none")
# Fewer frames than this are cloned as they are: no acceleration can be read off them.
_MIN_FRAMES = 3


@dataclass(frozen=True)
class SmoothedTake:
    """``smooth_take``'s result: points to clone and the rig to clone them with.

    Attributes
    ----------
    points : (F, K, 3) float64
    rig : Rig
        For "rts", the rig regularised for ``noise`` (``fit.refit_noise``); else the rig given.
    method : str
        "rts", "kalman" or "none": what ran.
    noise : float
        The landmark noise ``rig`` expects: the std the smoother leaves (its model's RMS
        over the frames and coordinates) for "rts", the rig's fitted noise otherwise.
    acceleration : (D,) float64 or None
        The process noise used, in units of the measurement noise per s^2: one for all the
        coordinates (D = 1), or one per principal direction of the take's motion; None
        when nothing ran.
    """

    points: np.ndarray
    rig: Rig
    method: str
    noise: float
    acceleration: np.ndarray | None


def smoothing_method(rig: Rig, smoothing: str = "auto", *, noise: float | None = None) -> str:
    """The method ``smooth_take`` runs: "rts", "kalman" or "none" ("auto" resolved).

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


def smooth_take(
    rig: Rig,
    points: npt.ArrayLike,
    times: npt.ArrayLike,
    *,
    smoothing: str = "auto",
    noise: float | None = None,
    acceleration: float | None = None,
) -> SmoothedTake:
    """A take's source points smoothed in time, and the rig to clone them with.

    "rts" smooths with ``RTSSmoother``, measurement noise the rig's, in the take's principal
    directions of motion (the SVD of its centred (F, 3K) coordinates: white noise stays
    white in any orthonormal basis), each with the acceleration under which it is most
    likely (``smoother.estimate_acceleration``): a jaw opening may move fast while most
    directions hold nearly still and carry mostly noise. The live default, 480 noise/s^2
    for every coordinate, suits a filter that must not lag, not a smoother: offline it
    over-smooths real takes at 0.1 mm. The smoothed points carry less noise than the rig
    was fitted for, so the result's rig is regularised for what is left
    (``fit.refit_noise``): on real takes that is most of the gain (README "Temporal
    coherence"). With ``acceleration`` given, every coordinate shares it (the live
    filter's model, run both ways). "kalman" runs the live filter (default 480 noise/s^2)
    with the rig as it is; "none" returns the points and the rig.

    Parameters
    ----------
    rig : Rig
    points : (F, K, 3) float
        The take's feature points, finite. Fewer than 3 frames pass through unsmoothed.
    times : (F,) float
        Seconds of each frame, non-decreasing (``SourceAnimation.times``).
    smoothing : {"auto", "rts", "kalman", "none"}
        See ``SMOOTHING_CHOICES``.
    noise : float, optional
        Measurement noise std in the points' units, instead of the rig's.
    acceleration : float, optional
        Process noise: std of the acceleration in units of the noise per s^2.

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
        return SmoothedTake(array, rig, "none", _noise(rig, noise), None)
    sigma = _noise(rig, noise)
    if not sigma > 0:
        raise InputError(
            f"smoothing {method!r} needs the landmark noise: the rig was fitted without one "
            "(fit with --noise SIGMA, give the noise, or use smoothing 'none')",
            code="no_noise",
        )
    channels = array.reshape(len(array), -1)  # as a live session filters them (K * 3)
    if method == "kalman":
        shared = KALMAN_ACCELERATION if acceleration is None else float(acceleration)
        filtered = KalmanFilter(sigma, shared * sigma).filter_series(channels, times)
        return SmoothedTake(filtered.reshape(array.shape), rig, method, sigma, np.array([shared]))
    if acceleration is None and len(array) < _MIN_FRAMES:
        return SmoothedTake(array, rig, method, sigma, None)
    if not np.isfinite(channels).all():
        bad = int(np.flatnonzero(~np.isfinite(channels).all(axis=1))[0])
        raise InputError(f"smoothing: frame {bad} has NaN or Inf coordinates", code="non_finite")
    if acceleration is not None:
        units = np.array([float(acceleration)])
        smoother = RTSSmoother(sigma, units[0] * sigma)
        smoothed = smoother.smooth(channels, times)
    else:
        mean = channels.mean(axis=0)
        directions = np.linalg.svd(channels - mean, full_matrices=False)[2]  # (D, 3K)
        components = (channels - mean) @ directions.T
        units = estimate_acceleration(components, times, sigma) / sigma
        smoother = RTSSmoother(sigma, units * sigma)
        smoothed = smoother.smooth(components, times) @ directions + mean
    left = float(np.sqrt(np.mean(np.square(smoother.smoothed_std(times)))))
    return SmoothedTake(smoothed.reshape(array.shape), _refit_for(rig, left, sigma), method,
                        left, units)  # fmt: skip


def _refit_for(rig: Rig, left: float, sigma: float) -> Rig:
    """``rig`` regularised for the noise ``left`` the smoother left of the frames' ``sigma``.

    A re-based rig (``rebase``) was fitted for the largest of the tracker's noise and what
    re-basing adds, the identity residual's share and the character rig's own noise: those
    are no frame noise, no smoother removes them, so its refit keeps them (refitted at the
    smoothed tracker noise alone, the generic path's offline blinks on the eyes clip fell
    to 0.03 of the truth, README "The eyes clip")."""
    rebased = (rig.fit_report or {}).get("rebase")
    if not rebased:
        return refit_noise(rig, left) if left < sigma else rig
    target = max(left, float(rebased["identity_noise"]), float(rebased["rig_noise"]))
    return refit_noise(rig, target) if target < float(rebased["noise"]) else rig


def _noise(rig: Rig, noise: float | None) -> float:
    """The frames' landmark noise: ``noise``, else the tracker's a re-based rig was fitted
    for, else the noise the rig was fitted with."""
    if noise is not None:
        return float(noise)
    report = rig.fit_report or {}
    rebased = report.get("rebase")
    if rebased:
        return float(rebased["tracker_noise"])
    return float(report.get("noise", 0.0))

"""Temporal coherence measured: jitter against lag of filtered takes (one-euro, Kalman, RTS).

Runs each filter on a take's noisy feature points (as a session's ``smoothing`` does; the
RTS smoother as ``facecast clone`` does), clones the result and measures the cloned
vertices' jitter, error and lag behind the ideal clone. Returns JSON-able numbers; it must
not plot, print or do I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..filters import KALMAN_ACCELERATION, KalmanFilter, OneEuroFilter
from ..rig import Rig
from ..smoother import RTSSmoother
from ..smoothing import smooth_take
from .error_metrics import eq41_frames, eq41_means, truth_terms
from .evaluate import jitter

__all__ = [
    "DEFAULT_KALMAN_ACCELERATIONS",
    "DEFAULT_ONE_EURO",
    "DEFAULT_RTS_ACCELERATIONS",
    "MAX_LAG_FRAMES",
    "best_under_one_frame",
    "lag_frames",
    "temporal_tradeoff",
]

#: One-euro settings (min_cutoff Hz, beta) compared: the protocol's default (1, 0) and
#: the range a 60 fps face sits in.
DEFAULT_ONE_EURO: tuple[tuple[float, float], ...] = (
    (0.5, 0.0), (1.0, 0.0), (2.0, 0.0), (4.0, 0.0), (8.0, 0.0), (16.0, 0.0),
    (1.0, 1.0), (1.0, 2.0), (1.0, 4.0), (1.0, 8.0),
    (2.0, 1.0), (2.0, 2.0), (2.0, 4.0), (3.0, 1.0), (3.0, 2.0), (4.0, 1.0), (4.0, 2.0),
)  # fmt: skip
#: Kalman process noise compared: the std of the acceleration in units of the landmark noise
#: per s^2 (the filter's acceleration is this times the noise), as ``hello.smoothing``'s
#: ``acceleration``; 480 is its default (rig.filters.KALMAN_ACCELERATION).
DEFAULT_KALMAN_ACCELERATIONS: tuple[float, ...] = (
    100.0, 200.0, 300.0, 360.0, 400.0, 440.0, 480.0, 500.0, 600.0, 900.0, 1400.0, 2000.0,
    6000.0, 20000.0,
)  # fmt: skip
#: RTS smoother process noise compared (the same units): the live default, which offline
#: ``facecast clone`` uses too, and its neighbours.
DEFAULT_RTS_ACCELERATIONS: tuple[float, ...] = (100.0, 200.0, KALMAN_ACCELERATION, 1000.0, 2000.0)
#: Lags searched, in frames.
MAX_LAG_FRAMES = 20
# Leads searched (frames): a constant-velocity filter can run slightly ahead.
_MAX_LEAD_FRAMES = 2
# Lag is measured on every LAG_STRIDE-th vertex: the whole face moves as one in time, and
# the search compares MAX_LAG_FRAMES + 1 shifted copies of the take.
_LAG_STRIDE = 16


def lag_frames(truth: np.ndarray, delayed: np.ndarray, *, max_lag: int = MAX_LAG_FRAMES) -> float:
    """How many frames ``delayed`` trails ``truth``: the shift that best aligns them.

    The RMS difference of delayed[t + s] and truth[t] over whole frames s in [-2, max_lag]
    (a predictive filter may lead a little), refined between frames by the parabola through
    the best shift and its neighbours.

    Parameters
    ----------
    truth, delayed : (F, ...) float
        The same quantity per frame; F > max_lag + 4.

    Returns
    -------
    float, frames in [-2, max_lag]; negative leads.
    """
    a = np.asarray(truth, dtype=np.float64).reshape(len(truth), -1)
    b = np.asarray(delayed, dtype=np.float64).reshape(len(delayed), -1)
    if a.shape != b.shape:
        raise InputError(f"lag: shapes differ, {a.shape} and {b.shape}")
    lead = _MAX_LEAD_FRAMES
    if len(a) <= max_lag + lead + 2:
        raise InputError(f"lag: need more than {max_lag + lead + 2} frames, got {len(a)}")
    # Every shift compared over the same frames of the truth (those all of them cover).
    span = len(a) - max_lag - lead
    shifts = np.arange(-lead, max_lag + 1)
    errors = np.array(
        [np.sqrt(np.mean((b[lead + s : lead + s + span] - a[lead : lead + span]) ** 2))
         for s in shifts]
    )  # fmt: skip
    best = int(np.argmin(errors))
    if 0 < best < len(shifts) - 1:
        left, mid, right = errors[best - 1 : best + 2]
        curve = left - 2.0 * mid + right
        if curve > 0:
            return float(shifts[best] + 0.5 * (left - right) / curve)
    return float(shifts[best])


def temporal_tradeoff(
    rig: Rig,
    noisy_points: npt.ArrayLike,
    truth_vertices: npt.ArrayLike,
    *,
    fps: float,
    noise: float,
    one_euro: Sequence[tuple[float, float]] = DEFAULT_ONE_EURO,
    kalman: Sequence[float] = DEFAULT_KALMAN_ACCELERATIONS,
    rts: Sequence[float] = DEFAULT_RTS_ACCELERATIONS,
) -> dict[str, Any]:
    """Jitter, error and lag of a noisy take cloned raw, through one-euro and Kalman filters
    and through RTS smoothers (offline: each frame from the whole take).

    Parameters
    ----------
    rig : Rig
        Clones the (filtered) points.
    noisy_points : (F, K, 3) float
    truth_vertices : (F, V, 3) float
        The ideal clone.
    fps : float
    noise : float
        Landmark noise std (the Kalman filters' measurement noise), > 0.
    one_euro : sequence of (min_cutoff, beta)
    kalman, rts : sequence of float
        Accelerations in landmark-noise units per s^2 (each filter's acceleration is this
        times ``noise``) of the Kalman filters and of the RTS smoothers.

    Returns
    -------
    dict (JSON-able): ``truth_jitter`` and ``rows``, one per filter (and ``raw``, and
    ``clone``: what ``facecast clone`` does by default, ``smoothing.smooth_take``), each
    {family, label, settings, jitter, lag_frames, rms_percent, eq41_percent, eq41_max};
    jitter in % of the truth's bounding-box diagonal per frame^2, lag in frames,
    ``eq41_percent`` {x, y, z} the thesis's eq. 4.1 (``cloning_error``) and ``eq41_max``
    its largest axis.
    """
    points = np.asarray(noisy_points, dtype=np.float64)
    truth = np.asarray(truth_vertices)
    if points.ndim != 3 or truth.ndim != 3 or len(points) != len(truth):
        raise InputError(
            f"temporal: expected (F, K, 3) points and (F, V, 3) truth of the same F, got "
            f"{points.shape} and {truth.shape}"
        )
    flat = truth.reshape(-1, 3)
    diagonal = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))
    scale = 100.0 / diagonal
    times = np.arange(len(points)) / float(fps)
    channels = points.reshape(len(points), -1)
    candidates: list[
        tuple[str, str, dict[str, float], OneEuroFilter | KalmanFilter | RTSSmoother | None]
    ] = [("raw", "raw", {}, None)]
    for min_cutoff, beta in one_euro:
        candidates.append(
            (
                "one-euro",
                f"one-euro {min_cutoff:g} Hz, beta {beta:g}",
                {"min_cutoff": float(min_cutoff), "beta": float(beta)},
                OneEuroFilter(min_cutoff=min_cutoff, beta=beta),
            )
        )
    models = (("kalman", "Kalman", kalman, KalmanFilter), ("rts", "RTS", rts, RTSSmoother))
    for family, name, accelerations, model in models:
        for acceleration in accelerations:
            candidates.append(
                (
                    family,
                    f"{name}, acceleration {acceleration:g} noise/s^2",
                    {"noise": float(noise), "acceleration": float(acceleration)},
                    model(noise, acceleration * noise),
                )
            )
    # Eq. 4.1's denominators depend on the truth alone: once for every row.
    denominator, _ = truth_terms(truth)
    rows = []
    for family, label, settings, smoother in candidates:
        if smoother is None:
            filtered = channels
        elif isinstance(smoother, RTSSmoother):
            filtered = smoother.smooth(channels, times)
        else:
            filtered = smoother.filter_series(channels, times)
        vertices = rig.clone(filtered.reshape(points.shape))
        rows.append(_row(family, label, settings, vertices, truth, denominator, scale))
    # What `facecast clone` does by default: RTS along the take's principal directions at
    # their most likely accelerations, cloned by the rig regularised for the noise left.
    take = smooth_take(rig, points, times, smoothing="rts", noise=noise)
    units = np.zeros(1) if take.acceleration is None else take.acceleration
    settings = {"noise": float(noise), "acceleration_median": float(np.median(units)),
                "rig_noise": take.noise}  # fmt: skip
    label = (
        f"clone default: RTS, a {np.min(units):.0f}-{np.max(units):.0f} (estimated), rig "
        f"noise {take.noise / noise:.2f} x"
    )
    clone = take.rig.clone(take.points)
    rows.append(_row("clone", label, settings, clone, truth, denominator, scale))
    return {"truth_jitter": jitter(truth) * scale, "fps": float(fps), "rows": rows}


def _row(
    family: str,
    label: str,
    settings: dict[str, float],
    vertices: np.ndarray,
    truth: np.ndarray,
    denominator: np.ndarray,
    scale: float,
) -> dict[str, Any]:
    """One row of ``temporal_tradeoff``: the clone's jitter, lag and errors (``denominator``:
    eq. 4.1's per frame and axis, sum_j |v_j| of the truth, (F, 3))."""
    diff = vertices.astype(np.float64) - truth
    eq41 = eq41_means(eq41_frames(np.abs(diff).sum(axis=1), denominator))
    return {
        "family": family,
        "label": label,
        "settings": settings,
        "jitter": jitter(vertices) * scale,
        "lag_frames": lag_frames(truth[:, ::_LAG_STRIDE], vertices[:, ::_LAG_STRIDE]),
        "rms_percent": float(np.sqrt(np.mean(np.sum(diff * diff, axis=-1))) * scale),
        "eq41_percent": eq41,
        "eq41_max": max(eq41.values()),
    }


def best_under_one_frame(tradeoff: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per filter family, the row of least jitter among those lagging less than one frame."""
    best: dict[str, dict[str, Any]] = {}
    for row in tradeoff["rows"]:
        if row["family"] == "raw" or not row["lag_frames"] < 1.0:
            continue
        if row["family"] not in best or row["jitter"] < best[row["family"]]["jitter"]:
            best[row["family"]] = row
    return best

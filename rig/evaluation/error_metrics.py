"""How far a clone is from the truth: eq. 4.1's error, RMS and largest distance, jitter.

Pure measures on vertex arrays (F, V, 3), accumulated a chunk of frames at a time; no rig,
no fitting, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError

__all__ = [
    "AXES",
    "CHUNK",
    "ErrorSums",
    "cloning_error",
    "eq41_frames",
    "eq41_means",
    "jitter",
    "sanitize_frames",
    "truth_terms",
]

AXES = ("x", "y", "z")
# Frames blended at once while measuring errors: bounds the (B, V, 3) scratch arrays.
CHUNK = 256


def sanitize_frames(
    name: str, frames: npt.ArrayLike, shape: tuple[int, ...] | None = None
) -> np.ndarray:
    array = np.asarray(frames)
    if array.dtype.kind not in "fiu":
        raise InputError(f"{name}: not a numeric array", code="bad_evaluation_input")
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1:
        raise InputError(
            f"{name}: expected shape (F, V, 3) with F >= 1, got {array.shape}",
            code="bad_evaluation_input",
        )
    if shape is not None and array.shape != shape:
        raise InputError(
            f"{name}: expected shape {shape} (the truth's), got {array.shape}",
            code="bad_evaluation_input",
        )
    return array


class ErrorSums:
    """Per-frame error terms of one method, accumulated a chunk of frames at a time."""

    def __init__(self, num_frames: int) -> None:
        self.eq41_numerator = np.zeros((num_frames, 3))
        self.mean_sq = np.zeros(num_frames)
        self.max_dist = np.zeros(num_frames)
        # Jitter (``jitter``) of the cloned vertices across chunks: the last two frames of
        # the chunk before, and the running sum of squared second differences.
        self._tail: np.ndarray | None = None
        self._second_sq = 0.0
        self._second_count = 0

    def add(self, start: int, truth: np.ndarray, pred: np.ndarray) -> None:
        # float32 when both are: the differences of float32 vertices are exact enough
        # (relative 1e-7), and it halves the memory traffic of the largest arrays here.
        diff = np.subtract(truth, pred, dtype=np.result_type(truth.dtype, pred.dtype, np.float32))
        stop = start + truth.shape[0]
        ones = np.ones(3, dtype=diff.dtype)
        # Products with vectors of ones are the fastest reductions over these axes.
        dist2 = np.matmul(diff * diff, ones)
        np.abs(diff, out=diff)
        self._add_jitter(pred)
        self.eq41_numerator[start:stop] = np.matmul(np.ones(diff.shape[1], diff.dtype), diff)
        self.mean_sq[start:stop] = dist2.mean(axis=1)
        self.max_dist[start:stop] = np.sqrt(dist2.max(axis=1))

    def _add_jitter(self, pred: np.ndarray) -> None:
        run = pred if self._tail is None else np.concatenate([self._tail, pred])
        if len(run) >= 3:
            second = run[2:] - 2.0 * run[1:-1] + run[:-2]
            self._second_sq += float(np.square(second, dtype=np.float64).sum())
            self._second_count += second.size
        self._tail = run[-2:].copy()

    def result(
        self, eq41_denominator: np.ndarray, diagonal: float, *, series: bool = True
    ) -> dict[str, Any]:
        per_axis = eq41_frames(self.eq41_numerator, eq41_denominator)
        scale = 100.0 / diagonal if diagonal > 0 else float("nan")
        rms_frames = np.sqrt(self.mean_sq) * scale
        max_frames = self.max_dist * scale
        out = {
            "eq41_percent": eq41_means(per_axis),
            "rms_percent": float(np.sqrt(self.mean_sq.mean()) * scale),
            "max_percent": float(max_frames.max()),
            # RMS second difference of the cloned vertices (``jitter``), % of the diagonal.
            "jitter_percent": (
                float(np.sqrt(self._second_sq / self._second_count) * scale)
                if self._second_count
                else float("nan")
            ),
        }
        if series:
            out["per_frame"] = {
                "eq41_percent": _rounded(per_axis),
                "rms_percent": _rounded(rms_frames),
                "max_percent": _rounded(max_frames),
            }
        return out


def eq41_frames(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """(F, 3) eq. 4.1 per frame and axis, %: sum_j |v_j - v'_j| over sum_j |v_j| (each (F, 3);
    the denominators are ``truth_terms``')."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out: np.ndarray = 100.0 * numerator / denominator
    return out


def eq41_means(per_frame: np.ndarray) -> dict[str, float]:
    """``eq41_frames`` averaged over the frames, by axis name: ``eq41_percent``."""
    return {a: float(v) for a, v in zip(AXES, per_frame.mean(axis=0), strict=True)}


def _rounded(array: np.ndarray) -> list[Any]:
    """A list of floats with 6 significant digits (a compact JSON series)."""
    rounded: list[Any] = np.vectorize(lambda x: float(f"{x:.6g}"), otypes=[float])(array).tolist()
    return rounded


def truth_terms(truth: np.ndarray) -> tuple[np.ndarray, float]:
    """Eq. 4.1's per-frame denominators sum_j |v_j| (F, 3) and the bounding-box diagonal."""
    denominator = np.empty((truth.shape[0], 3))
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for start in range(0, truth.shape[0], CHUNK):
        chunk = truth[start : start + CHUNK]
        denominator[start : start + len(chunk)] = np.abs(chunk).sum(axis=1, dtype=np.float64)
        low = np.minimum(low, chunk.min(axis=(0, 1)))
        high = np.maximum(high, chunk.max(axis=(0, 1)))
    return denominator, float(np.linalg.norm(high - low))


def cloning_error(truth: npt.ArrayLike, pred: npt.ArrayLike) -> dict[str, Any]:
    """Errors of a cloned animation against the ideal one.

    Parameters
    ----------
    truth, pred : (F, V, 3) float
        Ideal and cloned vertices per frame, the same vertex order.

    Returns
    -------
    dict
        ``eq41_percent`` {x, y, z}: thesis eq. 4.1 per axis, sum_j |v_j - v'_j| /
        sum_j |v_j| * 100, averaged over the frames (it depends on where the origin is,
        as the thesis's does); ``rms_percent`` and ``max_percent``: RMS and largest vertex
        distance relative to the truth's bounding-box diagonal (all frames), in %;
        ``per_frame``: the same three as series of F values ((F, 3) for eq41_percent).
    """
    truth = sanitize_frames("truth", truth)
    pred = sanitize_frames("pred", pred, truth.shape)
    denominator, diagonal = truth_terms(truth)
    sums = ErrorSums(truth.shape[0])
    for start in range(0, truth.shape[0], CHUNK):
        sums.add(start, truth[start : start + CHUNK], pred[start : start + CHUNK])
    return sums.result(denominator, diagonal)


def jitter(frames: np.ndarray | Sequence[Any]) -> float:
    """RMS second difference between consecutive frames: how much a series shakes.

    Parameters
    ----------
    frames : (F, ...) float
        Any per-frame quantity (weights, vertices); F >= 3.

    Returns
    -------
    float, in the frames' units per frame^2 (0 for a series moving at constant speed).
    """
    x = np.asarray(frames, dtype=np.float64).reshape(len(frames), -1)
    if len(x) < 3:
        raise InputError(f"jitter needs at least 3 frames, got {len(x)}")
    second = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(np.sqrt(np.mean(second * second)))

"""The peers a rig is compared with: blend weights read off the feature points directly.

Plain least squares and non-negative least squares on the example displacements, the
simplest methods a fitted rig must beat (thesis ch. 4). References, not hot paths.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import scipy.optimize

from ..errors import InputError
from ..examples import ExampleSet

__all__ = ["PEERS", "least_squares_weights", "nnls_weights"]


def _peer_system(
    example_set: ExampleSet, points: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The example displacements D (M-1, 3K) and the frames' displacements (B, 3K)."""
    if not isinstance(example_set, ExampleSet):
        raise TypeError(f"expected an ExampleSet, got {type(example_set).__name__}")
    x = np.asarray(points, dtype=np.float64)
    k = example_set.num_points
    if x.ndim not in (2, 3) or x.shape[-2:] != (k, 3):
        raise InputError(
            f"expected feature points of shape ({k}, 3) or (B, {k}, 3), got {x.shape}",
            code="wrong_point_count",
        )
    if not np.isfinite(x).all():
        raise InputError("feature points hold NaN or Inf", code="non_finite")
    single = x.ndim == 2
    neutral = example_set.source_neutral
    m = example_set.num_examples
    displacements = (example_set.source_points[1:] - neutral).reshape(m - 1, 3 * k)
    frames = (x.reshape(-1, k, 3) - neutral).reshape(-1, 3 * k)
    return displacements, frames, single


def _with_neutral(rest: np.ndarray, single: bool) -> np.ndarray:
    weights = np.empty((rest.shape[0], rest.shape[1] + 1))
    weights[:, 1:] = rest
    weights[:, 0] = 1.0 - rest.sum(axis=1)
    return weights[0] if single else weights


def least_squares_weights(example_set: ExampleSet, points: npt.ArrayLike) -> np.ndarray:
    """Plain least-squares blend weights read off the feature points (the simplest peer).

    Minimises |sum_i w_i (S_i - S_B) - (x - S_B)| over w_1..w_{M-1}; w_0 = 1 - sum.

    Parameters
    ----------
    example_set : ExampleSet
    points : (K, 3) or (B, K, 3) float

    Returns
    -------
    (M,) or (B, M) float64
    """
    displacements, frames, single = _peer_system(example_set, points)
    # One pseudo-inverse for all frames: the batch is a single product.
    rest = frames @ np.linalg.pinv(displacements)
    return _with_neutral(rest, single)


def nnls_weights(example_set: ExampleSet, points: npt.ArrayLike) -> np.ndarray:
    """Non-negative least-squares blend weights: as ``least_squares_weights`` with w_i >= 0.

    Solved frame by frame with ``scipy.optimize.nnls`` (a reference, not a hot path).

    Returns
    -------
    (M,) or (B, M) float64
    """
    displacements, frames, single = _peer_system(example_set, points)
    system = displacements.T
    rest = np.empty((frames.shape[0], displacements.shape[0]))
    for i, frame in enumerate(frames):
        rest[i] = scipy.optimize.nnls(system, frame)[0]
    return _with_neutral(rest, single)


PEERS: dict[str, Callable[[ExampleSet, np.ndarray], np.ndarray]] = {
    "least squares": least_squares_weights,
    "nnls": nnls_weights,
}

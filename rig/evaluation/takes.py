"""Real performances as cloning experiments: a tracker's ARKit weights on ICT-FaceKit.

A Live Link Face take (52 ARKit weights a frame) drives the ICT face's ARKit-named shapes:
its feature points are the source, and the same weights on another ICT identity are the
ideal clone. Builds arrays only; it must not fit, evaluate or print.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..examples import ExampleSet
from ..sources.source_rig import ARKIT_NAMES

__all__ = ["TakeExperiment", "take_experiment"]


@dataclass(frozen=True, eq=False)
class TakeExperiment:
    """A take made into an experiment with a known ideal clone.

    Attributes
    ----------
    examples : ExampleSet
        ``arkit_example_set``'s M paired examples.
    activations : (F, M) float64
        The take's weights on those examples (column 0, the neutral, is 0).
    points : (F, K, 3) float64
        Source feature points: S_B + activations @ (S_i - S_B).
    truth : (F, V, 3) float32
        The ideal clone: T_B + activations @ (T_i - T_B).
    fps : float
    """

    examples: ExampleSet
    activations: np.ndarray
    points: np.ndarray
    truth: np.ndarray
    fps: float


def take_experiment(
    examples: ExampleSet, arkit_weights: npt.ArrayLike, fps: float
) -> TakeExperiment:
    """Drive ``examples`` (ARKit-named, e.g. ``arkit_example_set``) with a take's weights.

    Parameters
    ----------
    examples : ExampleSet
        Examples named after ARKit shapes (others are ignored: weight 0).
    arkit_weights : (F, 52) float
        In ``ARKIT_NAMES`` order, as ``read_livelink_csv`` returns them.
    fps : float
    """
    weights = np.asarray(arkit_weights, dtype=np.float64)
    if weights.ndim != 2 or weights.shape[1] != len(ARKIT_NAMES) or weights.shape[0] < 1:
        raise InputError(
            f"take weights: expected shape (F, {len(ARKIT_NAMES)}), got {weights.shape}",
            code="bad_weights",
        )
    if not np.isfinite(weights).all():
        raise InputError("take weights: NaN or Inf values", code="non_finite")
    column = {name: i for i, name in enumerate(ARKIT_NAMES)}
    m = examples.num_examples
    activations = np.zeros((weights.shape[0], m))
    for i, name in enumerate(examples.names[1:], start=1):
        if name in column:
            activations[:, i] = weights[:, column[name]]
    source = examples.source_points
    source_deltas = (source[1:] - source[0]).reshape(m - 1, -1)
    points = (source[0].reshape(-1) + activations[:, 1:] @ source_deltas).reshape(
        len(weights), -1, 3
    )
    target = examples.target_vertices
    target_deltas = (target[1:] - target[0]).reshape(m - 1, -1).astype(np.float32)
    truth = activations[:, 1:].astype(np.float32) @ target_deltas
    truth += target[0].reshape(-1).astype(np.float32)
    return TakeExperiment(
        examples=examples,
        activations=activations,
        points=points,
        truth=truth.reshape(len(weights), -1, 3),
        fps=float(fps),
    )

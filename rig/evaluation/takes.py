"""Real performances as cloning experiments: a tracker's ARKit weights on ICT-FaceKit.

A Live Link Face take (52 ARKit weights a frame) drives the ICT face's ARKit-named shapes:
its feature points are the source, and the same weights on another ICT identity are the
ideal clone. Builds arrays only; it must not fit, evaluate or print.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..examples import ExampleSet
from ..sources.ict import ict_example_set
from ..sources.source_rig import ARKIT_NAMES, arkit_from_ict

__all__ = ["ARKIT_TARGET_IDENTITY", "TakeExperiment", "arkit_example_set", "take_experiment"]

#: The default target: another person than ICT's generic face (20 ship with the archive).
ARKIT_TARGET_IDENTITY = "person01"
# The face area of ICT's topology ([0, 9409), see shared/data/ict-facekit/README.md): the
# rest of the head hardly moves, and leaving it out keeps (F, V, 3) truths small.
_FACE_VERTICES = 9409


def arkit_example_set(
    path: str | os.PathLike[str], *, identity: str | None = ARKIT_TARGET_IDENTITY
) -> ExampleSet:
    """ICT-FaceKit's shapes under their ARKit names: the generic face -> ``identity``'s face.

    ICT's left and right halves of ``browInnerUp`` and ``cheekPuff`` are summed into the
    one ARKit shape; ``tongueOut`` has no ICT shape and is left out: 51 examples after the
    neutral. The source is ICT's default 20 landmarks; the target the face area (the first
    9,409 vertices) of ``identity`` (None: the generic face itself).

    Returns
    -------
    ExampleSet
        ``names`` ("neutral", ARKit names in ``ARKIT_NAMES`` order).
    """
    ict = ict_example_set(path, identity=identity)
    count = min(_FACE_VERTICES, ict.num_vertices)
    points, vertices = ict.source_points, ict.target_vertices[:, :count]
    names, source_points = arkit_from_ict(ict.names[1:], points[0], points[1:])
    _, target_vertices = arkit_from_ict(ict.names[1:], vertices[0], vertices[1:])
    faces = ict.target_faces[(ict.target_faces < count).all(axis=1)]
    return ExampleSet(
        names=names,
        source_points=source_points,
        target_vertices=target_vertices,
        target_faces=faces,
    )


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

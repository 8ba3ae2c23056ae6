"""ICT-FaceKit's shapes under their ARKit names, as an example set: the generic face -> an identity.

The source is ICT's default 24 landmarks, the target the face area of one identity; takes,
the transfer's truth and the webcam benchmark all start from it; ``with_tracked_eyes`` gives
the generic set its eyes as the tracker sees them. Builds arrays only.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ..examples import ExampleSet
from ..pose import similarity_transform
from .ict import DEFAULT_LANDMARKS, ict_example_set
from .source_rig import arkit_from_ict

__all__ = ["ARKIT_TARGET_IDENTITY", "FACE_VERTICES", "arkit_example_set", "with_tracked_eyes"]

#: The default target: another person than ICT's generic face (20 ship with the archive).
ARKIT_TARGET_IDENTITY = "person01"
# The face area of ICT's topology ([0, 9409), see shared/data/ict-facekit/README.md): the
# rest of the head hardly moves, and leaving it out keeps (F, V, 3) truths small.
FACE_VERTICES = 9409


def arkit_example_set(
    path: str | os.PathLike[str],
    *,
    identity: str | None = ARKIT_TARGET_IDENTITY,
    landmarks: Sequence[int] = DEFAULT_LANDMARKS,
) -> ExampleSet:
    """ICT-FaceKit's shapes under their ARKit names: the generic face -> ``identity``'s face.

    ICT's left and right halves of ``browInnerUp`` and ``cheekPuff`` are summed into the
    one ARKit shape; ``tongueOut`` has no ICT shape and is left out: 51 examples after the
    neutral. The source is ICT's default 24 landmarks (or ``landmarks``, positions in its
    ``landmarks68`` as ``ict_example_set``'s); the target the face area (the first 9,409
    vertices) of ``identity`` (None: the generic face itself).

    Returns
    -------
    ExampleSet
        ``names`` ("neutral", ARKit names in ``ARKIT_NAMES`` order).
    """
    ict = ict_example_set(path, identity=identity, landmarks=landmarks)
    count = min(FACE_VERTICES, ict.num_vertices)
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


def with_tracked_eyes(
    exact: npt.ArrayLike, tracked: npt.ArrayLike, eyes: Sequence[int]
) -> np.ndarray:
    """A source set's exact points with its eyes as a tracker sees the same face.

    ``tracked`` is the face making the same examples, tracked (its layout may append
    points, the iris centres, after the exact ones). It is carried into ``exact``'s frame
    by the similarity (rotation, uniform scale, shift) that best takes its neutral's first
    K points onto ``exact``'s neutral; then each example's points ``eyes`` (indices among
    the K: the lids) move from ``exact``'s neutral by the tracked example's displacement,
    and the appended points are the tracked ones. The rest keeps ``exact``.

    Why: FaceMesh's lids and iris do not move as the mesh's vertices do (a closed eye's
    lid gap closes a fifth of the way less, a look up moves the tracked iris with the lids
    down; README, option (z)). A generic rig fitted on exact lids reads a tracked blink
    at 0.8 and a gaze only by the lids it drags; on the lids and iris as tracked it reads
    the blink at 0.8-0.9 and the gaze from the iris.

    Parameters
    ----------
    exact : (M, K, 3)
        The examples' exact points, the neutral first.
    tracked : (M, L, 3), L >= K
        The same examples tracked, in the same order.
    eyes : sequence of int
        Which of the K points take the tracked displacements.

    Returns
    -------
    (M, L, 3) float64
    """
    ex = np.asarray(exact, dtype=np.float64)
    tr = np.asarray(tracked, dtype=np.float64)
    m, k, _ = ex.shape
    if ex.ndim != 3 or tr.ndim != 3 or tr.shape[0] != m or tr.shape[1] < k or tr.shape[2] != 3:
        raise ValueError(f"exact (M, K, 3) and tracked (M, L >= K, 3), got {ex.shape}, {tr.shape}")
    rotation, scales, shift = similarity_transform(tr[:1, :k], ex[0], scale=True)
    moved = scales[0] * tr @ rotation[0].T + shift[0]
    out = np.concatenate([ex, moved[:, k:]], axis=1)
    index = np.asarray(eyes, dtype=np.int64)
    out[:, index] = ex[:1, index] + (moved[:, index] - moved[:1, index])
    return out

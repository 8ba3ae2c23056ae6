"""ICT-FaceKit's shapes under their ARKit names, as an example set: the generic face -> an identity.

The source is ICT's default 24 landmarks, the target the face area of one identity; takes,
the transfer's truth and the webcam benchmark all start from it. Builds arrays only.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from ..examples import ExampleSet
from .ict import DEFAULT_LANDMARKS, ict_example_set
from .source_rig import arkit_from_ict

__all__ = ["ARKIT_TARGET_IDENTITY", "FACE_VERTICES", "arkit_example_set"]

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

"""Tracker head angles as the protocol's head pose: VMC's (Unity's) quaternion, §5.3.

The one place the bridges turn yaw/pitch/roll into the quaternion that both a channel
frame's ``head`` and a VMC ``/VMC/Ext/Bone/Pos "Head"`` carry; no I/O, no OSC here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from facecast.protocol import Head
from facecast.rig.sources.source_rig import head_rotation

__all__ = ["Vector", "head_pose", "unity_quaternion"]

#: A few floats: head angles (yaw, pitch, roll), a position or a quaternion.
Vector = Sequence[float] | np.ndarray

#: facecast's face frame has +x the performer's left, Unity's +x their right.
_MIRROR_X = np.diag([-1.0, 1.0, 1.0])


def unity_quaternion(angles: Vector) -> np.ndarray:
    """The (4,) float64 quaternion (x, y, z, w) of head (yaw, pitch, roll) radians.

    The rotation ``--head-pose`` applies to the points
    (`facecast.rig.sources.source_rig.head_rotation`: face frame +x the subject's left, +y up,
    +z out of the face) re-expressed in Unity's left-handed frame, where a VRM avatar
    faces +z with its left at -x: ``R_unity = S R S``, S = diag(-1, 1, 1). About y and z
    the turn reverses, about x (ear to ear) it does not.
    """
    rotation = _MIRROR_X @ head_rotation(np.asarray(angles, dtype=np.float64)) @ _MIRROR_X
    quaternion: np.ndarray = Rotation.from_matrix(rotation).as_quat()
    return quaternion


def head_pose(angles: Vector, position: Vector | None = None) -> Head:
    """The `Head` a bridge publishes for head (yaw, pitch, roll) radians (PROTOCOL.md §5.3).

    float32 on the wire: a unit quaternion's norm stays within 1e-7 of 1, and VMC
    receivers get float32 anyway. ``position``: the head bone's local position, metres.
    """
    return Head(
        rotation=unity_quaternion(angles).astype(np.float32),
        position=None if position is None else np.asarray(position, dtype=np.float32),
    )

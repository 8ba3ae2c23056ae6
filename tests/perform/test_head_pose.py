"""The head pose /perform sends, against ground truth: an ICT-FaceKit head turned by known
angles, rendered (``facecast.cli.bench.facevideo``) and tracked by the page's own pipeline
(``facecast track``, headless Chromium).

The angles follow `facecast.rig.sources.source_rig.head_rotation` (face frame: +x the
performer's left, +y up, +z out of the face); the page sends the protocol's quaternion
(PROTOCOL.md §5.3, Unity's frame: S R S with S = diag(-1, 1, 1)), which this file turns
back into angles. The feature points of the same frames stay head-pose-free.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facecast.cli.bench.facevideo import head_scene, write_video
from facecast.cli.bridges.head_pose import unity_quaternion
from facecast.rig.evaluation.webcam import ict_performer
from facecast.rig.sources.ict import ict_regions
from facecast.rig.sources.source_rig import head_rotation

from .conftest import ICT_ARCHIVE as ARCHIVE
from .conftest import ICT_TRACKING

pytestmark = ICT_TRACKING
_MIRROR_X = np.diag([-1.0, 1.0, 1.0])
#: (yaw, pitch, roll) degrees: facing the camera, then each axis alone at ±10° and ±20°.
POSES = [(0.0, 0.0, 0.0)] + [
    tuple(sign * size if axis == i else 0.0 for i in range(3))
    for axis in range(3)
    for size in (10.0, 20.0)
    for sign in (1.0, -1.0)
]
#: Largest error of any recovered angle, degrees: measured up to 6.3 (yaw), 8.3 (pitch),
#: 6.1 (roll) at ±20°, the page's tracker underestimating turns (docs/perform.md).
TOLERANCE_DEG = 9.0


def angles_of(quaternion: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) degrees of a §5.3 quaternion, as `head_rotation` takes them."""
    unity = Rotation.from_quat(np.asarray(quaternion, dtype=np.float64)).as_matrix()
    face = _MIRROR_X @ unity @ _MIRROR_X  # R = Ry(yaw) Rx(pitch) Rz(roll): intrinsic YXZ
    return np.degrees(Rotation.from_matrix(face).as_euler("YXZ"))


def test_angles_of_inverts_the_bridges_quaternion():
    angles = np.radians([12.0, -7.0, 3.0])

    assert np.allclose(angles_of(unity_quaternion(angles)), np.degrees(angles))


@pytest.fixture(scope="module")
def turned(tracker, tmp_path_factory):
    """The rendered poses and what the page's tracker made of them."""
    performer = ict_performer(ARCHIVE)
    regions, landmarks68 = ict_regions(ARCHIVE)
    rotations = head_rotation(np.radians(np.asarray(POSES)))
    act = np.zeros((len(POSES), len(performer.names)))
    path = write_video(tmp_path_factory.mktemp("head") / "turned.y4m",
                       head_scene(performer, regions, landmarks68), performer, act,
                       fps=30.0, rotations=rotations, progress=False)  # fmt: skip
    return tracker.track(path, progress=False)


def test_the_sent_head_pose_has_the_rendered_angles_signs_and_sizes(turned):
    assert turned.found.all()
    assert np.allclose(np.linalg.norm(turned.head, axis=1), 1.0, atol=1e-6)
    recovered = np.array([angles_of(q) for q in turned.head])
    truth = np.asarray(POSES)
    error = recovered - truth
    print("\nyaw pitch roll: rendered -> recovered (error), degrees")
    for pose, got, err in zip(truth, recovered, error, strict=True):
        print(f"  {pose} -> {np.round(got, 1)} ({np.round(err, 1)})")
    print(f"  per axis max |error|: {np.round(np.abs(error).max(axis=0), 1)}")
    print(f"  per axis RMS error:   {np.round(np.sqrt((error**2).mean(axis=0)), 1)}")

    assert np.abs(error).max() <= TOLERANCE_DEG, error
    # Each turned axis moves the right way and by about the right amount: the 20° turn
    # about 2x the 10° one on the turned axis (relative to facing the camera).
    rest = recovered[0]
    for axis in range(3):
        rows = 1 + 4 * axis
        big_plus, big_minus = recovered[rows + 2, axis], recovered[rows + 3, axis]
        small_plus, small_minus = recovered[rows, axis], recovered[rows + 1, axis]
        assert big_plus > small_plus > rest[axis] > small_minus > big_minus, recovered
        for got, want in ((big_plus, 20.0), (big_minus, -20.0)):
            assert math.isclose(got - rest[axis], want, abs_tol=TOLERANCE_DEG)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees of the rotation that best carries points ``a`` onto ``b`` (Kabsch)."""
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = (u @ np.diag([1.0, 1.0, d]) @ vt).T
    return float(np.degrees(Rotation.from_matrix(rotation).magnitude()))


def test_the_points_stay_free_of_the_head_pose(turned):
    """The turn goes in ``head``, not in the points: the turned heads' feature points are
    carried onto the facing head's by a rotation far smaller than the turn."""
    points = turned.points.astype(np.float64)
    left = np.array([_rotation_between(points[0], p) for p in points[1:]])
    turn = np.array([np.linalg.norm(p) for p in POSES[1:]])
    print(f"\nrotation left in the points, degrees: {np.round(left, 1)} (turns {turn})")

    # Measured: 0.6–4° left of 10–20° turns, 7.5° of pitch −20° (the tracker's mesh
    # changes shape as the head turns); a frame that kept the turn would leave all of it.
    assert (left < 0.5 * turn).all(), left

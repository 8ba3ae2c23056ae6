"""Tracker meshes -> feature points in a face-fixed frame: head pose and distance removed.

The one normalisation every mesh publisher applies (the NDJSON reader, ``facecast perform``
and, in JavaScript, the /perform page), driven by a ``Layout``; no fitting, no I/O.

The face-fixed frame (``Layout.frame``), per frame, from the mesh alone:

- ``x`` runs from the right eye's centre (mean of ``frame.right``) to the left eye's
  (``frame.left``): the subject's own left, as in ICT-FaceKit;
- ``y`` is ``mean(frame.top) - mean(frame.bottom)`` (forehead minus nose) made
  orthogonal to ``x``: up;
- ``z = x × y``: out of the face, towards the camera (right-handed);
- the origin is the mean of the ``stable`` points, and the unit makes the eye-centre
  distance ``frame.span`` (6.3 for the MediaPipe table: about centimetres).

Every point used is a stable one, so expressions do not move the frame, and a rigid head
motion or a change of distance to the camera leaves the normalised points unchanged.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .layouts import Layout

__all__ = ["face_frame", "image_to_mesh", "normalise_mesh"]


def image_to_mesh(landmarks: np.ndarray, width: float, height: float) -> np.ndarray:
    """MediaPipe's normalised image landmarks -> isotropic, y-up mesh coordinates.

    MediaPipe gives x in [0, 1] of the image width, y in [0, 1] of its height, y down, and
    z (into the screen) in about the units of x. Scaling by the image size makes the three
    axes one unit (pixels); negating y and z turns it y up, z towards the camera.

    Parameters
    ----------
    landmarks : (B, N, 3) or (N, 3) float
    width, height : float
        The image size in pixels (an unmirrored camera frame).

    Returns
    -------
    Same shape, float64.
    """
    scale = np.array([float(width), -float(height), -float(width)])
    points: np.ndarray = np.asarray(landmarks, dtype=np.float64) * scale
    return points


def _sanitize(mesh: npt.ArrayLike, layout: Layout) -> tuple[np.ndarray, bool]:
    x = np.asarray(mesh, dtype=np.float64)
    single = x.ndim == 2
    if single:
        x = x[None]
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(
            f"expected a mesh of shape (N, 3) or (B, N, 3) (layout {layout.name}: N = "
            f"{layout.tracker_points}), got {np.shape(mesh)}",
            code="wrong_landmark_count",
        )
    if x.shape[1] < layout.tracker_points:
        layout.count_within(x.shape[1])  # refuses a mesh without the frame's points
    if not np.isfinite(x).all():
        raise InputError("the mesh holds NaN or Inf", code="non_finite")
    return x, single


def face_frame(mesh: npt.ArrayLike, layout: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The face-fixed frame of each mesh (see the module docstring).

    Parameters
    ----------
    mesh : (B, N, 3) float
        Isotropic, y-up mesh coordinates (``image_to_mesh``).

    Returns
    -------
    rotation : (B, 3, 3)
        Rows are the frame's x, y, z axes in mesh coordinates.
    origin : (B, 3)
    scale : (B,)
        Multiply mesh distances by it to get layout units.

    Raises
    ------
    InputError
        ``degenerate_face`` when the eye centres coincide or the up vector is parallel to
        the eye axis (not a face).
    """
    x, _ = _sanitize(mesh, layout)
    frame = layout.frame
    right = x[:, frame["right"]].mean(axis=1)
    left = x[:, frame["left"]].mean(axis=1)
    up = x[:, frame["top"]].mean(axis=1) - x[:, frame["bottom"]].mean(axis=1)
    axis_x = left - right
    span = np.linalg.norm(axis_x, axis=1)
    tiny = 1e-9 * (1.0 + np.abs(x).max(axis=(1, 2)))
    if (span <= tiny).any():
        raise InputError("the eye centres coincide: not a face mesh", code="degenerate_face")
    axis_x /= span[:, None]
    axis_y = up - np.einsum("bi,bi->b", up, axis_x)[:, None] * axis_x
    height = np.linalg.norm(axis_y, axis=1)
    if (height <= tiny).any():
        raise InputError(
            "the face's up vector lies along the eye axis: not a face mesh",
            code="degenerate_face",
        )
    axis_y /= height[:, None]
    axis_z = np.cross(axis_x, axis_y)
    rotation = np.stack([axis_x, axis_y, axis_z], axis=1)
    origin = x[:, layout.stable].mean(axis=1)
    return rotation, origin, layout.span / span


def normalise_mesh(mesh: npt.ArrayLike, layout: Layout) -> np.ndarray:
    """The layout's feature points of each mesh, in the face-fixed frame.

    Parameters
    ----------
    mesh : (N, 3) or (B, N, 3) float
        Isotropic, y-up mesh coordinates (``image_to_mesh``), N >= ``tracker_points``
        (MediaPipe's 478-point mesh carries 10 iris points after the 468). A mesh of
        fewer points gives the layout's earlier count its points reach
        (``Layout.count_within``: the first 24 of a 468-point mesh).

    Returns
    -------
    (K, 3) or (B, K, 3) float64
        ``scale * (p - origin) @ rotation.T`` for the K features: head pose and distance
        to the camera removed, in layout units (about cm).
    """
    x, single = _sanitize(mesh, layout)
    rotation, origin, scale = face_frame(x, layout)
    features = layout.features
    if x.shape[1] < layout.tracker_points:
        features = features[: layout.count_within(x.shape[1])]
    picked = x[:, features] - origin[:, None, :]
    out: np.ndarray = np.einsum("bkj,bij->bki", picked, rotation)
    out *= scale[:, None, None]
    return out[0] if single else out

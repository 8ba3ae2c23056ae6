"""Fake-camera videos for the performer-page tests: scikit-image's astronaut photo, warped.

Writes YUV4MPEG2 (.y4m) files that Chromium's ``--use-file-for-fake-video-capture`` plays
in a loop; the face is animated by smooth backward warps (mouth opening, brows raised) and
by similarity transforms (roll, distance, shifts). Test data only: no assertion lives here.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

__all__ = ["FacePose", "render", "write_y4m"]

#: Where the astronaut's features are in the 512 x 512 photo (pixels, found by eye and
#: checked against the tracker's mesh on the unwarped photo).
_MOUTH = (224.0, 146.0)  # centre of the lips (x, y)
_MOUTH_HALF_WIDTH = 24.0
_CHIN_Y = 182.0
_BROW_Y = 89.0
_FACE_CENTRE = (222.0, 122.0)
_FACE_HALF_WIDTH = 52.0
#: The crop shown to the camera, (x0, y0, width, height) in the photo.
_CROP = (62, 2, 320, 240)


@dataclass(frozen=True)
class FacePose:
    """One frame's acting: mouth opening and brow raise in photo pixels, roll in degrees,
    scale (> 1: closer to the camera) and a shift in pixels."""

    mouth: float = 0.0
    brows: float = 0.0
    roll: float = 0.0
    scale: float = 1.0
    shift: tuple[float, float] = (0.0, 0.0)


def _photo() -> np.ndarray:
    from skimage import data

    return data.astronaut().astype(np.float32)


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def render(pose: FacePose, photo: np.ndarray | None = None) -> np.ndarray:
    """The camera image for ``pose``: (240, 320, 3) uint8 RGB."""
    photo = _photo() if photo is None else photo
    x0, y0, width, height = _CROP
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    # Similarity about the face centre: output pixel -> photo pixel (inverse transform).
    cx, cy = _FACE_CENTRE
    angle = np.deg2rad(pose.roll)
    c, s = np.cos(angle), np.sin(angle)
    u = xs + x0 - cx - pose.shift[0]
    v = ys + y0 - cy - pose.shift[1]
    px = cx + (c * u + s * v) / pose.scale
    py = cy + (-s * u + c * v) / pose.scale
    # Expression warps in photo coordinates (backward: sample above where the jaw went).
    mx, my = _MOUTH
    across_face = np.exp(-(((px - mx) / (_FACE_HALF_WIDTH * 0.9)) ** 2))
    jaw = _smoothstep((py - my + 2.0) / 4.0) * (1.0 - _smoothstep((py - _CHIN_Y - 10) / 40.0))
    py_src = py - pose.mouth * across_face * jaw
    above_brow = 1.0 - _smoothstep((py - _BROW_Y) / 7.0)
    forehead = _smoothstep((py - _BROW_Y + 50.0) / 30.0)
    across_brows = np.exp(-(((px - cx) / (_FACE_HALF_WIDTH * 1.1)) ** 4))
    py_src = py_src + pose.brows * above_brow * forehead * across_brows
    out = np.stack(
        [
            ndimage.map_coordinates(photo[..., ch], [py_src, px], order=1, mode="nearest")
            for ch in range(3)
        ],
        axis=-1,
    )
    if pose.mouth > 0.5:
        # The opened gap between the lips is the dark of the mouth, not stretched lip.
        gap = pose.mouth * np.exp(-(((px - mx) / _MOUTH_HALF_WIDTH) ** 4))
        inside = (py > my - 1.0) & (py < my + gap - 3.0)
        shade = np.where(inside, 1.0, 0.0)[..., None]
        shade = ndimage.gaussian_filter(shade, (1.0, 1.0, 0.0))
        out = out * (1.0 - shade) + np.array([40.0, 12.0, 14.0]) * shade
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _rgb_to_i420(rgb: np.ndarray) -> bytes:
    rgb = rgb.astype(np.float32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    y = 0.299 * r + 0.587 * g + 0.114 * b
    cb = 128.0 + (b - y) * 0.564
    cr = 128.0 + (r - y) * 0.713
    sub = lambda plane: plane.reshape(plane.shape[0] // 2, 2, plane.shape[1] // 2, 2).mean((1, 3))  # noqa: E731
    planes = [y, sub(cb), sub(cr)]
    return b"".join(np.clip(p + 0.5, 0, 255).astype(np.uint8).tobytes() for p in planes)


def _with_second_face(image: np.ndarray, photo: np.ndarray, size: float) -> np.ndarray:
    """The frame with the face moved left and a second, ``size`` times smaller, on the right."""
    face = render(FacePose(), photo)[20:220, 60:260]
    small = ndimage.zoom(face.astype(np.float32), (size, size, 1), order=1)
    h, w = small.shape[:2]
    out = image.copy()
    out[60 : 60 + h, 318 - w : 318] = np.clip(small + 0.5, 0, 255).astype(np.uint8)
    return out


@functools.lru_cache(maxsize=1)
def _shared_photo() -> np.ndarray:
    photo = _photo()
    photo.flags.writeable = False
    return photo


@functools.lru_cache(maxsize=256)
def _frame(pose: FacePose, second_face: float | None) -> bytes:
    """One pose's frame as ``write_y4m`` writes it (I420 planes). Drawn once a process: the
    same pose is the same bytes, and the camera files hold a pose for up to 125 frames
    and show the same few poses again and again (~26 ms of CPU a frame drawn, measured
    2026-12-05: ~1,400 frames a suite run, ~100 of them distinct)."""
    photo = _shared_photo()
    if second_face is None:
        image = render(pose, photo)
    else:
        moved = FacePose(pose.mouth, pose.brows, pose.roll, pose.scale, (-70.0, 0.0))
        image = _with_second_face(render(moved, photo), photo, second_face)
    return _rgb_to_i420(image)


def write_y4m(
    path: Path, poses: Iterable[FacePose], fps: int = 15, second_face: float | None = None
) -> Path:
    """Write one frame per pose to ``path`` (4:2:0, full range) and return the path.

    ``second_face``: also show a second person, that many times the first's size, on the
    right (the first then stands further left).
    """
    _, _, width, height = _CROP
    with open(path, "wb") as f:
        f.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg XYSCSS=420JPEG\n".encode())
        for pose in poses:
            f.write(b"FRAME\n")
            f.write(_frame(pose, second_face))
    return path

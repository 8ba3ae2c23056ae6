"""The tests' MediaPipe and OpenCV work, run by the perform venv's interpreter (.venv-perform).

mediapipe 0.10.21 needs numpy < 2, so the test process (in .venv, numpy 2) never imports it:
it starts this script with ``tests._perform_venv.run_worker`` and reads back ``.npz`` files.
It tracks and writes videos only; the tests make every assertion.

Commands::

    video SPEC.json PHOTO.npy OUT.avi   the fake-camera video (see make_video)
    track-video VIDEO OUT.npz           every frame of VIDEO through FaceTracker
    track-images IMAGES.npz OUT.npz     each image "0", "1", ... through FaceTracker
    track-video-without-litert VIDEO OUT.npz
                                        as track-video, LiteRT made unimportable (Intel
                                        macOS has no wheel of it); OUT also holds
                                        ``warnings``, the tracker's RuntimeWarnings
"""

from __future__ import annotations

import json
import sys
import warnings
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from facecast.cli.facetrack import FaceTracker, VideoSource
from facecast.rig.sources.layouts import load_layout

#: Mesh points FaceTracker gives: FaceMesh's 468 and the iris model's 10 iris points.
MESH_POINTS = 478


def _similarity(image, angle, scale, dx, dy):
    h, w = image.shape[:2]
    matrix = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    matrix[:, 2] += (dx, dy)
    return cv2.warpAffine(image, matrix, (w, h), borderMode=cv2.BORDER_REFLECT)


def _jaw_open(image, mesh_pixels, amount):
    """Pull the lower face down below the lips, most at the chin: the jaw drops."""
    h, w = image.shape[:2]
    lip, chin = mesh_pixels[14, 1], mesh_pixels[152, 1]
    centre = mesh_pixels[[61, 291], 0].mean()
    half = abs(mesh_pixels[291, 0] - mesh_pixels[61, 0])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = np.clip((yy - lip) / (chin - lip), 0, 1)
    ramp = ramp * ramp * (3 - 2 * ramp)
    dy = amount * ramp * np.exp(-(((xx - centre) / (1.6 * half)) ** 2))
    return cv2.remap(image, xx, (yy - dy).astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)  # fmt: skip


def make_video(spec: dict, photo: np.ndarray, out: Path) -> None:
    """An MJPG video of ``photo`` (RGB): the head moving (``spec["motions"]``: degrees,
    scale, dx, dy in pixels), then the jaw dropping (``spec["jaw_pixels"]``), then
    ``spec["blank_frames"]`` frames of no face, at ``spec["fps"]``."""
    with FaceTracker(static=True) as tracker:
        mesh = tracker.track(photo).mesh
    if mesh is None:
        raise SystemExit("no face found in the photo the video is made from")
    pixels = mesh * [1.0, -1.0, -1.0]  # back to image x right, y down
    frames = [_similarity(photo, *motion) for motion in spec["motions"]]
    frames += [_jaw_open(photo, pixels, amount) for amount in spec["jaw_pixels"]]
    frames += [np.full_like(photo, 128)] * spec["blank_frames"]
    h, w = photo.shape[:2]
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), spec["fps"], (w, h))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()


def track(images: Iterable[np.ndarray], out: Path) -> None:
    """Track each RGB image; save ``points`` (N, K, 3), ``meshes`` (N, 478, 3), both NaN
    where no face was found, ``faces`` (N,) and ``warnings`` (the tracker's) to ``out``."""
    layout = load_layout("mediapipe_face_mesh")
    n, k = MESH_POINTS, layout.num_features
    points, meshes, faces = [], [], []
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", RuntimeWarning)
        tracker = FaceTracker(layout)
    with tracker:
        for rgb in images:
            tracked = tracker.track(rgb)
            found = tracked.points is not None
            points.append(tracked.points if found else np.full((k, 3), np.nan))
            meshes.append(tracked.mesh if found else np.full((n, 3), np.nan))
            faces.append(tracked.faces)
    np.savez(
        out,
        points=np.reshape(points, (-1, k, 3)),
        meshes=np.reshape(meshes, (-1, n, 3)),
        faces=np.array(faces, dtype=np.int64),
        warnings=np.array([str(w.message) for w in said], dtype=str),
    )


def main(argv: list[str]) -> int:
    command, *paths = argv
    if command == "video":
        spec, photo, out = paths
        make_video(json.loads(Path(spec).read_text()), np.load(photo), Path(out))
    elif command == "track-video":
        video, out = paths
        with VideoSource(video) as source:
            track(source.frames(), Path(out))
    elif command == "track-video-without-litert":
        video, out = paths
        sys.modules["ai_edge_litert"] = None  # type: ignore[assignment]  # import fails
        with VideoSource(video) as source:
            track(source.frames(), Path(out))
    elif command == "track-images":
        images, out = paths
        with np.load(images) as data:
            track((data[str(i)] for i in range(len(data.files))), Path(out))
    else:
        raise SystemExit(f"unknown command {command!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

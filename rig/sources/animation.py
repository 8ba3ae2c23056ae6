"""Source animations (feature points per frame, validated) and cloned animations out (files).

``SourceAnimation`` is the performance every source yields; ``write_clone_output`` writes
weights/vertices as .npz, .glb or OBJ frames. Reading takes from disk is ``loading``. No
fitting, no blending beyond ``neutral + weights @ deltas`` for frames written without vertices.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.gltf import export_glb
from ..io.meshio import format_faces, format_obj

__all__ = ["DEFAULT_FPS", "FPS_FILE", "SourceAnimation", "check_fps", "write_clone_output"]

FPS_FILE = "fps.txt"
DEFAULT_FPS = 60.0
_FRAME_CHUNK = 64  # frames blended at once when vertices must be computed for OBJ output


def check_fps(fps, where: str) -> float:
    try:
        value = float(fps)
    except (TypeError, ValueError):
        raise InputError(
            f"{where}: fps must be a number, got {fps!r}", code="bad_animation"
        ) from None
    if not (np.isfinite(value) and value > 0):
        raise InputError(
            f"{where}: fps must be positive and finite, got {value}", code="bad_animation"
        )
    return value


@dataclass(eq=False)
class SourceAnimation:
    """Feature points of a performance, one (K, 3) set per frame.

    Parameters
    ----------
    points : (F, K, 3) float64
        Feature points per frame, in the order of the example set's points.
    fps : float
        Frame rate; frame i plays at ``i / fps`` unless ``timestamps`` says otherwise.
    source_vertices : (F, Vs, 3) float, optional
        Full source meshes per frame, when known and kept.
    timestamps : (F,) float64, optional
        Seconds of each frame, non-decreasing.
    """

    points: np.ndarray
    fps: float = DEFAULT_FPS
    source_vertices: np.ndarray | None = None
    timestamps: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 3 or points.shape[2] != 3 or points.shape[0] < 1 or points.shape[1] < 1:
            raise InputError(
                f"animation points: expected shape (F, K, 3) with F, K >= 1, got {points.shape}",
                code="bad_animation",
            )
        check_frames_finite("animation points", points)
        self.points = points
        self.fps = check_fps(self.fps, "animation")
        if self.source_vertices is not None:
            sv = np.asarray(self.source_vertices)
            if sv.dtype != np.float32:
                sv = sv.astype(np.float64)
            if sv.ndim != 3 or sv.shape[0] != points.shape[0] or sv.shape[2] != 3:
                raise InputError(
                    f"animation source_vertices: expected shape ({points.shape[0]}, Vs, 3), "
                    f"got {sv.shape}",
                    code="bad_animation",
                )
            self.source_vertices = sv
        if self.timestamps is not None:
            ts = np.asarray(self.timestamps, dtype=np.float64)
            if ts.shape != (points.shape[0],):
                raise InputError(
                    f"animation timestamps: expected shape ({points.shape[0]},), got {ts.shape}",
                    code="bad_animation",
                )
            if not np.isfinite(ts).all() or (np.diff(ts) < 0).any():
                raise InputError(
                    "animation timestamps: must be finite and non-decreasing", code="bad_animation"
                )
            self.timestamps = ts

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.points.shape[1])

    @property
    def times(self) -> np.ndarray:
        """(F,) seconds of each frame: ``timestamps`` or ``arange(F) / fps``."""
        if self.timestamps is not None:
            return self.timestamps
        return np.arange(self.num_frames, dtype=np.float64) / self.fps


def check_frames_finite(where: str, frames: np.ndarray) -> None:
    if np.isfinite(frames).all():
        return
    bad = int(np.flatnonzero(~np.isfinite(frames.reshape(frames.shape[0], -1)).all(axis=1))[0])
    raise InputError(f"{where}: frame {bad} has NaN or Inf coordinates", code="non_finite")


def _sanitize_output(weights, vertices, names, neutral, faces, deltas, fps):
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim != 2 or weights.shape[0] < 1:
        raise InputError(f"weights: expected shape (F, M), got {weights.shape}", code="bad_output")
    f, m = weights.shape
    names = [str(n) for n in names]
    if len(names) != m:
        raise InputError(f"names: {len(names)} names for {m} weight columns", code="bad_output")
    neutral = np.asarray(neutral, dtype=np.float64)
    if neutral.ndim != 2 or neutral.shape[1] != 3:
        raise InputError(f"neutral: expected shape (V, 3), got {neutral.shape}", code="bad_output")
    v = neutral.shape[0]
    deltas = np.asarray(deltas)
    if deltas.shape not in ((m, v, 3), (m, 3 * v)):
        raise InputError(
            f"deltas: expected shape ({m}, {v}, 3) or ({m}, {3 * v}), got {deltas.shape}",
            code="bad_output",
        )
    if vertices is not None:
        vertices = np.asarray(vertices)
        if vertices.shape != (f, v, 3):
            raise InputError(
                f"vertices: expected shape ({f}, {v}, 3), got {vertices.shape}", code="bad_output"
            )
    return weights, vertices, names, neutral, np.asarray(faces), deltas, check_fps(fps, "output")


def write_clone_output(
    path: str | os.PathLike,
    *,
    weights,
    vertices,
    names: Sequence[str],
    neutral,
    faces,
    deltas,
    fps: float,
) -> Path:
    """Write a cloned animation; the format follows the path's extension.

    Parameters
    ----------
    path : path-like
        ``.npz`` (weights, vertices when given, names, fps), ``.glb`` (target mesh with
        the examples as morph targets and the weights as an animation), or anything
        else: a folder with ``frame_00000.obj``... and ``fps.txt``.
    weights : (F, M) float
    vertices : (F, V, 3) float or None
        When None, OBJ frames are blended as ``neutral + weights @ deltas`` a chunk of
        frames at a time.
    names : sequence of M str
    neutral : (V, 3) float
    faces : (Ft, 3) int
    deltas : (M, V, 3) or (M, 3V) float
    fps : float

    Returns
    -------
    Path
        What was written.
    """
    weights, vertices, names, neutral, faces, deltas, fps = _sanitize_output(
        weights, vertices, names, neutral, faces, deltas, fps
    )
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        arrays = {
            "weights": weights.astype(np.float32),
            "names": np.asarray(names, dtype=str),
            "fps": np.float64(fps),
        }
        if vertices is not None:
            arrays["vertices"] = vertices.astype(np.float32, copy=False)
        np.savez(path, **arrays)
    elif suffix == ".glb":
        path.write_bytes(
            export_glb(
                neutral, faces, deltas.reshape(len(names), -1, 3), names, weights=weights, fps=fps
            )
        )
    else:
        _write_obj_frames(path, weights, vertices, neutral, faces, deltas, fps)
    return path


def _write_obj_frames(folder: Path, weights, vertices, neutral, faces, deltas, fps) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    faces_text = format_faces(faces)
    flat_deltas = deltas.reshape(deltas.shape[0], -1).astype(np.float32, copy=False)
    flat_neutral = neutral.reshape(-1).astype(np.float32)
    width = max(5, len(str(weights.shape[0] - 1)))
    for start in range(0, weights.shape[0], _FRAME_CHUNK):
        stop = min(start + _FRAME_CHUNK, weights.shape[0])
        if vertices is None:
            chunk = (weights[start:stop].astype(np.float32) @ flat_deltas + flat_neutral).reshape(
                stop - start, -1, 3
            )
        else:
            chunk = vertices[start:stop]
        for offset, frame in enumerate(chunk):
            name = f"frame_{start + offset:0{width}d}.obj"
            (folder / name).write_text(format_obj(frame, faces_text), encoding="ascii")
    (folder / FPS_FILE).write_text(f"{fps!r}\n", encoding="ascii")

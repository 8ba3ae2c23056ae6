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
from typing import SupportsFloat

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..io.gltf import export_glb
from ..io.meshio import format_faces, format_obj

__all__ = ["DEFAULT_FPS", "FPS_FILE", "SourceAnimation", "check_fps", "write_clone_output"]

FPS_FILE = "fps.txt"
DEFAULT_FPS = 60.0
_FRAME_CHUNK = 64  # frames blended at once when vertices must be computed for OBJ output


def check_fps(fps: object, where: str) -> float:
    try:
        if not isinstance(fps, str | SupportsFloat):
            raise TypeError
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


def _sanitize_output(
    weights: npt.ArrayLike,
    vertices: npt.ArrayLike | None,
    names: Sequence[str],
    neutral: npt.ArrayLike,
    faces: npt.ArrayLike,
    deltas: npt.ArrayLike,
    fps: float,
) -> tuple[np.ndarray, np.ndarray | None, list[str], np.ndarray, np.ndarray, np.ndarray, float]:
    """``write_clone_output``'s arguments as checked arrays, in the same order."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] < 1:
        raise InputError(f"weights: expected shape (F, M), got {w.shape}", code="bad_output")
    f, m = w.shape
    labels = [str(n) for n in names]
    if len(labels) != m:
        raise InputError(f"names: {len(labels)} names for {m} weight columns", code="bad_output")
    base = np.asarray(neutral, dtype=np.float64)
    if base.ndim != 2 or base.shape[1] != 3:
        raise InputError(f"neutral: expected shape (V, 3), got {base.shape}", code="bad_output")
    v = base.shape[0]
    d = np.asarray(deltas)
    if d.shape not in ((m, v, 3), (m, 3 * v)):
        raise InputError(
            f"deltas: expected shape ({m}, {v}, 3) or ({m}, {3 * v}), got {d.shape}",
            code="bad_output",
        )
    frames = None
    if vertices is not None:
        frames = np.asarray(vertices)
        if frames.shape != (f, v, 3):
            raise InputError(
                f"vertices: expected shape ({f}, {v}, 3), got {frames.shape}", code="bad_output"
            )
    return w, frames, labels, base, np.asarray(faces), d, check_fps(fps, "output")


def write_clone_output(
    path: str | os.PathLike[str],
    *,
    weights: npt.ArrayLike,
    vertices: npt.ArrayLike | None,
    names: Sequence[str],
    neutral: npt.ArrayLike,
    faces: npt.ArrayLike,
    deltas: npt.ArrayLike,
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
    w, frames, labels, base, mesh_faces, d, rate = _sanitize_output(
        weights, vertices, names, neutral, faces, deltas, fps
    )
    out = Path(path)
    suffix = out.suffix.lower()
    if suffix == ".npz":
        arrays = {
            "weights": w.astype(np.float32),
            "names": np.asarray(labels, dtype=str),
            "fps": np.asarray(rate, dtype=np.float64),
        }
        if frames is not None:
            arrays["vertices"] = frames.astype(np.float32, copy=False)
        # allow_pickle=False: no object arrays here (and given, mypy sees it is no array).
        np.savez(out, allow_pickle=False, **arrays)
    elif suffix == ".glb":
        out.write_bytes(
            export_glb(base, mesh_faces, d.reshape(len(labels), -1, 3), labels, weights=w, fps=rate)
        )
    else:
        _write_obj_frames(out, w, frames, base, mesh_faces, d, rate)
    return out


def _write_obj_frames(
    folder: Path,
    weights: np.ndarray,
    vertices: np.ndarray | None,
    neutral: np.ndarray,
    faces: np.ndarray,
    deltas: np.ndarray,
    fps: float,
) -> None:
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

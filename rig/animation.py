"""Source animations in (feature points per frame) and cloned animations out (files).

Reads .npz/.npy arrays or folders of OBJ frames into a validated ``SourceAnimation``,
and writes weights/vertices as .npz, .glb or OBJ frames; it does no fitting or blending
beyond ``neutral + weights @ deltas`` when frames must be written without vertices.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ExampleSetError, InputError
from .gltf import export_glb
from .meshio import format_faces, format_obj, read_obj_vertices

__all__ = ["SourceAnimation", "load_source_animation", "write_clone_output"]

FPS_FILE = "fps.txt"
DEFAULT_FPS = 60.0
_FRAME_CHUNK = 64  # frames blended at once when vertices must be computed for OBJ output


def _check_fps(fps, where: str) -> float:
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
        _check_frames_finite("animation points", points)
        self.points = points
        self.fps = _check_fps(self.fps, "animation")
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


def _check_frames_finite(where: str, frames: np.ndarray) -> None:
    if np.isfinite(frames).all():
        return
    bad = int(np.flatnonzero(~np.isfinite(frames.reshape(frames.shape[0], -1)).all(axis=1))[0])
    raise InputError(f"{where}: frame {bad} has NaN or Inf coordinates", code="non_finite")


def _natural_key(name: str) -> list:
    return [
        (0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name)
    ]


def _select(vertices: np.ndarray, indices, where: str) -> np.ndarray:
    if indices is None:
        raise InputError(
            f"{where}: holds full source meshes; pass feature_indices to select the points",
            code="bad_animation",
        )
    idx = np.asarray(indices)
    if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
        raise InputError(
            f"{where}: feature_indices must be a 1-D list of integers", code="bad_animation"
        )
    vs = vertices.shape[1]
    if idx.min() < 0 or idx.max() >= vs:
        raise InputError(
            f"{where}: feature index {int(idx[(idx < 0) | (idx >= vs)][0])} out of range for "
            f"meshes of {vs} vertices",
            code="index_out_of_range",
        )
    return vertices[:, idx.astype(np.int64)]


def load_source_animation(
    path: str | os.PathLike,
    *,
    feature_indices=None,
    num_points: int | None = None,
    keep_vertices: bool = False,
    source_rig=None,
) -> SourceAnimation:
    """Load a source performance as feature points per frame.

    Parameters
    ----------
    path : path-like
        - ``.npz`` with ``points`` (F, K, 3), optional ``fps`` and ``timestamps`` (F,);
        - ``.npz`` with ``vertices`` (F, Vs, 3) and no ``points``: ``feature_indices``
          select the points;
        - ``.npy`` holding (F, K, 3) points;
        - a folder of OBJ frames (natural name order, ``fps.txt`` optional, default 60);
          ``feature_indices`` select the points;
        - ``.csv``: a Live Link Face take (blendshape weights), turned into points by
          ``source_rig`` (required for CSV);
        - ``.ndjson`` / ``.jsonl``: MediaPipe face-landmarker results (see
          ``facecast.rig.trackers``).
    feature_indices : (K,) int, optional
        0-based vertex indices of the feature points in the source meshes.
    num_points : int, optional
        Expected K (the rig's); a mismatch is an error saying expected vs got.
    keep_vertices : bool
        Keep the full source meshes as ``source_vertices`` (float32 for OBJ frames).
        Off by default: a long mesh performance is large and the rig needs only points.
    source_rig : SourceRig or path, optional
        ARKit-named source shapes for blendshape-weight takes (``facecast.rig.source_rig``).

    Returns
    -------
    SourceAnimation

    Raises
    ------
    InputError
        Missing or unreadable file, bad shapes, NaN/Inf (naming the frame), wrong K.
    """
    path = Path(path)
    if path.is_dir():
        animation = _load_obj_frames(path, feature_indices, keep_vertices)
    elif path.suffix.lower() == ".npz":
        animation = _load_npz(path, feature_indices, keep_vertices)
    elif path.suffix.lower() == ".npy":
        animation = SourceAnimation(points=_load_array(path, None), fps=DEFAULT_FPS)
    elif path.suffix.lower() in (".csv", ".ndjson", ".jsonl") and path.is_file():
        animation = _load_tracker_take(path, source_rig)
    elif not path.exists():
        raise InputError(f"{path}: no such file or folder", code="missing_file")
    else:
        raise InputError(
            f"{path}: not a source animation (expected .npz, .npy, a Live Link .csv, a "
            "MediaPipe .ndjson or a folder of OBJ frames)",
            code="bad_animation",
        )
    if num_points is not None and animation.num_points != num_points:
        raise InputError(
            f"{path}: expected {num_points} feature points per frame, got {animation.num_points}",
            code="point_count_mismatch",
        )
    return animation


def _load_tracker_take(path: Path, source_rig) -> SourceAnimation:
    # Imported here: the tracker parsers build on this module's SourceAnimation.
    from .source_rig import SourceRig, load_source_rig
    from .trackers import livelink_csv_animation, mediapipe_animation

    if path.suffix.lower() != ".csv":
        return mediapipe_animation(path)
    if source_rig is None:
        raise InputError(
            f"{path}: a Live Link Face take holds blendshape weights, not points; give a "
            "source rig (--source-rig) to turn them into feature points",
            code="source_rig_required",
        )
    if not isinstance(source_rig, SourceRig):
        source_rig = load_source_rig(source_rig)
    return livelink_csv_animation(path, source_rig)


def _load_array(path: Path, key: str | None) -> np.ndarray:
    try:
        # Our own handle: np.load leaks its file when a zip is corrupt.
        with path.open("rb") as handle:
            if key is None:
                array = np.load(handle, allow_pickle=False)
            else:
                with np.load(handle, allow_pickle=False) as archive:
                    array = archive[key]
    except FileNotFoundError:
        raise InputError(f"{path}: file not found", code="missing_file") from None
    except Exception as exc:  # zipfile/zlib/numpy raise many types on a corrupt file
        raise InputError(
            f"{path}: not readable ({type(exc).__name__}: {exc})", code="bad_animation"
        ) from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu":
        raise InputError(f"{path}: {key or 'array'} is not a numeric array", code="bad_animation")
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1:
        raise InputError(
            f"{path}: {key or 'array'} must have shape (F, K, 3) with F >= 1, got {array.shape}",
            code="bad_animation",
        )
    return array


def _load_npz(path: Path, feature_indices, keep_vertices: bool) -> SourceAnimation:
    try:
        with path.open("rb") as handle, np.load(handle, allow_pickle=False) as archive:
            keys = set(archive.files)
            fps = archive["fps"] if "fps" in keys else DEFAULT_FPS
            timestamps = archive["timestamps"] if "timestamps" in keys else None
    except FileNotFoundError:
        raise InputError(f"{path}: file not found", code="missing_file") from None
    except Exception as exc:  # zipfile/zlib/numpy raise many types on a corrupt file
        raise InputError(
            f"{path}: not a readable .npz ({type(exc).__name__}: {exc})", code="bad_animation"
        ) from None
    fps = _check_fps(np.asarray(fps).reshape(-1)[0] if np.size(fps) == 1 else fps, str(path))
    vertices = None
    if "points" in keys:
        points = _load_array(path, "points")
        if keep_vertices and "vertices" in keys:
            vertices = _load_array(path, "vertices")
    elif "vertices" in keys:
        all_vertices = _load_array(path, "vertices")
        points = _select(all_vertices, feature_indices, str(path))
        vertices = all_vertices if keep_vertices else None
        del all_vertices
    else:
        raise InputError(f"{path}: needs a 'points' or a 'vertices' array", code="bad_animation")
    _check_frames_finite(str(path), points)
    try:
        return SourceAnimation(
            points=points, fps=fps, source_vertices=vertices, timestamps=timestamps
        )
    except InputError as exc:
        raise InputError(f"{path}: {exc.message}", code=exc.code) from None


def _load_obj_frames(folder: Path, feature_indices, keep_vertices: bool) -> SourceAnimation:
    if feature_indices is None:
        _select(np.empty((1, 0, 3)), None, str(folder))  # raises: meshes need indices
    files = sorted(
        (f for f in folder.iterdir() if f.is_file() and f.suffix.lower() == ".obj"),
        key=lambda f: _natural_key(f.name),
    )
    if not files:
        raise InputError(f"{folder}: no .obj frames", code="bad_animation")
    fps = DEFAULT_FPS
    fps_file = folder / FPS_FILE
    if fps_file.is_file():
        fps = _check_fps(
            fps_file.read_text(encoding="utf-8", errors="replace").strip(), str(fps_file)
        )
    points = None
    vertices = None
    idx = None
    vs = 0
    for i, file in enumerate(files):
        try:
            frame = read_obj_vertices(file)
        except ExampleSetError as exc:
            raise InputError(exc.message, code=exc.code) from None
        if i == 0:
            vs = frame.shape[0]
            _select(frame[None], feature_indices, str(folder))  # validates the indices
            idx = np.asarray(feature_indices, dtype=np.int64)
            points = np.empty((len(files), idx.size, 3))
            if keep_vertices:
                vertices = np.empty((len(files), vs, 3), dtype=np.float32)
        elif frame.shape[0] != vs:
            raise InputError(
                f"{file}: frame has {frame.shape[0]} vertices, the first frame {files[0].name} "
                f"has {vs}",
                code="vertex_count_mismatch",
            )
        points[i] = frame[idx]
        if vertices is not None:
            vertices[i] = frame
    return SourceAnimation(points=points, fps=fps, source_vertices=vertices)


# -- output -----------------------------------------------------------------------------


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
    return weights, vertices, names, neutral, np.asarray(faces), deltas, _check_fps(fps, "output")


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

"""A source performance read from disk: arrays, OBJ frames or a tracker's take, as points.

One entry point, ``load_source_animation``, picks the reader by what the path is (.npz,
.npy, a folder of OBJ frames, a Live Link .csv, a MediaPipe .ndjson); no fitting, no network.
"""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import ExampleSetError, InputError
from ..io.meshio import read_obj_vertices
from ..npy_reads import NPY_READS
from .animation import DEFAULT_FPS, FPS_FILE, SourceAnimation, check_fps, check_frames_finite
from .layouts import Layout, load_layout
from .source_rig import SourceRig, load_source_rig, names_generic_set
from .trackers import livelink_csv_animation, mediapipe_animation

__all__ = ["load_source_animation"]


def _natural_key(name: str) -> list[tuple[int, int, str]]:
    return [
        (0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name)
    ]


def _select(vertices: np.ndarray, indices: npt.ArrayLike | None, where: str) -> np.ndarray:
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
    path: str | os.PathLike[str],
    *,
    feature_indices: npt.ArrayLike | None = None,
    num_points: int | None = None,
    keep_vertices: bool = False,
    source_rig: SourceRig | str | os.PathLike[str] | None = None,
) -> SourceAnimation:
    """Load a source performance as feature points per frame.

    Parameters
    ----------
    path : path-like
        - ``.npz`` with ``points`` (F, K, 3), optional ``fps`` and ``timestamps`` (F,),
          and optional ``found`` (F,) bool (``facecast track``'s: frames without a face,
          NaN, hold the nearest earlier tracked frame, or the first tracked one);
        - ``.npz`` with ``vertices`` (F, Vs, 3) and no ``points``: ``feature_indices``
          select the points;
        - ``.npy`` holding (F, K, 3) points;
        - a folder of OBJ frames (natural name order, ``fps.txt`` optional, default 60);
          ``feature_indices`` select the points;
        - ``.csv``: a Live Link Face take (blendshape weights), turned into points by
          ``source_rig`` (required for CSV);
        - ``.ndjson`` / ``.jsonl``: MediaPipe face-landmarker results (see
          ``facecast.rig.sources.trackers``).
    feature_indices : (K,) int, optional
        0-based vertex indices of the feature points in the source meshes.
    num_points : int, optional
        Expected K (the rig's); a mismatch is an error saying expected vs got.
    keep_vertices : bool
        Keep the full source meshes as ``source_vertices`` (float32 for OBJ frames).
        Off by default: a long mesh performance is large and the rig needs only points.
    source_rig : SourceRig or path, optional
        ARKit-named source shapes for blendshape-weight takes (``facecast.rig.sources.source_rig``).

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
        layout = _tracked_layout(path, source_rig)
        if not (layout is not None and layout.takes_first(animation.num_points, num_points)):
            raise InputError(
                f"{path}: expected {num_points} feature points per frame, got "
                f"{animation.num_points}",
                code="point_count_mismatch",
            )
        # Tracked in a layout that has grown since the rig was fitted on its earlier
        # version: the rig takes the first num_points, as /perform sends it.
        animation = replace(animation, points=animation.points[:, :num_points])
    return animation


def _tracked_layout(
    path: Path, source_rig: SourceRig | str | os.PathLike[str] | None = None
) -> Layout | None:
    """The landmark layout a tracked take follows: an .npz's ``layout`` (``facecast
    track``'s), MediaPipe's for .ndjson, and for a Live Link .csv turned into points by
    facecast's generic set (by name or its file: it holds the layout's points, in order);
    None when the file names none."""
    if path.suffix.lower() in (".ndjson", ".jsonl"):
        return load_layout("mediapipe_face_mesh")  # the MediaPipe reader's (trackers.py)
    if path.suffix.lower() == ".csv":
        return load_layout() if names_generic_set(source_rig) else None
    if path.suffix.lower() != ".npz":
        return None
    with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as archive:
        if "layout" not in archive.files:
            return None
        name = str(archive["layout"])
    try:
        return load_layout(name)
    except InputError:
        return None  # a layout this facecast does not ship: the counts must agree


def _load_tracker_take(
    path: Path, source_rig: SourceRig | str | os.PathLike[str] | None
) -> SourceAnimation:
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
        with NPY_READS, path.open("rb") as handle:
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


def _load_npz(
    path: Path, feature_indices: npt.ArrayLike | None, keep_vertices: bool
) -> SourceAnimation:
    try:
        with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as archive:
            keys = set(archive.files)
            fps = archive["fps"] if "fps" in keys else DEFAULT_FPS
            timestamps = archive["timestamps"] if "timestamps" in keys else None
            found = archive["found"] if "found" in keys else None
    except FileNotFoundError:
        raise InputError(f"{path}: file not found", code="missing_file") from None
    except Exception as exc:  # zipfile/zlib/numpy raise many types on a corrupt file
        raise InputError(
            f"{path}: not a readable .npz ({type(exc).__name__}: {exc})", code="bad_animation"
        ) from None
    fps = check_fps(np.asarray(fps).reshape(-1)[0] if np.size(fps) == 1 else fps, str(path))
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
    if found is not None:
        points = _hold_untracked(points, found, path)
    check_frames_finite(str(path), points)
    try:
        return SourceAnimation(
            points=points, fps=fps, source_vertices=vertices, timestamps=timestamps
        )
    except InputError as exc:
        raise InputError(f"{path}: {exc.message}", code=exc.code) from None


def _hold_untracked(points: np.ndarray, found: np.ndarray, path: Path) -> np.ndarray:
    """Frames ``found`` marks as without a face take the nearest earlier tracked frame (the
    first tracked one before it): a live viewer too keeps the last face it was sent."""
    found = np.asarray(found)
    if found.dtype != np.bool_ or found.shape != points.shape[:1]:
        raise InputError(
            f"{path}: found must be a bool array of shape ({points.shape[0]},), got "
            f"{found.dtype} {found.shape}",
            code="bad_animation",
        )
    if not found.any():
        raise InputError(
            f"{path}: no frame has a face (found is all false): nothing to clone",
            code="no_face",
        )
    frames = np.arange(found.size)
    source = np.maximum.accumulate(np.where(found, frames, -1))
    source[source < 0] = int(np.argmax(found))
    return points[source]


def _load_obj_frames(
    folder: Path, feature_indices: npt.ArrayLike | None, keep_vertices: bool
) -> SourceAnimation:
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
        fps = check_fps(
            fps_file.read_text(encoding="utf-8", errors="replace").strip(), str(fps_file)
        )
    # Sized by the first frame, so empty until then (a folder has at least one, checked above).
    points = np.empty((0, 0, 3))
    vertices: np.ndarray | None = None
    idx = np.empty(0, dtype=np.int64)
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

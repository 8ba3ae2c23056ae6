"""MediaPipe face-landmarker NDJSON takes -> source animations.

Streams the file line by line with bounded memory and names the line at fault in every
error; it must not fit, clone or touch the network.

MediaPipe face-landmarker NDJSON: one JSON object per line,
``{"landmarks": [[x, y, z] x 478], "transform": [16 floats], "t": seconds}``
(``transform``, the row-major 4x4 facial transformation matrix, and ``t`` optional;
468-landmark meshes without irises are accepted too: they give the layout's first 24
feature points, the iris centres being the last two). Blank lines are skipped.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np

from ..errors import InputError
from .animation import SourceAnimation
from .facemesh import image_to_mesh, normalise_mesh
from .layouts import load_layout
from .take_text import MAX_TAKE_FRAMES, check_fps, open_text

__all__ = [
    "MAX_LINE_CHARS",
    "MEDIAPIPE_FEATURES",
    "MediaPipeTake",
    "load_mediapipe_mapping",
    "mediapipe_animation",
    "read_mediapipe_ndjson",
]

#: Longest NDJSON line accepted, characters (478 landmarks at full precision is ~40 KB).
MAX_LINE_CHARS = 1 << 20

#: MediaPipe face-mesh landmark for each of the layout's feature points, the first 24 in the
#: order of ``facecast.rig.sources.ict.DEFAULT_LANDMARKS`` (Multi-PIE 68 positions), so a
#: MediaPipe take drives a rig imported from ICT-FaceKit with the default landmarks, then
#: the two iris centres (no Multi-PIE position: None): (feature, Multi-PIE 68 position,
#: MediaPipe landmark), read from the one table the /perform page uses too,
#: ``facecast/rig/sources/layouts/mediapipe_face_mesh.json``; "right" is the subject's right.
_LAYOUT = load_layout("mediapipe_face_mesh")
MEDIAPIPE_FEATURES: tuple[tuple[str, int | None, int], ...] = tuple(
    zip(_LAYOUT.feature_names, _LAYOUT.multipie68 or (), _LAYOUT.features.tolist(), strict=True)
)
_DEFAULT_MEDIAPIPE = tuple(_LAYOUT.features.tolist())
_MEDIAPIPE_COUNTS = (468, 478)


def load_mediapipe_mapping(path: str | os.PathLike[str]) -> tuple[int, ...]:
    """A custom MediaPipe landmark index per feature point, from a file.

    JSON (a list of ints, or ``{"indices": [...]}``) or plain text (integers separated
    by spaces, commas or newlines; ``#`` comments).

    Raises
    ------
    InputError
        ``bad_mapping``: unreadable, not integers, empty, out of [0, 478), repeated.
    """
    path = Path(path)
    with open_text(path, "mapping file") as handle:
        try:
            text = handle.read(MAX_LINE_CHARS + 1)
        except UnicodeDecodeError:
            raise InputError(f"{path}: not UTF-8 text", code="bad_mapping") from None
    if len(text) > MAX_LINE_CHARS:
        raise InputError(f"{path}: mapping file too large", code="bad_mapping")
    stripped = text.lstrip()
    try:
        if stripped.startswith(("[", "{")):
            doc = json.loads(text)
            items = doc.get("indices") if isinstance(doc, dict) else doc
            if not isinstance(items, list):
                raise ValueError("expected a list of indices")
        else:
            items = []
            for line in text.splitlines():
                items.extend(t for t in re.split(r"[\s,]+", line.split("#", 1)[0]) if t)
        indices = [_mapping_int(item) for item in items]
    except ValueError as exc:
        raise InputError(
            f"{path}: a mapping is a list of MediaPipe landmark indices ({exc})", code="bad_mapping"
        ) from None
    return _check_mapping(indices, str(path))


def _mapping_int(item: object) -> int:
    if isinstance(item, bool) or not isinstance(item, int | str):
        raise ValueError(f"{item!r} is not an integer")
    return int(item)  # a non-integer string raises ValueError, reported by the caller


def _check_mapping(indices: Sequence[int], where: str) -> tuple[int, ...]:
    if not indices:
        raise InputError(f"{where}: the mapping is empty", code="bad_mapping")
    bad = [i for i in indices if not 0 <= i < _MEDIAPIPE_COUNTS[-1]]
    if bad:
        raise InputError(
            f"{where}: landmark index {bad[0]} is outside [0, {_MEDIAPIPE_COUNTS[-1]})",
            code="bad_mapping",
        )
    if len(set(indices)) != len(indices):
        raise InputError(f"{where}: a landmark is mapped twice", code="bad_mapping")
    return tuple(int(i) for i in indices)


@dataclass(eq=False)
class MediaPipeTake:
    """Feature points of a MediaPipe face-landmarker take.

    Attributes
    ----------
    points : (F, K, 3) float64
        The mapped landmarks, y up (see `read_mediapipe_ndjson`).
    timestamps : (F,) float64 or None
        ``t`` of every line when all lines have one, from the first; else None.
    transforms : (F, 4, 4) float64 or None
        The facial transformation matrices when every line has one.
    """

    points: np.ndarray
    timestamps: np.ndarray | None
    transforms: np.ndarray | None


def read_mediapipe_ndjson(
    path: str | os.PathLike[str],
    *,
    mapping: Sequence[int] | None = None,
    y_up: bool = True,
    face_frame: bool = False,
    image_size: tuple[float, float] = (1.0, 1.0),
    max_frames: int = MAX_TAKE_FRAMES,
) -> MediaPipeTake:
    """Read a MediaPipe face-landmarker NDJSON take, keeping the mapped landmarks.

    Parameters
    ----------
    mapping : sequence of K int, optional
        MediaPipe landmark index of each feature point; default the 24 of
        ``MEDIAPIPE_FEATURES``.
    y_up : bool
        MediaPipe's normalised image coordinates have y down and z into the screen;
        turn them 180 degrees about x to (x, -y, -z), y up like the rigs (a rotation,
        so the server's ``align`` still applies).
    face_frame : bool
        Remove head pose and distance to the camera as ``facecast perform`` and the
        /perform page do: each line's whole mesh goes through
        ``facecast.rig.sources.facemesh.normalise_mesh`` with the ``mediapipe_face_mesh`` layout
        (points about in cm, y up; ``mapping`` and ``y_up`` do not apply). Needs every
        line's mesh to be complete; a degenerate one is ``degenerate_face``.
    image_size : (width, height)
        With ``face_frame``: the video's size in pixels, which makes MediaPipe's
        normalised x and y one unit (leave (1, 1) for a square video).
    max_frames : int

    Raises
    ------
    InputError
        Naming the line: not JSON or not an object (``bad_ndjson``), no ``landmarks``,
        a landmark count other than 468/478 or a landmark that is not 3 numbers
        (``wrong_landmark_count``/``bad_ndjson``), NaN/Inf (``non_finite``), a bad
        ``transform`` or ``t``, ``t`` going backwards, an over-long line, no frames.
    """
    path = Path(path)
    if face_frame and mapping is not None:
        raise InputError("a mapping does not apply with face_frame", code="bad_mapping")
    indices = np.asarray(
        _DEFAULT_MEDIAPIPE if mapping is None else _check_mapping(list(mapping), "mapping")
    )
    # The landmarks read from a line of each count MediaPipe gives. The face frame needs
    # the stable points too: every mesh point of a line. The default mapping takes the
    # layout's earlier count from a line without the iris (468: the first 24 features); a
    # custom one is the caller's, the same for both.
    if face_frame:
        indices_for = {n: np.arange(n) for n in _MEDIAPIPE_COUNTS}
        width, height = (float(v) for v in image_size)
        if not (math.isfinite(width) and math.isfinite(height) and width > 0 and height > 0):
            raise InputError(f"image_size must be positive, got {image_size}", code="bad_input")
    elif mapping is None:
        indices_for = {n: indices[: _LAYOUT.count_within(n)] for n in _MEDIAPIPE_COUNTS}
    else:
        indices_for = dict.fromkeys(_MEDIAPIPE_COUNTS, indices)
    frames: list[np.ndarray] = []
    stamps: list[float | None] = []
    transforms: list[np.ndarray | None] = []
    with open_text(path, "NDJSON file") as handle:
        line_no = 0
        while True:
            try:
                line = handle.readline(MAX_LINE_CHARS + 1)
            except UnicodeDecodeError:
                raise InputError(f"{path}: not UTF-8 text", code="bad_ndjson") from None
            if not line:
                break
            line_no += 1
            if len(line) > MAX_LINE_CHARS:
                raise InputError(
                    f"{path} line {line_no}: longer than {MAX_LINE_CHARS} characters",
                    code="bad_ndjson",
                )
            if not line.strip():
                continue
            if len(frames) >= max_frames:
                raise InputError(
                    f"{path} line {line_no}: more than {max_frames} frames", code="too_many_frames"
                )
            where = f"{path} line {line_no}"
            points, stamp, transform = _parse_mediapipe_line(line, indices_for, where)
            if face_frame:
                try:
                    points = normalise_mesh(image_to_mesh(points, width, height), _LAYOUT)
                except InputError as exc:
                    raise InputError(f"{where}: {exc.message}", code=exc.code) from None
            if stamp is not None and stamps and stamps[-1] is not None and stamp < stamps[-1]:
                raise InputError(
                    f"{where}: t={stamp} is earlier than the line before", code="bad_time"
                )
            if frames and points.shape != frames[0].shape:
                raise InputError(
                    f"{where}: {len(points)} feature points where the lines before gave "
                    f"{len(frames[0])} (a take's meshes all have or all lack the iris)",
                    code="wrong_landmark_count",
                )
            frames.append(points)
            stamps.append(stamp)
            transforms.append(transform)
    if not frames:
        raise InputError(f"{path}: the take has no frames", code="bad_ndjson")
    points = np.stack(frames)
    if y_up and not face_frame:
        points[..., 1:] *= -1.0
    times = None
    if all(s is not None for s in stamps):
        times = np.asarray(stamps, dtype=np.float64)
        times -= times[0]
    given = [m for m in transforms if m is not None]
    mats = np.stack(given) if len(given) == len(transforms) else None
    return MediaPipeTake(points=points, timestamps=times, transforms=mats)


def _parse_mediapipe_line(
    line: str, indices_for: Mapping[int, np.ndarray], where: str
) -> tuple[np.ndarray, float | None, np.ndarray | None]:
    try:
        # NaN/Infinity literals are not JSON; refuse them as non-finite, by name.
        doc = json.loads(line, parse_constant=_refuse_constant)
    except _NonFinite as exc:
        raise InputError(f"{where}: {exc} is not a finite number", code="non_finite") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{where}: not valid JSON ({exc})", code="bad_ndjson") from None
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object", code="bad_ndjson")
    marks = doc.get("landmarks")
    if not isinstance(marks, list):
        raise InputError(f'{where}: no "landmarks" list', code="bad_ndjson")
    if len(marks) not in _MEDIAPIPE_COUNTS:
        raise InputError(
            f"{where}: {len(marks)} landmarks, expected 478 (or 468 without irises)",
            code="wrong_landmark_count",
        )
    indices = indices_for[len(marks)]
    if indices.max() >= len(marks):
        raise InputError(
            f"{where}: the mapping uses landmark {int(indices.max())} but the line has "
            f"{len(marks)}",
            code="wrong_landmark_count",
        )
    picked = np.empty((indices.size, 3))
    for j, i in enumerate(indices):
        picked[j] = _triple(marks[i], f"{where}: landmark {i}")
    if not np.isfinite(picked).all():
        raise InputError(f"{where}: a landmark has NaN or Inf coordinates", code="non_finite")
    stamp = doc.get("t")
    if stamp is not None:
        if not _is_number(stamp):
            raise InputError(f'{where}: "t" must be a number of seconds', code="bad_ndjson")
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise InputError(f'{where}: "t" is not finite', code="non_finite")
    transform = doc.get("transform")
    if transform is not None:
        if not (
            isinstance(transform, list)
            and len(transform) == 16
            and all(_is_number(v) for v in transform)
        ):
            raise InputError(f'{where}: "transform" must be 16 numbers', code="bad_ndjson")
        transform = np.asarray(transform, dtype=np.float64).reshape(4, 4)
        if not np.isfinite(transform).all():
            raise InputError(f'{where}: "transform" is not finite', code="non_finite")
    return picked, stamp, transform


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _triple(value: object, where: str) -> tuple[float, float, float]:
    """``[x, y, z]`` (or ``{"x":, "y":, "z":}``, as some exporters write) as three floats."""
    if isinstance(value, dict):
        value = [value.get("x"), value.get("y"), value.get("z")]
    if not (isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value)):
        raise InputError(f"{where} is not [x, y, z]", code="bad_ndjson")
    return float(value[0]), float(value[1]), float(value[2])


class _NonFinite(ValueError):
    pass


def _refuse_constant(name: str) -> NoReturn:
    raise _NonFinite(name)


def mediapipe_animation(
    path: str | os.PathLike[str],
    *,
    mapping: Sequence[int] | None = None,
    fps: float = 30.0,
    face_frame: bool = False,
    image_size: tuple[float, float] = (1.0, 1.0),
) -> SourceAnimation:
    """A MediaPipe NDJSON take as a ``SourceAnimation`` (``timestamps`` from ``t`` when given).

    The points are in MediaPipe's normalised units, not the rig's: stream them with the
    server's ``align`` and ``scale`` options (or calibration) to map them onto the rig.
    With ``face_frame`` (see `read_mediapipe_ndjson`) they are what ``facecast perform``
    publishes: head pose and distance removed, about in cm; calibration maps them on.
    """
    take = read_mediapipe_ndjson(
        path, mapping=mapping, face_frame=face_frame, image_size=image_size
    )
    return SourceAnimation(points=take.points, fps=check_fps(fps), timestamps=take.timestamps)

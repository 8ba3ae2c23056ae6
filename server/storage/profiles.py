"""Performer profiles: a performer's captured source examples, validated, kept in the rig store.

Parses a calibration capture (JSON or msgpack) and the profile files made from it, and
reads and writes those files under ``<rigs_dir>/performers/``; no fitting, no HTTP.
Blocking calls: run them in a thread. See server/SERVER.md, "Performers".
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn, TypeGuard

import msgpack
import numpy as np

from facecast.rig import estimate_noise
from facecast.rig.sources.layouts import DEFAULT_LAYOUT, layout_names

from ..errors import ApiError, ProfileNotFoundError
from ..names import valid_name
from .rig_store import fsync_directory, write_atomically

__all__ = [
    "PROFILE_FORMAT",
    "Capture",
    "PerformerProfile",
    "ProfileNotFoundError",
    "ProfileStore",
    "parse_capture",
]

PROFILE_FORMAT = "facecast-performer"
PROFILE_VERSION = 1
#: Most expressions a capture may name, and the most points per expression.
MAX_EXPRESSIONS = 4096
MAX_POINTS = 4096
MAX_NAME_CHARS = 256
#: Most held frames a capture may give per expression (20 s at 30 fps), and the fewest
#: (a frame-to-frame step needs two).
MAX_HELD_FRAMES = 600
MIN_HELD_FRAMES = 2
#: The least landmark noise held frames measure (layout units: 0.1 mm in the mediapipe
#: layout's centimetres). Below it a spread measures the tracker's stillness, not the noise
#: of a performance: a still image tracks identically frame after frame.
HELD_NOISE_FLOOR = 0.01
_SUFFIX = ".json"
_JSON_TYPES = ("application/json",)
_MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")


@dataclass(frozen=True, eq=False)
class Capture:
    """A validated capture body: points per expression name, in some landmark layout.

    Attributes
    ----------
    points : {name: (K, 3) float64}
        Every entry has the same K; shapes and finiteness are checked, names against a
        rig are not (``facecast.rig.retarget`` does that).
    noise : float or None
        The landmark noise the fit uses: the capture's own ``noise`` when it gives one,
        else the one measured from its ``held`` frames (``held_noise``), else None.
    noise_source : {"capture", "held_frames", None}
        Where ``noise`` came from.
    held_frames : int
        How many held frames measured it (0 unless ``noise_source`` is "held_frames").
    """

    layout: str
    points: dict[str, np.ndarray]
    noise: float | None
    noise_source: str | None = None
    held_frames: int = 0

    @property
    def num_points(self) -> int:
        return int(next(iter(self.points.values())).shape[0])


@dataclass(frozen=True, eq=False)
class PerformerProfile:
    """A performer's latest capture and where it was made (the file under ``performers/``)."""

    performer: str
    rig: str  # the rig the capture was made for
    capture: Capture
    captured: float = field(default_factory=time.time)  # POSIX seconds

    def to_bytes(self) -> bytes:
        doc = {
            "format": PROFILE_FORMAT,
            "version": PROFILE_VERSION,
            "performer": self.performer,
            "rig": self.rig,
            "captured": self.captured,
            "layout": self.capture.layout,
            "noise": self.capture.noise,
            "noise_source": self.capture.noise_source,
            "held_frames": self.capture.held_frames,
            "points": {name: p.tolist() for name, p in self.capture.points.items()},
        }
        return json.dumps(doc, separators=(",", ":")).encode()

    def summary(self) -> dict[str, Any]:
        return {
            "performer": self.performer,
            "rig": self.rig,
            "captured": self.captured,
            "layout": self.capture.layout,
            "noise": self.capture.noise,
            "noise_source": self.capture.noise_source,
            "num_points": self.capture.num_points,
            "expressions": list(self.capture.points),
        }

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> PerformerProfile:
        """Parse and validate a profile file; ``ValueError`` naming what is wrong."""
        try:
            doc = json.loads(data, parse_constant=_refuse_constant)
        except (ValueError, RecursionError) as exc:
            raise ValueError(f"{where}: not a profile ({exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != PROFILE_FORMAT:
            raise ValueError(f"{where}: not a {PROFILE_FORMAT} file")
        if doc.get("version") != PROFILE_VERSION:
            raise ValueError(f"{where}: unknown profile version {doc.get('version')!r}")
        performer, rig, captured = doc.get("performer"), doc.get("rig"), doc.get("captured")
        if not (isinstance(performer, str) and valid_name(performer)):
            raise ValueError(f"{where}: bad performer name")
        if not (isinstance(rig, str) and valid_name(rig)):
            raise ValueError(f"{where}: bad rig id")
        if not (_is_number(captured) and math.isfinite(captured)):
            raise ValueError(f"{where}: bad capture time")
        body = {k: doc.get(k) for k in ("layout", "noise", "points")}
        try:
            capture = _capture_from_doc(body)
        except ApiError as exc:
            raise ValueError(f"{where}: {exc.detail}") from None
        # A profile keeps the noise its capture was fitted with, and where it came from
        # (profiles written before these fields read as the capture's own noise).
        source, frames = doc.get("noise_source"), doc.get("held_frames", 0)
        if capture.noise is not None and source in ("capture", "held_frames"):
            if not (isinstance(frames, int) and not isinstance(frames, bool) and frames >= 0):
                raise ValueError(f"{where}: bad held_frames")
            capture = Capture(capture.layout, capture.points, capture.noise, source, frames)
        return cls(performer=performer, rig=rig, capture=capture, captured=float(captured))


class _NonFinite(ValueError):
    pass


def _refuse_constant(name: str) -> NoReturn:
    # NaN/Infinity literals are not JSON; refuse them as non-finite, by name.
    raise _NonFinite(f"{name} is not a finite number")


def _is_number(value: object) -> TypeGuard[int | float]:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _bad(code: str, detail: str, status: int = 422) -> ApiError:
    return ApiError(status, code, detail)


def parse_capture(data: bytes, content_type: str | None) -> Capture:
    """Decode and validate a capture body (JSON, or msgpack by its content type).

    The body is ``{"layout": str, "points": {name: [[x, y, z] x K]}, "noise": float,
    "held": {name: [[[x, y, z] x K] x F]}}`` (``layout`` defaults to
    ``mediapipe_face_mesh``; ``noise`` and ``held`` are optional). ``held`` gives, for some
    or all expressions, the F frames (2 to ``MAX_HELD_FRAMES``, in capture order) over which
    the expression was held; without ``noise`` the landmark noise is measured from them
    (``held_noise``). A ``noise`` given wins: it is the caller's say.

    Raises
    ------
    ApiError
        415 ``unsupported_media_type``; 400 ``bad_capture`` for bytes that do not decode;
        422 ``bad_capture`` (wrong types, empty, too many names), ``wrong_point_count``
        (not K x 3, or K differing between expressions), ``non_finite``, ``bad_noise``,
        ``unknown_layout``, ``bad_held_frames`` (held frames of an expression not in
        ``points``, fewer than 2 or more than ``MAX_HELD_FRAMES``, or of another K; a frame
        that is not K x 3 numbers is ``wrong_point_count``, one with NaN ``non_finite``).
    """
    kind = (content_type or "application/json").split(";", 1)[0].strip().lower()
    try:
        if kind in _JSON_TYPES:
            doc = json.loads(data, parse_constant=_refuse_constant)
        elif kind in _MSGPACK_TYPES:
            doc = msgpack.unpackb(
                data,
                raw=False,
                strict_map_key=True,
                max_str_len=4 * MAX_NAME_CHARS,
                max_bin_len=0,
                max_array_len=max(MAX_POINTS * 3, MAX_HELD_FRAMES),
                max_map_len=MAX_EXPRESSIONS,
                max_ext_len=0,
            )
        else:
            raise _bad(
                "unsupported_media_type",
                f"a capture is application/json or application/msgpack, not {kind!r}",
                415,
            )
    except ApiError:
        raise
    except _NonFinite as exc:
        raise _bad("non_finite", f"the capture holds {exc}") from None
    except (ValueError, RecursionError, msgpack.UnpackException, TypeError) as exc:
        raise _bad("bad_capture", f"the body is not valid {kind} ({exc})", 400) from None
    return _capture_from_doc(doc, allow_held=True)


def held_noise(held: dict[str, np.ndarray]) -> tuple[float, int]:
    """The landmark noise sigma of held expressions, and the frames that measured it.

    ``rig.estimate_noise`` on each expression's held frames (half the mean squared
    frame-to-frame step, so a slow drift of the held face does not count), pooled over the
    expressions by their frame-to-frame steps: sigma^2 = sum_e (F_e - 1) sigma_e^2 /
    sum_e (F_e - 1); at least ``HELD_NOISE_FLOOR``.

    Parameters
    ----------
    held : {name: (F, K, 3) float}, each F >= 2
    """
    steps = np.array([len(frames) - 1 for frames in held.values()], dtype=np.float64)
    variances = np.array([estimate_noise(frames) ** 2 for frames in held.values()])
    sigma = max(HELD_NOISE_FLOOR, float(np.sqrt(np.dot(steps, variances) / steps.sum())))
    return sigma, int(sum(len(frames) for frames in held.values()))


def _capture_from_doc(doc: object, *, allow_held: bool = False) -> Capture:
    fields = ("layout", "points", "noise", "held") if allow_held else ("layout", "points", "noise")
    if not isinstance(doc, dict):
        raise _bad("bad_capture", 'a capture is an object {"layout", "points", "noise"}')
    unknown = sorted(str(k) for k in doc if k not in fields)
    if unknown:
        raise _bad("bad_capture", f"unknown capture field {unknown[0][:40]!r}")
    layout = doc.get("layout") or DEFAULT_LAYOUT
    if not isinstance(layout, str) or layout not in layout_names():
        raise _bad(
            "unknown_layout",
            f"no landmark layout named {str(layout)[:64]!r}; expected one of "
            f"{', '.join(layout_names())}",
        )
    noise = doc.get("noise")
    if noise is not None and not (_is_number(noise) and math.isfinite(noise) and noise >= 0):
        raise _bad("bad_noise", f"noise must be a finite number >= 0, got {str(noise)[:40]}")
    points_doc = doc.get("points")
    if not isinstance(points_doc, dict) or not points_doc:
        raise _bad("bad_capture", 'points must be an object {"neutral": [[x, y, z], ...], ...}')
    if len(points_doc) > MAX_EXPRESSIONS:
        raise _bad("bad_capture", f"more than {MAX_EXPRESSIONS} expressions")
    points: dict[str, np.ndarray] = {}
    k = None
    for name, value in points_doc.items():
        if not isinstance(name, str) or not 0 < len(name) <= MAX_NAME_CHARS:
            raise _bad("bad_capture", f"expression names are 1-{MAX_NAME_CHARS} characters")
        array = _points_array(name, value)
        if k is None:
            k = array.shape[0]
        elif array.shape[0] != k:
            raise _bad(
                "wrong_point_count",
                f"points[{name!r}] has {array.shape[0]} points, the first expression {k}",
            )
        points[name] = array
    held = _held_frames(doc.get("held"), points, k) if allow_held else None
    if noise is not None:
        return Capture(layout, points, float(noise), "capture")
    if held:
        sigma, frames = held_noise(held)
        return Capture(layout, points, sigma, "held_frames", frames)
    return Capture(layout=layout, points=points, noise=None)


def _held_frames(
    value: object, points: dict[str, np.ndarray], k: int | None
) -> dict[str, np.ndarray] | None:
    """Validate ``held``: {name of a captured expression: F x K x 3 frames}."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise _bad("bad_held_frames", 'held must be an object {"neutral": [frame, ...], ...}')
    held: dict[str, np.ndarray] = {}
    for name, frames in value.items():
        if not isinstance(name, str) or name not in points:
            raise _bad(
                "bad_held_frames",
                f"held frames of {str(name)[:64]!r}, which points does not capture",
            )
        if not (isinstance(frames, list) and MIN_HELD_FRAMES <= len(frames) <= MAX_HELD_FRAMES):
            raise _bad(
                "bad_held_frames",
                f"held[{name!r}] must be a list of {MIN_HELD_FRAMES}-{MAX_HELD_FRAMES} frames",
            )
        stack = [_points_array(f"held {name!r} frame {i}", f) for i, f in enumerate(frames)]
        if any(frame.shape[0] != k for frame in stack):
            raise _bad("bad_held_frames", f"held[{name!r}]: every frame has {k} points")
        held[name] = np.stack(stack)
    return held


def _points_array(name: str, value: object) -> np.ndarray:
    rows_ok = (
        isinstance(value, list)
        and 0 < len(value) <= MAX_POINTS
        and all(
            isinstance(row, list) and len(row) == 3 and all(_is_number(v) for v in row)
            for row in value
        )
    )
    if not rows_ok or not isinstance(value, list):  # (rows_ok means a list: for mypy)
        raise _bad(
            "wrong_point_count",
            f"points[{name!r}] must be a list of 1-{MAX_POINTS} [x, y, z] numbers",
        )
    try:
        array = np.asarray(value, dtype=np.float64)
    except OverflowError:  # an integer beyond float range
        array = np.full((len(value), 3), np.inf)
    if not np.isfinite(array).all():
        raise _bad("non_finite", f"points[{name!r}] holds NaN or Inf")
    return array


class ProfileStore:
    """Performer profiles as ``<name>.json`` in ``directory`` (the rig store's ``performers/``).

    Names must satisfy ``valid_name`` (callers check first; here a bad one is a
    ``ValueError``). A file that does not validate on load is a ``ValueError`` too.
    """

    def __init__(self, directory: Path, *, max_bytes: int, scratch: Callable[[], Path]) -> None:
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        # The rig store's scratch folder (claimed on first use), for temp files of writes.
        self._scratch = scratch

    def _path(self, performer: str) -> Path:
        if not valid_name(performer):
            raise ValueError(f"invalid performer name {performer!r}")
        return self.directory / f"{performer}{_SUFFIX}"

    def get(self, performer: str) -> PerformerProfile:
        path = self._path(performer)
        try:
            with path.open("rb") as fh:
                data = fh.read(4 * self.max_bytes + 1)
        except FileNotFoundError:
            raise ProfileNotFoundError(performer) from None
        if len(data) > 4 * self.max_bytes:
            raise ValueError(f"performer profile {performer!r}: file too large")
        profile = PerformerProfile.from_bytes(data, f"performer profile {performer!r}")
        if profile.performer != performer:
            raise ValueError(f"performer profile {performer!r} names {profile.performer!r}")
        return profile

    def put(self, profile: PerformerProfile) -> bool:
        """Store (replace) the profile; returns whether it is new."""
        self._path(profile.performer)
        self.directory.mkdir(parents=True, exist_ok=True)
        return write_atomically(
            self.directory,
            f"{profile.performer}{_SUFFIX}",
            profile.to_bytes(),
            scratch=self._scratch(),
        )

    def delete(self, performer: str) -> None:
        path = self._path(performer)
        try:
            path.unlink()
        except FileNotFoundError:
            raise ProfileNotFoundError(performer) from None
        with contextlib.suppress(OSError):
            fsync_directory(self.directory)

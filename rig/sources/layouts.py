"""Landmark layouts: which of a tracker's mesh points are the rig's feature points, as data.

Loads and validates the JSON tables in ``facecast/rig/sources/layouts/`` (one per tracker; a new
tracker is a new table, no code). It must not read frames, fit or touch the network.

A layout file is one JSON object::

    name            str, the file's stem
    tracker_points  int N, points of the tracker's mesh (indices lie in [0, N))
    features        K mesh indices: the feature points, in the order of the rig's points
    feature_names   K str
    multipie68      K int or null, optional: the Multi-PIE 68 position of each feature, so
                    the table maps onto ``facecast.rig.sources.ict.DEFAULT_LANDMARKS``;
                    null for a feature the 68 do not have (an iris centre), only after
                    every feature that has one
    stable          mesh indices that expressions barely move (head-pose removal)
    eyes            {"left"|"right": {"upper", "lower", "outer", "inner": index}}
    frame           {"left", "right", "bottom", "top": [indices], "span": float}: the
                    face-fixed frame of ``facecast.rig.sources.facemesh`` (see there)
    source          str, optional: where the correspondences come from
    earlier_counts  [int], optional: the feature counts of this layout's earlier versions.
                    A layout only grows by appending features, so a rig fitted on an
                    earlier version (K points) is driven by the first K of today's points
                    (``Layout.drives``); captures and rigs stored before stay usable.
                    A mesh with fewer than ``tracker_points`` points (MediaPipe's 468
                    without the iris) gives the longest of these counts whose features it
                    has (``Layout.count_within``).
"""

from __future__ import annotations

import functools
import json
import math
import re
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["DEFAULT_LAYOUT", "Layout", "layout_from_dict", "layout_names", "load_layout"]

#: The layout used when none is named: MediaPipe's 468/478-point face mesh.
DEFAULT_LAYOUT = "mediapipe_face_mesh"

_NAME = re.compile(r"^[a-z0-9][a-z0-9_]{0,63}$")
_EYE_PARTS = ("upper", "lower", "outer", "inner")
_FRAME_PARTS = ("left", "right", "bottom", "top")
_KNOWN_KEYS = {
    "name",
    "tracker_points",
    "features",
    "feature_names",
    "multipie68",
    "stable",
    "eyes",
    "frame",
    "source",
    "earlier_counts",
}
_MAX_TRACKER_POINTS = 100_000
_MAX_FILE_BYTES = 1 << 20


@dataclass(frozen=True, eq=False)
class Layout:
    """A validated landmark layout (see the module docstring for the fields).

    Attributes
    ----------
    features : (K,) int64
    stable : (S,) int64, S >= 3
    eyes : {"left"|"right": {"upper"|"lower"|"outer"|"inner": int}}
    frame : {"left"|"right"|"bottom"|"top": (n,) int64}
    span : float
        Distance between the two eye centres in the normalised frame (cm of an average
        adult face), so normalised points come out in about centimetres.
    """

    name: str
    tracker_points: int
    features: np.ndarray
    feature_names: tuple[str, ...]
    multipie68: tuple[int | None, ...] | None
    stable: np.ndarray
    eyes: dict[str, dict[str, int]]
    frame: dict[str, np.ndarray]
    span: float
    source: str = ""
    earlier_counts: tuple[int, ...] = ()

    @property
    def num_features(self) -> int:
        return int(self.features.size)

    @property
    def counts(self) -> tuple[int, ...]:
        """The feature counts a rig of this layout may have: earlier versions', then K."""
        return (*self.earlier_counts, self.num_features)

    def drives(self, k: int) -> bool:
        """Whether a rig of ``k`` feature points takes this layout's points: ``k`` is its
        feature count, or an earlier version's (then the first ``k`` points)."""
        return k in self.counts

    def takes_first(self, points: int, k: int) -> bool:
        """Whether a rig of ``k`` feature points takes the first ``k`` of ``points`` points
        of this layout: both are its counts and ``k`` is smaller (an earlier version's
        features are the first of a later one's, in order)."""
        return k < points and self.drives(k) and self.drives(points)

    @property
    def multipie_count(self) -> int:
        """How many leading features have a Multi-PIE 68 position (0 without the table)."""
        if self.multipie68 is None:
            return 0
        return sum(1 for position in self.multipie68 if position is not None)

    def count_within(self, n: int) -> int:
        """The most feature points a mesh of ``n`` points gives: the largest of ``counts``
        whose features all lie below ``n``.

        Raises
        ------
        InputError
            ``wrong_landmark_count``: the mesh lacks a point of the face frame or the
            stable set, or of the layout's first version's features.
        """
        frame = max(
            int(self.stable.max()),
            *(int(f.max()) for f in self.frame.values()),
            *(i for parts in self.eyes.values() for i in parts.values()),
        )
        least = 1 + max(frame, int(self.features[: self.counts[0]].max()))
        if n < least:
            raise InputError(
                f"a mesh of {n} points is too few for layout {self.name}: it needs "
                f"{self.tracker_points} ({least} for its first {self.counts[0]} features)",
                code="wrong_landmark_count",
            )
        return next(k for k in reversed(self.counts) if int(self.features[:k].max()) < n)

    def to_dict(self) -> dict[str, Any]:
        """The layout as the JSON object it was read from."""
        doc: dict[str, Any] = {
            "name": self.name,
            "tracker_points": self.tracker_points,
            "features": self.features.tolist(),
            "feature_names": list(self.feature_names),
            "stable": self.stable.tolist(),
            "eyes": {side: dict(parts) for side, parts in self.eyes.items()},
            "frame": {
                **{part: self.frame[part].tolist() for part in _FRAME_PARTS},
                "span": self.span,
            },
        }
        if self.multipie68 is not None:
            doc["multipie68"] = list(self.multipie68)
        if self.source:
            doc["source"] = self.source
        if self.earlier_counts:
            doc["earlier_counts"] = list(self.earlier_counts)
        return doc


def _fail(where: str, message: str) -> InputError:
    return InputError(f"layout {where}: {message}", code="bad_layout")


def _index(value: object, n: int, where: str, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(where, f"{what} must be an integer, got {value!r}")
    if not 0 <= value < n:
        raise _fail(where, f"{what} = {value} is outside [0, {n})")
    return value


def _indices(value: object, n: int, where: str, what: str, *, minimum: int = 1) -> np.ndarray:
    if not isinstance(value, list) or len(value) < minimum:
        raise _fail(where, f"{what} must be a list of at least {minimum} mesh indices")
    out = [_index(v, n, where, f"{what}[{i}]") for i, v in enumerate(value)]
    if len(set(out)) != len(out):
        raise _fail(where, f"{what} names a mesh point twice")
    return np.asarray(out, dtype=np.int64)


def layout_from_dict(doc: object, where: str = "<dict>") -> Layout:
    """Validate a layout's JSON object.

    Raises
    ------
    InputError
        ``bad_layout``, naming the field: a missing or unknown key, an index that is not
        an integer in ``[0, tracker_points)``, a repeated index, fewer than 3 stable
        points, names that do not match the features one for one, a bad eye or frame.
    """
    if not isinstance(doc, dict):
        raise _fail(where, "expected a JSON object")
    unknown = sorted(set(doc) - _KNOWN_KEYS)
    if unknown:
        raise _fail(where, f"unknown key {unknown[0]!r}")
    missing = [k for k in ("name", "tracker_points", "features", "stable", "eyes", "frame")
               if k not in doc]  # fmt: skip
    if missing:
        raise _fail(where, f"missing key {missing[0]!r}")
    name = doc["name"]
    if not isinstance(name, str) or not _NAME.match(name):
        raise _fail(where, f"name must match {_NAME.pattern}, got {name!r}")
    n = doc["tracker_points"]
    if isinstance(n, bool) or not isinstance(n, int) or not 3 <= n <= _MAX_TRACKER_POINTS:
        raise _fail(where, f"tracker_points must be an integer in [3, {_MAX_TRACKER_POINTS}]")
    features = _indices(doc["features"], n, where, "features")
    k = features.size
    names = doc.get("feature_names", [f"p{i}" for i in range(k)])
    if not (isinstance(names, list) and all(isinstance(s, str) and s for s in names)):
        raise _fail(where, "feature_names must be a list of non-empty strings")
    if len(names) != k or len(set(names)) != k:
        raise _fail(where, f"feature_names must name the {k} features once each")
    multipie = doc.get("multipie68")
    if multipie is not None:
        if not isinstance(multipie, list) or len(multipie) != k:
            raise _fail(where, f"multipie68 must list {k} positions, one per feature")
        multipie = tuple(
            None if v is None else _index(v, 68, where, f"multipie68[{i}]")
            for i, v in enumerate(multipie)
        )
        known = [v for v in multipie if v is not None]
        if not known or any(v is None for v in multipie[: len(known)]):
            raise _fail(
                where,
                "multipie68 starts with positions; its nulls (features the 68 lack) come last",
            )
    stable = _indices(doc["stable"], n, where, "stable", minimum=3)
    eyes_doc = doc["eyes"]
    if not isinstance(eyes_doc, dict) or set(eyes_doc) != {"left", "right"}:
        raise _fail(where, 'eyes must be {"left": {...}, "right": {...}}')
    eyes: dict[str, dict[str, int]] = {}
    for side in ("left", "right"):
        parts = eyes_doc[side]
        if not isinstance(parts, dict) or set(parts) != set(_EYE_PARTS):
            raise _fail(where, f"eyes.{side} must have exactly {', '.join(_EYE_PARTS)}")
        eyes[side] = {p: _index(parts[p], n, where, f"eyes.{side}.{p}") for p in _EYE_PARTS}
    frame_doc = doc["frame"]
    if not isinstance(frame_doc, dict) or set(frame_doc) != {*_FRAME_PARTS, "span"}:
        raise _fail(where, f"frame must have exactly {', '.join(_FRAME_PARTS)}, span")
    frame = {p: _indices(frame_doc[p], n, where, f"frame.{p}") for p in _FRAME_PARTS}
    span = frame_doc["span"]
    if (
        isinstance(span, bool)
        or not isinstance(span, int | float)
        or not (math.isfinite(span) and span > 0)
    ):
        raise _fail(where, f"frame.span must be a positive number, got {span!r}")
    source = doc.get("source", "")
    if not isinstance(source, str):
        raise _fail(where, "source must be a string")
    earlier = doc.get("earlier_counts", [])
    if (
        not isinstance(earlier, list)
        or any(isinstance(c, bool) or not isinstance(c, int) for c in earlier)
        or any(not 0 < c < k for c in earlier)
        or sorted(set(earlier)) != earlier
    ):
        raise _fail(where, f"earlier_counts must be increasing feature counts in [1, {k})")
    for array in (features, stable, *frame.values()):
        array.flags.writeable = False  # layouts are shared (load_layout caches them)
    return Layout(
        name=name,
        tracker_points=n,
        features=features,
        feature_names=tuple(names),
        multipie68=multipie,
        stable=stable,
        eyes=eyes,
        frame=frame,
        span=float(span),
        source=source,
        earlier_counts=tuple(earlier),
    )


def layout_names() -> tuple[str, ...]:
    """Names of the layouts shipped with facecast."""
    folder = resources.files(__package__).joinpath("layouts")
    return tuple(sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json")))


def load_layout(name: str = DEFAULT_LAYOUT) -> Layout:
    """A shipped layout by name (``mediapipe_face_mesh``...).

    Raises
    ------
    InputError
        ``unknown_layout`` for a name that is not shipped; ``bad_layout`` for a table that
        does not validate (a packaging error).
    """
    if not isinstance(name, str) or not _NAME.match(name) or name not in layout_names():
        raise InputError(
            f"no landmark layout named {name!r}; expected one of {', '.join(layout_names())}",
            code="unknown_layout",
        )
    return _read_layout(name)


@functools.cache
def _read_layout(name: str) -> Layout:
    path = resources.files(__package__).joinpath("layouts", f"{name}.json")
    text = path.read_bytes()[: _MAX_FILE_BYTES + 1]
    if len(text) > _MAX_FILE_BYTES:
        raise _fail(name, "file too large")
    try:
        doc = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _fail(name, f"not valid JSON ({exc})") from None
    layout = layout_from_dict(doc, name)
    if layout.name != name:
        raise _fail(name, f"the file is named {name!r} but its name is {layout.name!r}")
    return layout

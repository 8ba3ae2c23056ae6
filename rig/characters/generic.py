"""facecast's generic ARKit source set: ICT-FaceKit's face for each ARKit shape, 26 points.

Reads the package data ``generic_arkit/points.npz`` (written by
scripts/make_generic_sources.py from ICT-FaceKit, MIT, see generic_arkit/LICENSE-ICT-FaceKit:
ICT's 24 default landmarks, the lids and the two iris centres as facecast's tracker sees
ICT's generic face; README, option (z))
and composes source points for VRM presets that have no ARKit twin (the table is
docs/characters.md), from this set's shapes or from a performer's captured ones
(``composed_captures``); ``CHARACTER_FIT_DEFAULTS`` are the fit options of a character
paired with it, ``GAZE_SHAPES``, ``DRIVEN_SHARE`` and ``DEPENDENT_RELATIVE`` what it leaves
unpaired so that what shows moves at full strength. It must not read characters, fit or
touch the network.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from types import MappingProxyType
from typing import Final

import numpy as np

from ..errors import ExampleSetError
from ..npy_reads import NPY_READS

__all__ = [
    "CHARACTER_FIT_DEFAULTS",
    "DEPENDENT_RELATIVE",
    "DRIVEN_SHARE",
    "GAZE_SHAPES",
    "GENERIC_ATTRIBUTION",
    "GENERIC_SOURCE_NAME",
    "PART_COMPOSITIONS",
    "PRESET_CHECK_ORDER",
    "VRM_COMPOSITIONS",
    "GenericSources",
    "composed_captures",
    "generic_sources",
    "is_gaze",
    "is_generic_layout",
]

GENERIC_ATTRIBUTION: Final = (
    "generic ARKit source set: 24 landmarks of the ICT Face Model and 2 iris centres, its "
    "lids and irises as facecast's tracker sees it (ICT-FaceKit, USC Institute for Creative "
    "Technologies, MIT licence)"
)

#: ``fit`` options of a character paired with this set when its uploader gives no noise:
#: the landmark noise (centimetres, this set's units) and the bound the rig is fitted for.
#: Exact interpolation (noise 0) of the 20 points (the layout then) amplifies noise ~3000-fold
#: (noise gain 3174): live, tracker noise became weights of 7 to 190. Measured on the
#: ground-truth webcam benchmark and the bundled real take (docs/characters.md, "Fit
#: defaults"): 0.05 cm with weights bounded to [0, 1] had the lowest weight error on tracked
#: landmarks (0.03 cm: +0.004 to +0.007), cost nothing on /perform's noise-aware calibrate
#: and kept every weight in [0, 1]. It held the generic source's own exact poses below full
#: strength, though (the ridge it stands for shrinks a closed eye's 0.79 cm lid motion to
#: eyeBlink 0.85, gaze already unpaired); 0.035 cm gives 0.92, and on the bundled take
#: a lower weight error on exact and Gaussian-noisy landmarks ("Full strength"); its noise
#: gain is 13.6.
CHARACTER_FIT_DEFAULTS: Final = MappingProxyType({"noise": 0.035, "clamp": "unit"})

_L, _R = "Left", "Right"


def _both(shape: str, weight: float) -> dict[str, float]:
    return {shape + _L: weight, shape + _R: weight}


#: VRM 1.0 presets without an ARKit twin, as weighted sums of ARKit shapes: their source
#: points are the neutral plus these weights times the shapes' deltas. Visemes follow the
#: Japanese vowels VRM names (aa あ, ih い, ou う, ee え, oh お); emotions the usual FACS
#: reading of each (happy: AU6+12, angry: AU4+9, sad: AU1+15, surprised: AU1+2+5+26).
VRM_COMPOSITIONS: Final = MappingProxyType(
    {
        # The jaw alone: aa is the open mouth, the other vowels shape it (a jaw-open pose
        # reads as aa; composed as jawOpen 0.6 + mouthLowerDown 0.3, it needed ee 0.69 too).
        "aa": {"jawOpen": 1.0},
        "ih": {"jawOpen": 0.15, **_both("mouthStretch", 0.5), **_both("mouthSmile", 0.3)},
        "ou": {"jawOpen": 0.15, "mouthPucker": 0.9, "mouthFunnel": 0.3},
        # The lower lip down too: else ee lay in the span of aa, ih and a smile.
        "ee": {"jawOpen": 0.35, **_both("mouthStretch", 0.4), **_both("mouthLowerDown", 0.3)},
        "oh": {"jawOpen": 0.45, "mouthFunnel": 0.7},
        "blink": _both("eyeBlink", 1.0),
        "blinkLeft": {"eyeBlinkLeft": 1.0},
        "blinkRight": {"eyeBlinkRight": 1.0},
        "happy": {**_both("mouthSmile", 0.8), **_both("cheekSquint", 0.5), **_both("eyeSquint", 0.3)},
        "angry": {**_both("browDown", 0.9), **_both("noseSneer", 0.4), **_both("mouthFrown", 0.3)},
        "sad": {"browInnerUp": 0.9, **_both("mouthFrown", 0.7)},
        "relaxed": {**_both("mouthSmile", 0.5), **_both("eyeBlink", 0.35)},
        "surprised": {"browInnerUp": 0.8, **_both("browOuterUp", 0.8), **_both("eyeWide", 0.8), "jawOpen": 0.4},
        "lookUp": _both("eyeLookUp", 1.0),
        "lookDown": _both("eyeLookDown", 1.0),
        # The character's own left: its left eye turns out, its right eye in.
        "lookLeft": {"eyeLookOutLeft": 1.0, "eyeLookInRight": 1.0},
        "lookRight": {"eyeLookInLeft": 1.0, "eyeLookOutRight": 1.0},
    }
)  # fmt: skip


#: VRoid Studio's part clips (``expression_names.VROID_PART_CLIPS``), each the part of its
#: emotion's composition above that it moves: ``Fcl_MTH_Joy`` the mouth of ``happy`` (a full
#: smile), ``Fcl_EYE_Joy`` its eyes, ``Fcl_BRW_Angry`` the brows of ``angry``... Paired, a
#: smile drives the mouth-only clip; the whole-face ``Fcl_ALL_*`` emotion is then a mix of
#: its parts (or mostly driven by them) and is left out.
PART_COMPOSITIONS: Final = MappingProxyType(
    {
        "Fcl_MTH_Joy": _both("mouthSmile", 1.0),
        "Fcl_MTH_Fun": _both("mouthSmile", 0.5),
        "Fcl_MTH_Sorrow": _both("mouthFrown", 0.7),
        "Fcl_MTH_Angry": {**_both("noseSneer", 0.4), **_both("mouthFrown", 0.3)},
        "Fcl_EYE_Joy": {**_both("cheekSquint", 0.5), **_both("eyeSquint", 0.3)},
        "Fcl_EYE_Surprised": _both("eyeWide", 0.8),
        "Fcl_BRW_Angry": _both("browDown", 0.9),
        "Fcl_BRW_Sorrow": {"browInnerUp": 0.9},
        "Fcl_BRW_Surprised": {"browInnerUp": 0.8, **_both("browOuterUp", 0.8)},
    }
)  # fmt: skip
_COMPOSED: Final = MappingProxyType({**VRM_COMPOSITIONS, **PART_COMPOSITIONS})

#: ARKit shapes the generic set leaves unpaired: gaze. Its landmarks hold lid points (two
#: per eye in the 20-point layout these figures were measured on, four now) and no iris,
#: so it sees a gaze only by the lids it drags: eyeLookDown lowers the outer upper lid
#: point 0.64 cm where eyeBlink lowers it 0.79 cm. Paired, a rig fitted for
#: tracker noise (``CHARACTER_FIT_DEFAULTS``) split the exact "both eyes closed" pose into
#: eyeBlink 0.57 + eyeLookDown 0.37 (half-open eyes), and a VRM's look presets, whose
#: lid motion is within that noise of the rest pose, took 0.02-0.07 at the exact neutral.
#: With four lid points an eye it is still 0.75 + 0.26 (a look down 0.74 + blink 0.19; the
#: whole set fitted with these defaults, 2026-12-04): gaze stays unpaired.
#: Gaze is the character's look-at's (its eye bones), not these points'.
GAZE_SHAPES: Final = tuple(
    f"eyeLook{way}{side}" for side in (_L, _R) for way in ("Down", "In", "Out", "Up")
)
_GAZE: Final = frozenset(GAZE_SHAPES)


def is_gaze(name: str) -> bool:
    """Whether the expression ``name`` is gaze: one of ``GAZE_SHAPES`` or a preset composed
    of them (VRM's ``lookUp``...). An upload leaves it unpaired; a re-based rig with none
    reads its blinks through a curve of its own (``rebase.default_contrast``)."""
    return name in _GAZE or not _GAZE.isdisjoint(_COMPOSED.get(name, ()))


#: A composed VRM preset whose motion the character's own ARKit shapes carry at least this
#: share of (``GenericSources.driven_share``) is left unpaired: paired too, it would drive
#: the same motion twice (a mouth-only smile became VRoid's whole-face ``Fcl_ALL_Joy``).
#: Below it the preset drives what those shapes lack (``aa`` beside a ``jawOpen`` that
#: moves nothing). VRoid's part clips count as their shapes for an emotion holding them all.
DRIVEN_SHARE: Final = 0.5

#: A composed preset whose displacement at these landmarks lies within this fraction (of
#: its length) of the span of those paired before it (the character's ARKit shapes, then
#: presets in ``PRESET_CHECK_ORDER``) is left unpaired: it is a mix of them, to rounding
#: (``blink`` is ``blinkLeft`` + ``blinkRight``; ``ee`` beside ``aa`` on a character whose
#: ``jawOpen`` moves nothing is ``aa`` plus its ARKit shapes). Paired, the rig's examples
#: would be linearly dependent, and the fit cannot then keep the neutral exact (a rig took
#: 0.07 of eyeSquint and 0.44 in all at the exact neutral).
DEPENDENT_RELATIVE: Final = 1e-6

#: The order presets are checked in against ``DEPENDENT_RELATIVE``: one-sided blinks before
#: both (each eye its own weight), the mouth-only visemes and VRoid's part clips before the
#: whole-face emotions.
PRESET_CHECK_ORDER: Final = (
    "blinkLeft", "blinkRight", "aa", "ih", "ou", "ee", "oh", *PART_COMPOSITIONS,
    "happy", "angry", "sad", "relaxed", "surprised", "blink",
    "lookUp", "lookDown", "lookLeft", "lookRight",
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class GenericSources:
    """The generic set: ``names`` (neutral first), ``points`` (M, K, 3) in centimetres,
    ``landmarks68`` (K,) the Multi-PIE position of each point (-1: none, the iris
    centres), ``stable_points`` (S,)."""

    names: tuple[str, ...]
    points: np.ndarray
    landmarks68: np.ndarray
    stable_points: np.ndarray

    def source_points(self, name: str) -> np.ndarray | None:
        """(K, 3) points of an ARKit shape, a composed VRM preset or a VRoid part clip; None
        if it has none."""
        index = self._index.get(name)
        if index is not None:
            points: np.ndarray = self.points[index]
            return points
        composition = _COMPOSED.get(name)
        if composition is None:
            return None
        neutral = self.points[0]
        out: np.ndarray = neutral.copy()
        for shape, weight in composition.items():
            out += weight * (self.points[self._index[shape]] - neutral)
        return out

    def driven_share(self, name: str, shapes: Iterable[str]) -> float:
        """How much of composed preset ``name``'s motion at these landmarks ``shapes`` (ARKit
        shapes) carry: the sum of weight x |shape displacement| over the composition's
        shapes among them, over that sum for all its shapes. 0 for a name not composed."""
        composition = _COMPOSED.get(name)
        if composition is None or name in self._index:
            return 0.0
        given = set(shapes)
        neutral = self.points[0]
        size = {s: w * float(np.linalg.norm(self.points[self._index[s]] - neutral))
                for s, w in composition.items()}  # fmt: skip
        total = sum(size.values())
        return sum(v for s, v in size.items() if s in given) / total if total > 0 else 0.0

    def composition(self, name: str) -> dict[str, float] | None:
        """The ARKit weights a composed preset stands for, or {name: 1} for a shape."""
        if name in self._index and name != "neutral":
            return {name: 1.0}
        found = _COMPOSED.get(name)
        return None if found is None else dict(found)

    @functools.cached_property
    def _index(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.names)}


#: What ``--source-rig`` and ``load_source_rig`` take as the word for this set.
GENERIC_SOURCE_NAME: Final = "generic"
_KEYS = ("names", "points", "landmarks68", "stable_points")


def is_generic_layout(keys: Iterable[str]) -> bool:
    """Whether an .npz's arrays are this set's layout (``generic_arkit/points.npz``'s)."""
    return set(_KEYS) <= set(keys)


@functools.cache
def generic_sources() -> GenericSources:
    """The packaged set, read once and shared (its arrays are read-only)."""
    path = resources.files(__package__).joinpath("generic_arkit", "points.npz")
    try:
        with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as data:
            arrays = {k: data[k] for k in _KEYS}
    except (OSError, KeyError, ValueError) as exc:
        raise ExampleSetError(
            f"facecast's generic source set is missing or damaged ({type(exc).__name__}); "
            "reinstall facecast",
            code="generic_set_missing",
        ) from None
    points = arrays["points"].astype(np.float64)
    points.flags.writeable = False
    names = tuple(str(n) for n in arrays["names"])
    missing = sorted({s for c in _COMPOSED.values() for s in c} - set(names))
    if missing or names[0] != "neutral" or points.shape[0] != len(names):
        raise ExampleSetError(
            f"facecast's generic source set does not match this facecast (missing {missing})",
            code="generic_set_missing",
        )
    return GenericSources(
        names=names,
        points=points,
        landmarks68=arrays["landmarks68"].astype(np.int64),
        stable_points=arrays["stable_points"].astype(np.int64),
    )


def composed_captures(
    names: Iterable[str], captured: Mapping[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """A performer's points for the VRM presets among ``names`` they did not capture.

    The generic set's rule on the performer's own face: a preset ``captured`` lacks whose
    every ARKit shape in ``VRM_COMPOSITIONS`` (or ``PART_COMPOSITIONS``) it holds is ``captured["neutral"]`` plus the
    composition's weights times those shapes' displacements, so a calibration captured on
    an ARKit character drives a VRM / VRoid one's presets too. Presets with a shape not
    captured, a preset equal to one of its shapes the rig has as well (``blinkLeft``
    beside ``eyeBlinkLeft``), and every preset when there is no neutral or the shapes'
    points differ in shape from it, are left out (the fit names what is wrong with the
    capture itself).
    """
    neutral = captured.get("neutral")
    if neutral is None:
        return {}
    base = np.asarray(neutral, dtype=np.float64)
    wanted = tuple(names)
    out: dict[str, np.ndarray] = {}
    for name in wanted:
        composition = _COMPOSED.get(name)
        if name in captured or composition is None:
            continue
        shapes = [captured.get(shape) for shape in composition]
        if any(s is None or np.shape(s) != base.shape for s in shapes):
            continue
        point = base.copy()
        for weight, shape in zip(composition.values(), shapes, strict=True):
            point += weight * (np.asarray(shape, dtype=np.float64) - base)
        # ``blinkLeft`` is ``eyeBlinkLeft``: a rig with both cannot tell them apart.
        if any(s in wanted and np.array_equal(point, captured[s]) for s in composition):
            continue
        out[name] = point
    return out

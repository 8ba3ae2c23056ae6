"""The demo performance on facecast's generic ARKit source set: any character, at once.

The same activations as the procedural demo (``scene.demo_activations``: emotions, visemes,
blinks) acted as ARKit blendshape weights (``DEMO_ARKIT``), turned into the generic set's 26
points (``sources.source_rig.generic_source_rig``), which every character uploaded as a
file is paired with. Reads only facecast's packaged generic set; no fitting, no network.
"""

from __future__ import annotations

import functools
from types import MappingProxyType
from typing import Final

import numpy as np

from ..characters.expression_names import ARKIT_NAMES
from ..characters.generic import generic_sources
from ..sources.animation import SourceAnimation
from ..sources.layouts import load_layout
from ..sources.source_rig import generic_source_rig
from .scene import DEMO_NAMES, demo_activations, demo_example_set

__all__ = [
    "DEMO_ARKIT",
    "PERFORMANCES",
    "arkit_demo_animation",
    "arkit_demo_weights",
    "performance_for",
]

_L, _R = "Left", "Right"


def _both(shape: str, weight: float) -> dict[str, float]:
    return {shape + _L: weight, shape + _R: weight}


#: Each demo expression as ARKit weights: the procedural source's face controls
#: (``scene._SOURCE_POSES``) read as the ARKit shapes that make them (smile, cheek raise
#: and squint for happy; brows, lids and jaw for surprise; ...).
DEMO_ARKIT: Final = MappingProxyType(
    {
        "happy": {**_both("mouthSmile", 1.0), **_both("cheekSquint", 0.7), **_both("eyeSquint", 0.4), "jawOpen": 0.1},
        "sad": {"browInnerUp": 1.0, **_both("mouthFrown", 0.9), **_both("mouthPress", 0.2), **_both("eyeBlink", 0.2)},
        "surprise": {"browInnerUp": 1.0, **_both("browOuterUp", 1.0), **_both("eyeWide", 1.0), "jawOpen": 0.6},
        "fear": {"browInnerUp": 1.0, **_both("browOuterUp", 0.35), **_both("eyeWide", 0.8), **_both("mouthStretch", 0.9), "jawOpen": 0.25},
        "anger": {**_both("browDown", 1.0), **_both("eyeSquint", 0.6), **_both("mouthPress", 0.55), **_both("mouthFrown", 0.25), **_both("noseSneer", 0.3)},
        "disgust": {**_both("noseSneer", 1.0), **_both("mouthUpperUp", 0.9), **_both("browDown", 0.45), **_both("eyeSquint", 0.5), **_both("mouthFrown", 0.3)},
        "aa": {"jawOpen": 0.9, **_both("mouthLowerDown", 0.3)},
        "oo": {"mouthPucker": 1.0, "mouthFunnel": 0.4, "jawOpen": 0.25},
        "ee": {**_both("mouthStretch", 0.8), "jawOpen": 0.25, **_both("mouthSmile", 0.2), **_both("mouthUpperUp", 0.2)},
        "mbp": {**_both("mouthPress", 0.8), "mouthClose": 0.3, "mouthRollLower": 0.3, "mouthRollUpper": 0.3},
        "fv": {"mouthRollLower": 0.8, **_both("mouthUpperUp", 0.3), "jawOpen": 0.1},
        "blink": _both("eyeBlink", 1.0),
    }
)  # fmt: skip

#: The demo performances ``GET /v1/demo/animation`` serves, by the source points they are on.
PERFORMANCES: Final = ("demo", "generic")


def _table() -> np.ndarray:
    """(M, 52): row m the ARKit weights of demo expression m (row 0, the neutral, zero)."""
    index = {name: i for i, name in enumerate(ARKIT_NAMES)}
    table = np.zeros((len(DEMO_NAMES), len(ARKIT_NAMES)))
    for m, name in enumerate(DEMO_NAMES[1:], start=1):
        for shape, weight in DEMO_ARKIT[name].items():
            table[m, index[shape]] = weight
    return table


def arkit_demo_weights(seconds: float = 12.0, fps: float = 60.0, *, seed: int = 7) -> np.ndarray:
    """The demo performance as ARKit weights, (F, 52) in ``ARKIT_NAMES`` order, in [0, 1].

    ``demo_activations(seconds, fps, seed=seed) @ DEMO_ARKIT``, clipped to [0, 1] as a
    tracker's weights are.
    """
    weights: np.ndarray = np.clip(demo_activations(seconds, fps, seed=seed) @ _table(), 0.0, 1.0)
    return weights


def arkit_demo_animation(
    seconds: float = 12.0, fps: float = 60.0, *, seed: int = 7
) -> SourceAnimation:
    """The demo performance on the generic ARKit set's 24 points, (F, 24, 3) centimetres.

    Drives any character paired with the generic set (one uploaded as a .glb/.vrm) as the
    procedural demo drives the demo rig: the same emotions, visemes and blinks, at the
    same times.
    """
    points = generic_source_rig().points(arkit_demo_weights(seconds, fps, seed=seed))
    return SourceAnimation(points=points, fps=float(fps))


@functools.cache
def _reference_neutrals() -> tuple[tuple[str, np.ndarray], ...]:
    return (
        ("demo", demo_example_set().source_points[0]),
        ("generic", generic_sources().points[0]),
    )


def performance_for(source_neutral: np.ndarray) -> str | None:
    """Which demo performance a rig with this source neutral (K, 3) takes, or None.

    ``"demo"`` for the procedural demo's points (the demo rig), ``"generic"`` for the
    generic ARKit set's (characters uploaded as files: its 26 points, or its first 24 or
    20, ICT-FaceKit's default landmarks, for a character fitted before the set or the
    layout grew, which takes the performance's first 24 or 20 points), None for any other
    source (its own tracker's points).
    """
    neutral = np.asarray(source_neutral, dtype=np.float64)
    k = len(neutral)
    for name, reference in _reference_neutrals():
        if name == "generic" and load_layout().takes_first(len(reference), k):
            reference = reference[:k]  # the layout's earlier version: its first k points
        if neutral.shape == reference.shape and np.allclose(
            neutral, reference, rtol=0.0, atol=1e-4 * float(np.ptp(reference))
        ):
            return name
    return None

"""facecast.rig.demo: the procedural demo: two heads, their expressions and a performance.

Generated from seeded formulas in milliseconds; it reads no file but facecast's packaged
generic ARKit set (``arkit``) and never touches the network. The public names live in
``scene``, the heads' geometry in ``geometry``, the facial controls that pose it in
``controls``; ``arkit`` plays the same performance on the generic ARKit set's points.
"""

from .arkit import DEMO_ARKIT, arkit_demo_animation, arkit_demo_weights, performance_for
from .scene import (
    DEMO_EMOTIONS,
    DEMO_FEATURE_NAMES,
    DEMO_NAMES,
    DEMO_VISEMES,
    demo_activations,
    demo_animation,
    demo_example_set,
    demo_landmarks,
    demo_target_frames,
)

__all__ = [
    "DEMO_ARKIT",
    "DEMO_EMOTIONS",
    "DEMO_FEATURE_NAMES",
    "DEMO_NAMES",
    "DEMO_VISEMES",
    "arkit_demo_animation",
    "arkit_demo_weights",
    "demo_activations",
    "demo_animation",
    "demo_example_set",
    "demo_landmarks",
    "demo_target_frames",
    "performance_for",
]

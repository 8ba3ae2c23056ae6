"""facecast.rig.demo: the procedural demo: two heads, their expressions and a performance.

Generated from seeded formulas in milliseconds; it must not read files or touch the network.
The public names live in ``scene``, the heads' geometry in ``geometry``, the facial
controls that pose it in ``controls``.
"""

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
    "DEMO_EMOTIONS",
    "DEMO_FEATURE_NAMES",
    "DEMO_NAMES",
    "DEMO_VISEMES",
    "demo_activations",
    "demo_animation",
    "demo_example_set",
    "demo_landmarks",
    "demo_target_frames",
]

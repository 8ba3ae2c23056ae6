"""``WinkCapture``: a wink of each eye told from a performance after its neutral."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig.closure import CLOSURE_NAMES
from facecast.rig.errors import InputError
from facecast.rig.sources.capture import WinkCapture

#: Four points: each eye's upper and lower lid (the subject's left eye first).
LIDS = {"left": (0, 1), "right": (2, 3)}
NEUTRAL = np.array([[3.0, 1.0, 0], [3.0, 0.0, 0], [-3.0, 1.0, 0], [-3.0, 0.0, 0]])


def eyes(left: float, right: float, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """The neutral with each eye's lid gap at that share of its own."""
    points = NEUTRAL.copy()
    points[0, 1], points[2, 1] = left, right
    return points + np.random.default_rng(seed).normal(0, jitter, points.shape)


def test_each_wink_is_the_robust_average_of_its_own_frames_left_eye_first():
    capture = WinkCapture(NEUTRAL, LIDS, frames=4)
    assert capture.wanted == "eyeBlinkLeft"
    seen = []
    frames = (
        [eyes(0.2, 0.2, 0.01, i) for i in range(5)]  # a blink: both shut, neither wink
        + [eyes(1.0, 1.0, 0.01, i) for i in range(3)]  # open
        + [eyes(0.2, 1.0, 0.01, i) for i in range(10, 14)]  # the left wink
        + [eyes(0.2, 1.0, 0.01, 20)]  # still the left: not the right's
        + [eyes(1.0, 0.25, 0.01, i) for i in range(30, 34)]  # the right wink
    )
    for frame in frames:
        seen.append(capture.add(frame))
    assert [name for name in seen if name] == list(CLOSURE_NAMES)
    assert seen.index("eyeBlinkLeft") == 5 + 3 + 3  # its 4th frame
    assert capture.wanted is None and capture.add(eyes(0.2, 1.0)) is None
    np.testing.assert_allclose(capture.closed["eyeBlinkLeft"], eyes(0.2, 1.0), atol=0.02)
    np.testing.assert_allclose(capture.closed["eyeBlinkRight"], eyes(1.0, 0.25), atol=0.02)


def test_a_half_closed_eye_or_a_squint_of_both_is_no_wink():
    capture = WinkCapture(NEUTRAL, LIDS, frames=3)
    for frame in [eyes(0.7, 1.0)] * 5 + [eyes(0.5, 0.7)] * 5:
        assert capture.add(frame) is None
    assert capture.held == [] and capture.closed == {}


@pytest.mark.parametrize("frames", [0, 2])
def test_too_few_frames_or_a_shut_neutral_is_refused(frames):
    with pytest.raises(InputError, match="at least 3 frames"):
        WinkCapture(NEUTRAL, LIDS, frames=frames)
    with pytest.raises(InputError, match="eyes are shut"):
        WinkCapture(eyes(0.0, 0.0), LIDS)

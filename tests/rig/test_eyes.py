"""The eyes clip's scoring: the truth scores perfectly, a one-sided error is reported."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig.errors import InputError
from facecast.rig.evaluation.eyes import BLINK_PROFILE, GAZE_WEIGHTS, eyes_clip, eyes_scores

NAMES = (
    "neutral", "eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft", "mouthSmileRight",
    *(name for pair in GAZE_WEIGHTS.values() for name in pair),
)  # fmt: skip


def test_the_clip_holds_each_event_where_it_says():
    clip = eyes_clip(NAMES)

    kinds = [event.kind for event in clip.events]
    assert kinds == ["blink"] * 3 + ["wink"] * 2 + ["gaze"] * 4 + ["combo"]
    blink = clip.events[0]
    assert blink.stop - blink.start == len(BLINK_PROFILE) == 5
    closed = clip.activations[blink.start : blink.stop, NAMES.index("eyeBlinkLeft")]
    assert closed.max() == 1.0 and closed[0] < 1.0 and clip.activations[blink.start - 1].max() == 0
    assert (clip.activations[:10] == 0).all()  # a neutral to calibrate on


def test_the_short_clip_has_each_kind_of_event_once_held_three_frames_apart():
    clip = eyes_clip(NAMES, short=True)

    assert [event.kind for event in clip.events] == ["blink", "wink", "wink", *["gaze"] * 4,
                                                     "combo"]  # fmt: skip
    assert [event.stop - event.start for event in clip.events] == [5] + [3] * 7
    # Each event back at rest for 3 frames between its ramp down and the next one's ramp up.
    for event, after in zip(clip.events, clip.events[1:], strict=False):
        down = 0 if event.kind == "blink" else 3  # a blink is its whole profile
        rest = clip.activations[event.stop + down : after.start - 3]
        assert len(rest) == 3 and (rest == 0).all()
        assert clip.activations[after.start - 3].max() > 0  # the ramp up
    assert len(clip.activations) == 102


def test_the_truth_scores_perfectly():
    clip = eyes_clip(NAMES)

    scores = eyes_scores(clip.activations, NAMES, clip)

    assert all(b == {"left": 1.0, "right": 1.0} for b in scores["blinks"])
    assert [(w["eye"], w["peak"], w["other"]) for w in scores["winks"]] == [
        ("left", 1.0, 0.0), ("right", 1.0, 0.0)
    ]  # fmt: skip
    assert [g["seen"] for g in scores["gaze"]] == ["up", "down", "left", "right"]
    assert all(g["right"] and g["share"] == pytest.approx(1.0) for g in scores["gaze"])
    assert all(g["shut"] == 0.0 for g in scores["gaze"])
    assert scores["combo"] == [{"jawOpen": pytest.approx(1.0), "smile": pytest.approx(1.0)}]
    assert all(scores["goals"].values())


def test_eyes_closing_on_a_gaze_hold_are_reported_as_shut():
    clip = eyes_clip(NAMES)
    left, right = NAMES.index("eyeBlinkLeft"), NAMES.index("eyeBlinkRight")
    weights = clip.activations.copy()
    up, down = (e for e in clip.events if e.kind == "gaze" and e.detail in ("up", "down"))
    weights[up.start : up.stop, [left, right]] = [0.4, 0.2]  # half-closing on the look up
    weights[down.start : down.stop - 2, left] = 0.6  # and the left eye on most of the look down

    scores = eyes_scores(weights, NAMES, clip)

    shut = {g["direction"]: g["shut"] for g in scores["gaze"]}
    hold = down.stop - down.start
    assert shut == pytest.approx(
        {"up": 0.3, "down": 0.3 * (hold - 2) / hold, "left": 0.0, "right": 0.0}
    )
    assert scores["goals"]["gaze"]  # the direction is still read right


def test_a_wink_that_closes_both_eyes_and_half_blinks_are_reported():
    clip = eyes_clip(NAMES)
    left, right = NAMES.index("eyeBlinkLeft"), NAMES.index("eyeBlinkRight")
    weights = clip.activations.copy()
    weights[:, right] = np.maximum(weights[:, right], weights[:, left])  # the left wink: both
    blinks = [e for e in clip.events if e.kind == "blink"]
    weights[blinks[1].start : blinks[1].stop, left] *= 0.5  # one blink half on the left only

    scores = eyes_scores(weights, NAMES, clip)

    assert scores["winks"][0] == {"eye": "left", "peak": 1.0, "other": 1.0}
    assert scores["winks"][1]["other"] == 0.0
    assert scores["blinks"][1] == {"left": 0.5, "right": 1.0}
    assert scores["goals"] == {"blinks": False, "winks": False, "gaze": True, "combo": True}


def test_gaze_the_wrong_way_and_a_weak_smile_fail_their_goals():
    clip = eyes_clip(NAMES)
    up, down = GAZE_WEIGHTS["up"], GAZE_WEIGHTS["down"]
    weights = clip.activations.copy()
    for a, b in zip(up, down, strict=True):  # looking down reads as up and back
        i, j = NAMES.index(a), NAMES.index(b)
        weights[:, [i, j]] = weights[:, [j, i]]
    weights[:, NAMES.index("mouthSmileLeft")] *= 0.1

    scores = eyes_scores(weights, NAMES, clip)

    assert [g["seen"] for g in scores["gaze"]] == ["down", "up", "left", "right"]
    assert scores["combo"][0]["smile"] == pytest.approx(0.55)
    assert scores["goals"] == {"blinks": True, "winks": True, "gaze": False, "combo": False}


def test_a_rig_without_eye_look_shapes_sees_no_direction():
    # An uploaded character's rig leaves gaze unpaired (its look-at turns its eyes): no
    # hold is credited with the first of four zero directions.
    clip = eyes_clip(NAMES)
    gazeless = [i for i, name in enumerate(NAMES) if not name.startswith("eyeLook")]

    scores = eyes_scores(clip.activations[:, gazeless], [NAMES[i] for i in gazeless], clip)

    assert [(g["seen"], g["right"], g["share"]) for g in scores["gaze"]] == [(None, False, 0.0)] * 4
    assert scores["goals"]["gaze"] is False and scores["goals"]["blinks"] is True


def test_weights_of_the_wrong_shape_are_refused():
    clip = eyes_clip(NAMES)

    with pytest.raises(InputError, match="expected shape"):
        eyes_scores(clip.activations[:-1], NAMES, clip)

"""The performer's own rig reading the eyes through the tracker: an ICT-FaceKit head, its
eyeballs turning with the eye-look weights, performs its eye and brow keys and then a
short eyes clip (a quick blink, a wink each side, four gaze holds), rendered
(``facecast.cli.bench.facevideo``) and tracked offline by the /perform page's own pipeline
(``facecast track``, a real headless Chromium); the personal rig is fitted on the tracked
keys as the server fits it and the clip is scored per event as viewers get it (the live
path, each frame as it comes: ``eyes.eyes_rows``' "personal live"); and on the generic
path, the character on facecast's shipped generic source re-based on the captured
neutral (its lids and irises as the tracker sees ICT's generic face: README, option (z)).

The layout's last two points are the iris centres (client/viewer/src/perform/eyelids.js);
the personal rig is fitted on all 26. What they are worth, measured on these frames
(2026-12-04 21:25 UTC; the same capture cut to its first 24 points, the layout before):

                         26 points            24 points
  blink, left / right    0.72 / 0.79          0.67 / 0.52
  wink own / other eye   1.00 / 0.01 (both)   1.00 / 0.02, 1.00 / 0.07
  gaze holds right       4/4                  4/4

so on 24 points the blink floor fails, by 0.10 (the right eye, 0.52; 26 points pass it by
0.10); the winks and the gaze pass on both. On a swaying head (1.5 degrees, the bench's;
the held noise 0.36 mm, not the still head's 0.1 mm floor) the same keys with a clip held
a frame or two longer read gaze 3/4 on both layouts (the right hold as up) and blinks
0.51 / 0.62 (24 points: 0.41 / 0.61): too close to pin, so the head is still here, and the
bench's full clip after all 52 keys measures the swaying one (README, "The eyes clip",
option (n)).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from facecast.cli.bench.facevideo import head_scene, write_video
from facecast.rig import fit
from facecast.rig.evaluation.eyes import (
    EYES_IDENTITY,
    GAZE_WEIGHTS,
    EyesClip,
    EyesTiming,
    eyes_clip,
    eyes_rows,
)
from facecast.rig.evaluation.webcam import captured_keys, ict_performer, key_clips, on_generic_set
from facecast.rig.rebase import REBASE_BLINK_CONTRAST
from facecast.rig.sources.ict import DEFAULT_LANDMARKS, ict_regions
from facecast.rig.sources.ict_arkit import ARKIT_TARGET_IDENTITY, arkit_example_set
from facecast.rig.sources.layouts import load_layout
from facecast.server.storage.profiles import held_noise

from .conftest import ICT_ARCHIVE as ARCHIVE
from .conftest import ICT_TRACKING

pytestmark = ICT_TRACKING
FPS = 30.0
#: The keys performed after the neutral: the eyes', and the brows' (they move the face
#: around the eyes, as a look up does; a capture walk-through asks for them too).
KEYS = (
    "eyeBlinkLeft", "eyeBlinkRight",
    "eyeLookUpLeft", "eyeLookUpRight", "eyeLookDownLeft", "eyeLookDownRight",
    "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
)  # fmt: skip
#: Frames, 30 fps. Each key rises in 1 frame and is held 8, the capture: the page crops the
#: eyes from the last 9 frames (eyelids.js's EYE_BOX_FRAMES), so most held frames are
#: cropped on the key itself (held 6 and jumped to, the right eye's blink read 0.27).
KEY_RAMP, KEY_HOLD = 1, 8
#: The clip: LEAD frames at rest, then each event and REST frames at rest; a wink and a
#: gaze hold rise and fall in RAMP frames and are held WINK_HOLD / GAZE_HOLD frames.
LEAD, REST, RAMP, WINK_HOLD, GAZE_HOLD = 9, 3, 2, 6, 9
#: How far an eye-look weight of 1 turns the eyeball (as tests/perform/test_iris.py).
GAZE_DEGREES = 20.0

# The floors, from the figures in the module's docstring.
BLINK_FLOOR = 0.62  # each eye's blink peak / the truth: 0.72 and 0.79 (24 points: 0.52)
WINK_EYE = 0.8  # the winking eye: 1.00 each side
WINK_OTHER = 0.15  # the other eye: 0.01 each side (24 points: 0.02 / 0.07)
# The generic path on the shipped source (option (z)), 2026-12-05 06:55 UTC: blinks 1.00 /
# 0.83, the winks' other eye 0.02 / 0.04, gaze right in 3 holds (up read as down); on ICT's
# exact landmarks, the source before: 0.85 / 0.83, 0.05 / 0.14, 1 hold (down). Through the
# re-base's blink curve (rebase.REBASE_BLINK_CONTRAST, option (ag), 2026-12-05 15:52 UTC):
# blinks 1.00 / 1.00, the other eye 0.00 / 0.00, the same gaze; the floors below fail
# without it.
GENERIC_BLINK_FLOOR = 0.95
#: A character uploaded as a file (gaze left out), through the server's curve for a rig
#: without gaze (rebase.REBASE_BLINK_CONTRAST_GAZELESS, option (ak), 2026-12-05 19:50 UTC):
#: 1.00 / 1.00; through the curve of a rig that reads gaze 0.95 / 1.00.
UPLOADED_BLINK_FLOOR = 0.97
GENERIC_WINK_OTHER = 0.01
#: The holds the generic path reads right: the tracker hardly sees an eye turn up from the
#: lids' own rise (the iris moves down with the lids in the face frame, test_iris.py).
GENERIC_GAZE = ("down", "left", "right")


#: The short clip: one quick blink, a wink each side, the four gaze holds (no jaw + smile).
CLIP_TIMING = EyesTiming(
    blinks=1, lead=LEAD, rest=REST, wink=(RAMP, WINK_HOLD), gaze=(RAMP, GAZE_HOLD), combo=None
)


@dataclass(frozen=True, eq=False)
class Tracked:
    clip: EyesClip
    keys: dict[str, np.ndarray]  # the captured keys, (K, 3) each
    noise: float  # the held frames' spread
    points: np.ndarray  # (F, K, 3): the clip's tracked points


@pytest.fixture(scope="module")
def tracked(tracker, tmp_path_factory) -> Tracked:
    """The keys and the clip rendered as one video on ICT's person12, tracked offline."""
    performer = ict_performer(ARCHIVE, identity=EYES_IDENTITY)
    regions, landmarks68 = ict_regions(ARCHIVE)
    clips = key_clips(performer.names, keys=KEYS, ramp=KEY_RAMP, hold=KEY_HOLD)
    clip = eyes_clip(performer.names, timing=CLIP_TIMING)
    path = write_video(tmp_path_factory.mktemp("eyes-rig") / "eyes.y4m",
                       head_scene(performer, regions, landmarks68), performer,
                       np.concatenate([clips.activations, clip.activations]), fps=FPS,
                       sway_degrees=0.0, gaze_degrees=GAZE_DEGREES, progress=False)  # fmt: skip
    result = tracker.track(path, progress=False)
    assert result.found.all()
    points = result.points.astype(np.float64)
    assert points.shape[1] == load_layout().num_features == len(DEFAULT_LANDMARKS) + 2
    split = len(clips.activations)
    keys, held = captured_keys(points[:split], clips)
    assert set(keys) == {"neutral", *KEYS}
    noise, _ = held_noise(held)
    return Tracked(clip, keys, noise, points[split:])


@pytest.fixture(scope="module")
def scores(tracked) -> dict[str, Any]:
    """The clip's events scored on the personal rig's weights, live unfiltered (the
    filter /perform asks for keeps a quick blink: README, option (a′))."""
    examples = arkit_example_set(ARCHIVE, identity=ARKIT_TARGET_IDENTITY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact ICT rig (and the bounded fits) advise
        character = fit(examples)
        rows = eyes_rows(character, tracked.clip, tracked.points, tracked.keys,
                         noise=tracked.noise, fps=FPS, filters={"live": ("none", None)})  # fmt: skip
    assert character.num_points == len(DEFAULT_LANDMARKS)  # the capture has 2 more
    out: dict[str, Any] = rows["personal live"]
    print(f"\npersonal rig, live, {tracked.points.shape[1]} points (noise "
          f"{10 * tracked.noise:.2f} mm): blinks {out['blinks']}; winks {out['winks']}; "
          f"gaze {[(g['direction'], g['seen']) for g in out['gaze']]}")  # fmt: skip
    return out


@pytest.fixture(scope="module")
def generic_scores(tracked) -> dict[str, Any]:
    """The clip on the generic path, live: the character on facecast's shipped generic
    source (ICT's landmarks with the lids and irises as tracked, option (z)), re-based on
    the captured neutral with its noise and the captured blinks, as /perform's calibrate."""
    examples = arkit_example_set(ARCHIVE, identity=ARKIT_TARGET_IDENTITY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        character = fit(examples)
        generic = fit(on_generic_set(examples))
        rows = eyes_rows(character, tracked.clip, tracked.points, tracked.keys, noise=tracked.noise,
                         fps=FPS, filters={"live": ("none", None)}, generic=generic)  # fmt: skip
    out: dict[str, Any] = rows["generic live"]
    print(f"\ngeneric rig (shipped source), live: blinks {out['blinks']}; winks {out['winks']}; "
          f"gaze {[(g['direction'], g['seen']) for g in out['gaze']]}")  # fmt: skip
    return out


@pytest.fixture(scope="module")
def uploaded_scores(tracked) -> dict[str, Any]:
    """The clip on the generic path of a character uploaded as a file: the same shipped
    source, gaze left out as an upload pairs it (its look-at turns its eyes), re-based as
    /perform's calibrate asks, through the server's curve for a rig without gaze."""
    examples = arkit_example_set(ARCHIVE, identity=ARKIT_TARGET_IDENTITY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        character = fit(examples)
        uploaded = fit(on_generic_set(examples, uploaded=True))
        rows = {
            curve: eyes_rows(character, tracked.clip, tracked.points, tracked.keys,
                             noise=tracked.noise, fps=FPS, filters={"live": ("none", None)},
                             generic=uploaded, contrast=curve)["generic live"]
            for curve in (None, REBASE_BLINK_CONTRAST)
        }  # fmt: skip
    out: dict[str, Any] = rows[None]
    print(f"\nuploaded character, live: blinks {out['blinks']} ({rows[REBASE_BLINK_CONTRAST]['blinks']} "
          f"through a gaze rig's curve); winks {out['winks']}")  # fmt: skip
    return out


def test_a_quick_blink_peaks_on_both_eyes(scores):
    (blink,) = scores["blinks"]
    assert min(blink.values()) >= BLINK_FLOOR, blink


def test_a_wink_closes_its_own_eye_and_leaves_the_other_open(scores):
    assert [w["eye"] for w in scores["winks"]] == ["left", "right"]
    for wink in scores["winks"]:
        assert wink["peak"] >= WINK_EYE, wink
        assert wink["other"] <= WINK_OTHER, wink


def test_every_gaze_hold_reads_its_own_direction(scores):
    seen = {g["direction"]: g["seen"] for g in scores["gaze"]}
    assert seen == {direction: direction for direction in GAZE_WEIGHTS}


def test_on_the_generic_path_a_quick_blink_peaks_on_both_eyes_and_a_wink_stays_one_sided(
    generic_scores,
):
    (blink,) = generic_scores["blinks"]
    assert min(blink.values()) >= GENERIC_BLINK_FLOOR, blink
    assert [w["eye"] for w in generic_scores["winks"]] == ["left", "right"]
    for wink in generic_scores["winks"]:
        assert wink["peak"] >= WINK_EYE and wink["other"] <= GENERIC_WINK_OTHER, wink


def test_on_the_generic_path_the_iris_gives_the_gaze_but_up(generic_scores):
    seen = {g["direction"]: g["seen"] for g in generic_scores["gaze"]}
    assert {d: seen[d] for d in GENERIC_GAZE} == {d: d for d in GENERIC_GAZE}, seen


def test_an_uploaded_characters_quick_blink_peaks_and_its_gaze_is_left_to_its_look_at(
    uploaded_scores,
):
    (blink,) = uploaded_scores["blinks"]
    assert min(blink.values()) >= UPLOADED_BLINK_FLOOR, blink
    for wink in uploaded_scores["winks"]:
        assert wink["peak"] >= WINK_EYE and wink["other"] <= GENERIC_WINK_OTHER, wink
    assert [g["seen"] for g in uploaded_scores["gaze"]] == [None] * 4  # no eye-look shapes

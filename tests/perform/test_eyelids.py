"""The tracked eyelids against ground truth: an ICT-FaceKit head blinking and winking with
known weights, rendered (``facecast.cli.bench.facevideo``) and tracked by the /perform
page's own pipeline, offline (``facecast track``) and live (the page on Chromium's fake
camera), both in a real headless Chromium; and a quick blink, 5 frames at 30 fps.

FaceMesh's own lids (468 points, no refinement) close a fifth of the way on this face and
move both eyes alike on a wink; the page refines them with the iris model
(client/viewer/src/perform/eyelids.js), each eye cropped where the last frames put it
(FaceMesh moves its eye corners, and so the crop, when both eyes close). Measured per eye
as the lid gap (upper minus lower lid point, the layout's features) over the same gap at
rest.
"""

from __future__ import annotations

import asyncio
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest

from facecast.cli.bench.facevideo import HeadScene, head_scene, write_video
from facecast.rig.evaluation.eyes import BLINK_PROFILE, EYES_IDENTITY
from facecast.rig.evaluation.webcam import Performer, ict_performer
from facecast.rig.sources.ict import ict_regions
from facecast.rig.sources.layouts import load_layout

from .._perform_venv import run_worker
from .conftest import FPS, ICT_TRACKING, done, open_page
from .conftest import ICT_ARCHIVE as ARCHIVE
from .test_perform_page import collect, perform_url, tracking

pytestmark = ICT_TRACKING
#: The layout's lid features per eye (subject's side): upper, lower.
_NAMES = load_layout().feature_names
LIDS = {
    side: (_NAMES.index(f"{side}_upper_lid"), _NAMES.index(f"{side}_lower_lid"))
    for side in ("right", "left")
}
#: Each lid's second point (the inner thirds, appended when the layout grew to 24 points).
INNER_LIDS = {
    side: (_NAMES.index(f"{side}_upper_lid_inner"), _NAMES.index(f"{side}_lower_lid_inner"))
    for side in ("right", "left")
}
#: The poses rendered, each held HOLD frames: rest, a blink, each wink. Each pose is
#: scored on its last frame, where the page crops the eyes from that pose's frames alone
#: (eyelids.js's EYE_BOX_FRAMES, 9), as on a camera showing the pose still.
POSES = {
    "rest": {},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "wink left": {"eyeBlinkLeft": 1.0},
    "wink right": {"eyeBlinkRight": 1.0},
}
HOLD = 10
#: Then, after REST frames at rest, a quick blink (the eyes clip's: 5 frames, closed in the
#: middle one) and REST frames again.
REST = 10
QUICK = len(BLINK_PROFILE)
#: How much less a quick blink may close an eye than a held wink of that eye closes it (its
#: fullest frame's lid gap over the wink's, as shares of the gap at rest). Measured, right /
#: left eye, winks 0.40 / 0.56: the quick blink 0.50 / 0.55 while each crop followed
#: FaceMesh's corners, which move 4-5 px down when both eyes close; 0.41 / 0.50 with the
#: crops the median of the last 9 frames' (eyelids.js EyeBoxes; README, "The eyes clip").
QUICK_SLACK = 0.04
#: A lid gap at most this share of its rest is closed; at least OPEN, open. Measured on
#: these frames: exact (ICT's landmark vertices, not on the lid margin) 0.62 / 0.48 closed
#: (right / left eye); tracked with the lids refined 0.40-0.56 closed, 0.94-1.03 the other
#: eye of a wink; with FaceMesh's own lids 0.91-0.93 a blink, 0.91 / 0.92 both eyes of a
#: left wink, 1.01 / 1.00 of a right one (README, "The eyes clip").
CLOSED, OPEN = 0.7, 0.85


@dataclass(frozen=True, eq=False)
class Clip:
    performer: Performer
    scene: HeadScene
    activations: np.ndarray  # (F, M): each pose held HOLD frames, then the quick blink


@pytest.fixture(scope="module")
def clip() -> Clip:
    performer = ict_performer(ARCHIVE, identity=EYES_IDENTITY)
    regions, landmarks68 = ict_regions(ARCHIVE)
    act = np.zeros((len(POSES) * HOLD + 2 * REST + QUICK, len(performer.names)))
    for i, weights in enumerate(POSES.values()):
        for name, value in weights.items():
            act[i * HOLD : (i + 1) * HOLD, performer.names.index(name)] = value
    quick = slice(len(POSES) * HOLD + REST, len(POSES) * HOLD + REST + QUICK)
    for name in ("eyeBlinkLeft", "eyeBlinkRight"):
        act[quick, performer.names.index(name)] = BLINK_PROFILE
    return Clip(performer, head_scene(performer, regions, landmarks68), act)


def shares(points: np.ndarray, lids=LIDS) -> dict[str, dict[str, float]]:
    """(len(POSES), K, 3) points, one set per pose -> each pose's lid gap per eye (between
    ``lids``' points) as a share of the gap at rest (the first pose)."""
    gap = {
        side: np.linalg.norm(points[:, u] - points[:, d], axis=1) for side, (u, d) in lids.items()
    }
    return {
        pose: {side: float(gap[side][i] / gap[side][0]) for side in LIDS}
        for i, pose in enumerate(POSES)
    }  # fmt: skip


def per_pose(points) -> np.ndarray:
    """Each pose's last held frame (K, 3): (len(POSES), K, 3)."""
    held = np.asarray(points, dtype=np.float64)[: len(POSES) * HOLD]
    return held.reshape(len(POSES), HOLD, -1, 3)[:, -1]


def quick_blink(points) -> dict[str, float]:
    """The quick blink's fullest closing per eye: its least lid gap over its 5 frames, as a
    share of the gap on the REST frames before it."""
    x = np.asarray(points, dtype=np.float64)[len(POSES) * HOLD :]
    out = {}
    for side, (upper, lower) in LIDS.items():
        gap = np.linalg.norm(x[:, upper] - x[:, lower], axis=1)
        out[side] = float(gap[REST : REST + QUICK].min() / gap[:REST].mean())
    return out


@pytest.fixture(scope="module")
def video(clip, tmp_path_factory):
    """The clip rendered: the poses held, then the quick blink."""
    return write_video(tmp_path_factory.mktemp("eyelids") / "blinks.y4m", clip.scene,
                       clip.performer, clip.activations, fps=30.0, sway_degrees=0.0,
                       progress=False)  # fmt: skip


@pytest.fixture(scope="module")
def gaps(clip, video, tracker):
    """Each pose's lid gap per eye, tracked offline and exact."""
    result = tracker.track(video, progress=False)
    assert result.found.all()
    out = {
        "tracked": shares(per_pose(result.points)),
        "exact": shares(per_pose(clip.performer.landmark_points(clip.activations))),
        "quick": quick_blink(result.points),
        "tracked inner": shares(per_pose(result.points), INNER_LIDS),
        "exact inner": shares(
            per_pose(clip.performer.landmark_points(clip.activations)), INNER_LIDS
        ),
    }
    print(f"\nlid gap / rest: {out}")
    return out


def assert_blink_and_winks(gaps: dict[str, dict[str, float]]) -> None:
    """Both eyes closed on the blink; on each wink its own eye closed, the other open."""
    assert gaps["blink"]["right"] <= CLOSED and gaps["blink"]["left"] <= CLOSED, gaps
    for side, other in (("left", "right"), ("right", "left")):
        assert gaps[f"wink {side}"][side] <= CLOSED, gaps
        assert gaps[f"wink {side}"][other] >= OPEN, gaps


def test_a_blink_closes_both_tracked_eyes_and_a_wink_only_its_own(gaps):
    assert_blink_and_winks(gaps["tracked"])
    # Each lid's second point too (measured: a blink 0.52 / 0.54 of the gap at rest, the
    # winks 0.39 / 0.51, their other eyes 0.94 / 1.04; exact 0.28 / 0.48).
    assert_blink_and_winks(gaps["tracked inner"])
    # The truth of the same frames: a wink's other eye does not move at all.
    for side, other in (("left", "right"), ("right", "left")):
        assert gaps["exact"][f"wink {side}"][other] == pytest.approx(1.0, abs=1e-3)
        assert gaps["exact inner"][f"wink {side}"][other] == pytest.approx(1.0, abs=1e-3)


def test_a_quick_blink_closes_each_tracked_eye_as_far_as_a_held_wink_of_it(gaps):
    # FaceMesh moves its eye corners down when both eyes close; the eyes are cropped where
    # the last frames put them, so a blink's lids are read in the crop a wink's are.
    for side in LIDS:
        assert gaps["quick"][side] <= gaps["tracked"][f"wink {side}"][side] + QUICK_SLACK, gaps


@pytest.fixture(scope="module")
def performed(video, perform_python) -> np.ndarray:
    """The clip through ``facecast perform``'s tracker (Python MediaPipe: FaceMesh's 468
    points with the attention mesh's lids and the iris model's irises, ``cli.facetrack``):
    (F, K, 3), a face found in every frame."""
    out = video.with_name("perform.npz")
    run_worker(perform_python, "track-video", video, out)
    with np.load(out) as tracked:
        points, found = tracked["points"], tracked["faces"] > 0
    assert found.all()
    return points.astype(np.float64)


def test_facecast_performs_tracker_closes_the_lids_as_the_page_does(performed):
    """On the same frames as the page: a blink closes both eyes, a wink only its own, a
    quick blink both (measured, right / left eye: a blink 0.34 / 0.29 of the gap at rest,
    a wink 0.27 / 0.25 and its other eye 1.05 / 1.00, the quick blink 0.34 / 0.18;
    FaceMesh's own lids leave 0.91-0.93 on a blink)."""
    tracked_gaps = shares(per_pose(performed))
    quick = quick_blink(performed)
    print(f"\nfacecast perform's lid gap / rest: {tracked_gaps}; quick blink {quick}")

    assert_blink_and_winks(tracked_gaps)
    assert max(quick.values()) <= CLOSED, quick


def test_without_litert_facecast_perform_says_so_and_takes_the_attention_meshs_irises(
    video, perform_python, performed
):
    """Where LiteRT has no wheel (Intel macOS; the ``perform`` extra leaves it out there)
    the tracker still tracks: the lids and every other point as with it, the irises the
    attention mesh's, which move less on a blink (measured, right / left: 0.18 / 0.25 where
    the iris model's move 0.60 / 0.61), and a warning says what that costs."""
    out = video.with_name("perform-without-litert.npz")
    run_worker(perform_python, "track-video-without-litert", video, out)
    with np.load(out) as tracked:
        points, found, said = tracked["points"], tracked["faces"] > 0, list(tracked["warnings"])
    assert found.all()
    assert len(said) == 1 and "no iris model" in said[0] and "option (z)" in said[0], said
    np.testing.assert_array_equal(points[:, :24], performed[:, :24])
    irises = [_NAMES.index("right_iris"), _NAMES.index("left_iris")]
    rest, blink = per_pose(points)[:2]
    moved = np.linalg.norm((blink - rest)[irises], axis=1)
    rest_iris, blink_iris = per_pose(performed)[:2]
    moved_with = np.linalg.norm((blink_iris - rest_iris)[irises], axis=1)
    print(f"\nthe blink's iris motion, right / left: {moved} without LiteRT, {moved_with} with")
    assert moved.max() < 0.4 < moved_with.min()


#: ``facecast perform --winks`` on the clip: the neutral from the rest frames, each wink from
#: its held pose (MediaPipe closes a wink's eye to 0.25-0.27 of its rest gap).
PERFORM_NEUTRAL, PERFORM_WINK = 8, 6
#: The frames of the quick blink.
QUICK_FRAMES = range(len(POSES) * HOLD + REST, len(POSES) * HOLD + REST + QUICK)


def _import_rig(generic_set: bool):
    """The ICT import's rig: on ICT's own landmarks (24 points), or on facecast's shipped
    generic set (26: the lids and irises as the page's tracker sees ICT's generic face),
    as a character uploaded as a file is."""
    from facecast.cli.commands.import_ import arkit_example_set
    from facecast.rig import fit
    from facecast.rig.evaluation.webcam import on_generic_set
    from facecast.rig.sources.ict import DEFAULT_LANDMARKS

    example_set, _ = arkit_example_set(ARCHIVE, DEFAULT_LANDMARKS, "face")
    if generic_set:
        example_set = on_generic_set(example_set)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # exact: the re-base is what makes it live-worthy
        return fit(example_set)


@pytest.mark.parametrize("generic_set", [False, True], ids=["ict-landmarks", "generic-set"])
def test_winks_captured_as_facecast_perform_captures_them_make_a_quick_blink_read_closed(
    performed, generic_set
):
    """What ``facecast perform --winks`` does with the tracked frames (its neutral's robust
    average and noise, ``WinkCapture``, the calibrate's re-base with the closed eyes), on
    both rigs a performer drives: the clip's quick blink peaks at 0.6 or more on both eyes.
    Measured, left / right: ICT's landmarks (24 points) 0.83 / 0.72; the shipped generic
    set (26) 1.00 / 0.86. The set's irises are the page's tracker's, which follow the lids
    down on a blink: with the attention mesh's irises, which barely move, the set's rig
    read the left eye's quick blink at 0.46."""
    from facecast.rig import estimate_noise
    from facecast.rig.rebase import calibrate
    from facecast.rig.sources.capture import WinkCapture, robust_example

    rig = _import_rig(generic_set)
    points = performed[:, : rig.num_points]
    held = points[:PERFORM_NEUTRAL]
    neutral, _, _ = robust_example(held)
    winks = WinkCapture(neutral, {side: LIDS[side] for side in ("left", "right")},
                        frames=PERFORM_WINK)  # fmt: skip
    for frame in points[PERFORM_NEUTRAL:]:
        winks.add(frame)
    assert winks.wanted is None, f"{winks.wanted} not captured"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        live = calibrate(rig, neutral, estimate_noise(held), winks.closed)
    blink = [rig.names.index(name) for name in ("eyeBlinkLeft", "eyeBlinkRight")]
    peaks = np.array([live.weights(points[f])[blink] for f in QUICK_FRAMES]).max(axis=0)
    print(f"\nthe quick blink's peaks, left / right, on the {rig.num_points}-point rig: {peaks}")
    assert peaks.min() >= 0.6, peaks


def test_facecast_performs_winks_make_a_generic_rig_read_a_quick_blink_as_closed(
    video, perform_python, tmp_path
):
    """``facecast perform --winks`` captures a wink of each eye after the neutral and sends
    them with it (``calibrate.blinks``): the generic rig a character uploaded as a file gets
    (ICT's shapes on the shipped generic set), re-based on the neutral, then reads the
    clip's quick blink as closed on both eyes, live through a channel (measured: left /
    right peaks 1.00 / 0.86, as the same steps offline above)."""
    from facecast.server.settings import Settings

    from ..client.test_perform import _perform_stats, _perform_to_channel, _performed

    rig = _import_rig(generic_set=True)
    argv = ["--neutral-frames", str(PERFORM_NEUTRAL), "--winks",
            "--wink-frames", str(PERFORM_WINK)]  # fmt: skip
    # Its own event loop in a thread of its own: this package's Playwright (the ``browser``
    # fixture, sync API) keeps one running on the main thread once a page test has used it.
    with ThreadPoolExecutor(1) as pool:
        performance = _perform_to_channel(
            perform_python, Settings(rigs_dir=tmp_path / "rigs"), rig, argv, video
        )
        finished, messages = pool.submit(asyncio.run, performance).result()
    stats = _perform_stats(finished.err)
    assert stats["found"] == stats["read"] == len(POSES) * HOLD + 2 * REST + QUICK
    assert "eyeBlinkLeft captured" in finished.err and "both winks captured" in finished.err
    # The frame of each result: the neutral's first frames are not published.
    blink = [rig.names.index(name) for name in ("eyeBlinkLeft", "eyeBlinkRight")]
    peaks = np.array([
        r.weights[blink] for r in _performed(messages) if r.seq + PERFORM_NEUTRAL - 1 in QUICK_FRAMES
    ]).max(axis=0)  # fmt: skip
    print(f"\nfacecast perform --winks: the quick blink's peaks, left / right {peaks}")
    assert peaks.min() >= 0.6, peaks


def test_the_live_page_on_the_camera_publishes_the_same_lids(
    browser, server, camera_file, pages, clip, gaps
):
    """Each pose on the fake camera (a still clip, looped), the page's published points."""
    published = []
    for i, pose in enumerate(POSES):
        frames = clip.activations[i * HOLD : i * HOLD + 1].repeat(4, axis=0)
        write_video(camera_file, clip.scene, clip.performer, frames, fps=FPS,
                    sway_degrees=0.0, progress=False)  # fmt: skip
        page = open_page(browser, perform_url(server, f"eyelids-{i}", "demo"))
        pages.append(page)
        tracking(page)
        samples = [s for s in collect(page, 3) if s is not None]
        assert samples, f"no face in the live page's frames of {pose}"
        published.append(np.mean([s["points"] for s in samples], axis=0).reshape(-1, 3))
        assert page.errors == []
        done(page)
    live = shares(np.stack(published))
    live_inner = shares(np.stack(published), INNER_LIDS)
    print(f"\nlive lid gap / rest: {live}; each lid's second point: {live_inner}")

    assert_blink_and_winks(live)
    assert_blink_and_winks(live_inner)
    # The very pixels the offline tracker had: the same points to the float32 rounding.
    for pose in POSES:
        for side in LIDS:
            assert live[pose][side] == pytest.approx(gaps["tracked"][pose][side], abs=1e-3)

"""``facecast track``: the /perform page's own tracker, offline, on every frame of a video.

The agreement test runs the live page (a real Chromium whose fake camera plays the clip,
publishing to a real server, its frames read back by a real points watcher) beside
``track_video`` on the same images. The clip holds each of a few distinct expressions
for several frames, so whichever camera frames the live page happened to track, each
is one of the clip's few images. The page crops the eyes where its last 9 tracked frames
put them (eyelids.js, EYE_BOX_FRAMES): from an image's SETTLED-th tracked frame in a row
on, the crops are that image's own, and its points must equal the offline points of that
image held as long.
"""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.cli.track import track_video
from facecast.cli.y4m import MAX_SIDE
from facecast.rig.sources.layouts import load_layout

from .conftest import CHARACTER, LAYOUT_RIG, FacePose, open_page, watching
from .facevideo import write_y4m

K = load_layout().num_features
#: Distinct images of the clip, each held HOLD frames (the page tracks at 5-25 fps of 25).
POSES = [FacePose(), FacePose(mouth=12.0), FacePose(brows=6.0, roll=4.0, shift=(6.0, 3.0))]
HOLD = 8
#: The frames of one image in a row after which the page's eye crops are that image's: the
#: median of eyelids.js's EYE_BOX_FRAMES (9) crops is the image's own once 5 are.
SETTLED = 5
#: The live page's clip holds each image longer (2 s): at 3-25 tracked frames a second it tracks
#: each image SETTLED times or more in a row.
LIVE_HOLD = 50
OUT_OF_VIEW = FacePose(shift=(400.0, 0.0))


@pytest.fixture(scope="module")
def clip_points(camera_file, tmp_path_factory):
    """The clip on the package's camera file and what ``track_video`` makes of it."""
    write_y4m(camera_file, [pose for pose in POSES for _ in range(HOLD)], fps=25)
    kept = tmp_path_factory.mktemp("clip") / "clip.y4m"
    shutil.copy(camera_file, kept)
    return kept, track_video(kept, progress=False)


def test_track_gives_every_frame_points_of_the_layout(clip_points):
    _, result = clip_points

    assert result.points.shape == (len(POSES) * HOLD, K, 3)
    assert result.points.dtype == np.float32
    assert result.head.shape == (len(POSES) * HOLD, 4) and result.head.dtype == np.float32
    assert result.found.all() and result.fps == 25.0
    assert result.backend == "wasm" and result.layout == "mediapipe_face_mesh"
    # An image held still gives the same points once the eye crops settle on it (the rest
    # of the face from its first frame: the head), and the expressions differ.
    held = result.points.reshape(len(POSES), HOLD, K, 3)[:, SETTLED - 1 :]
    assert np.array_equal(held, np.broadcast_to(held[:, :1], held.shape))
    heads = result.head.reshape(len(POSES), HOLD, 4)
    assert np.array_equal(heads, np.broadcast_to(heads[:, :1], heads.shape))
    assert np.abs(held[1, 0] - held[0, 0]).max() > 0.3


def test_track_gives_the_points_the_live_page_publishes(
    browser, server, rigs_dir, camera, clip_points, pages
):
    _, result = clip_points
    # A performer's own rig (published from the first frame) on the layout's 26 points.
    rig = f"{LAYOUT_RIG}@agree"
    shutil.copy(rigs_dir / f"{LAYOUT_RIG}.rig", rigs_dir / f"{rig}.rig")
    distinct = result.points[HOLD - 1 :: HOLD]  # each image's last frame: settled
    camera.show([pose for pose in POSES for _ in range(LIVE_HOLD)])
    recorder, thread = watching(server, "agree", rig, "points")
    try:
        page = open_page(browser, f"{server}/perform?channel=agree&rig={rig}")
        pages.append(page)
        # Until every image has been tracked SETTLED times in a row (the page's rate decides
        # how many frames that takes), within 120 s.
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if len(recorder.results) >= 30:
                frames = np.array([r.points for _, r in list(recorder.results)], np.float32)
                nearest, settled = _runs(frames, distinct)
                if len(set(nearest[settled].tolist())) == len(POSES):
                    break
            page.wait_for_timeout(250)
    finally:
        recorder.stop.set()
        thread.join(5)
    live = np.array([r.points for _, r in recorder.results], dtype=np.float32)
    heads = [r.head for _, r in recorder.results]

    assert live.shape[0] >= 30 and live.shape[1:] == (K, 3), live.shape
    # Match each live frame to the clip's image whose offline points are nearest; in each
    # run of frames of one image, those from the SETTLED-th on equal its offline points.
    gaps = np.abs(live[:, None] - distinct[None]).max(axis=(2, 3))
    nearest, settled = _runs(live, distinct)
    assert gaps.min(axis=1)[settled].max() <= 1e-5, (gaps.min(axis=1), nearest)
    # Every image compared, settled.
    assert set(nearest[settled].tolist()) == set(range(len(POSES))), nearest
    # ... and the match is unambiguous: the images are far apart at that tolerance.
    apart = np.abs(distinct[:, None] - distinct[None]).max(axis=(2, 3))
    assert apart[~np.eye(len(POSES), dtype=bool)].min() > 0.1
    # The page sends its head pose with every frame; the channel relays it to the watcher
    # (a points watcher: whatever the output), the offline tracker's for the same image.
    assert all(head is not None and head.position is None for head in heads)
    live_heads = np.array([head.rotation for head in heads])
    np.testing.assert_allclose(live_heads, result.head[::HOLD][nearest], atol=1e-5)
    # The rolled image's head is not the upright one's (test_head_pose.py: the signs).
    assert np.abs(result.head[2 * HOLD] - result.head[0]).max() > 0.02


def _runs(live: np.ndarray, distinct: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each live frame's nearest image (by its offline points) and whether it is at least
    the SETTLED-th frame of that image in a row."""
    nearest = np.abs(live[:, None] - distinct[None]).max(axis=(2, 3)).argmin(axis=1)
    run = np.zeros(len(live), dtype=int)
    for i in range(1, len(live)):
        run[i] = run[i - 1] + 1 if nearest[i] == nearest[i - 1] else 0
    return nearest, run >= SETTLED - 1


def test_a_kept_tracker_gives_a_video_after_another_the_points_it_has_alone(
    clip_points, tracker, tmp_path
):
    """A ``Tracker`` (one browser for several videos, as the package's modules and ``bench
    webcam`` share one) tracks each video on a pipeline of its own: after another face's
    video, whose last frames fill the eyelid model's history, the clip's points are
    ``track_video``'s, bit for bit."""
    kept, alone = clip_points
    before = write_y4m(tmp_path / "before.y4m", [OUT_OF_VIEW, POSES[2], POSES[2], POSES[1]])

    assert tracker.track(before, progress=False).found.tolist() == [False, True, True, True]
    again = tracker.track(kept, progress=False)

    np.testing.assert_array_equal(again.points, alone.points)
    np.testing.assert_array_equal(again.head, alone.head)
    assert again.faces.tolist() == alone.faces.tolist()


def test_frames_without_a_face_are_nan_and_not_found(tmp_path):
    video = write_y4m(tmp_path / "gone.y4m", [POSES[0], OUT_OF_VIEW, POSES[1], OUT_OF_VIEW])

    result = track_video(video, progress=False)

    assert result.found.tolist() == [True, False, True, False]
    assert np.isnan(result.points[~result.found]).all()
    assert np.isfinite(result.points[result.found]).all()
    assert result.faces.tolist() == [1, 0, 1, 0]


def test_a_video_without_a_face_is_said_and_fails_with_require_face(tmp_path, capsys):
    video = write_y4m(tmp_path / "empty.y4m", [OUT_OF_VIEW] * 2)
    out = tmp_path / "points.npz"

    status = main(["track", str(video), "-o", str(out), "--require-face", "-q"])

    assert status == 3
    assert "no face was found in any of the 2 frames" in capsys.readouterr().err
    with np.load(out) as saved:
        assert not saved["found"].any() and np.isnan(saved["points"]).all()


def test_clone_puts_a_tracked_video_on_a_rig(clip_points, rigs_dir, tmp_path, capsys):
    _, result = clip_points
    found = result.found.copy()
    found[HOLD : 2 * HOLD] = False  # as if the face had left during the open mouth
    points = result.points.copy()
    points[~found] = np.nan
    tracked = tmp_path / "tracked.npz"
    # As ``facecast track`` writes it: 26 points in the layout it names; the cartoon rig,
    # fitted on the layout's earlier 20, takes the first 20.
    np.savez(tracked, points=points, found=found, fps=result.fps, layout=np.str_(result.layout))
    out = tmp_path / "out.npz"

    status = main(["clone", str(rigs_dir / f"{CHARACTER}.rig"), str(tracked), "-o", str(out)])

    assert status == 0, capsys.readouterr().err
    with np.load(out) as cloned:
        weights = cloned["weights"]
    assert weights.shape[0] == len(POSES) * HOLD and np.isfinite(weights).all()
    # The frames without a face hold the last tracked one (the closed mouth's).
    np.testing.assert_array_equal(weights[HOLD : 2 * HOLD], weights[[HOLD - 1] * HOLD])
    assert np.abs(weights[2 * HOLD] - weights[0]).max() > 1e-3
    glb = tmp_path / "out.glb"
    assert main(["clone", str(rigs_dir / f"{CHARACTER}.rig"), str(tracked), "-o", str(glb)]) == 0
    assert glb.read_bytes()[:4] == b"glTF"


def test_the_largest_frame_the_reader_takes_is_tracked(tmp_path):
    """``MAX_SIDE`` is what the page can take: at 8192^2, the old maximum, Chromium's page
    died after minutes (a TargetClosedError traceback, issue 31)."""
    side = MAX_SIDE
    path = tmp_path / "largest.y4m"
    planes = bytes([90]) * (side * side) + bytes([128]) * (side * side // 2)
    path.write_bytes(f"YUV4MPEG2 W{side} H{side} F25:1\nFRAME\n".encode() + planes)

    result = track_video(path, progress=False)

    assert result.num_frames == 1 and result.faces.tolist() == [0]

"""The webcam benchmark through ``facecast track``: the face found, followed, and cloned.

``facecast bench webcam`` renders its camera videos (an ICT head, Lambert on grey) and
tracks them with the /perform page's own pipeline in a real Chromium, once for the module
(its slowest test): every path is scored against the known truth within a bound, a second
run reuses the kept videos and points, and the keys video's tracked points move the way
the rendered face does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from facecast.cli.bench.facevideo import ARKIT_GAZE_DEGREES
from facecast.cli.main import main
from facecast.rig.evaluation.webcam import ict_performer, key_clips

from .conftest import ICT_ARCHIVE as ARCHIVE
from .conftest import ICT_TRACKING

pytestmark = ICT_TRACKING
#: The take's first 20 frames (a third of a second at 60 fps: the brows and eyes rise, the
#: jaw opens); three keys, of which the take uses the first two, so the personal path
#: clones something (on the first 8 frames it did no better than the neutral).
KEYS = ("browInnerUp", "jawOpen", "eyeBlinkLeft")
FRAMES, HOLD = 20, 3
#: Feature positions of the inner upper and lower lip (Multi-PIE 62, 66) in the layout.
INNER_UPPER, INNER_LOWER = 17, 18


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> tuple[list[dict[str, Any]], Path]:
    """Two runs of ``bench webcam`` on one ``--videos`` folder (the second reuses what the
    first kept): their JSON reports and the folder."""
    folder = tmp_path_factory.mktemp("webcam")
    argv = ["bench", "webcam", "--frames", str(FRAMES), "--keys", ",".join(KEYS),
            "--ramp", "0", "--hold", str(HOLD), "--eyes-short",
            "--videos", str(folder / "kept")]  # fmt: skip
    reports = []
    for run in ("first", "again"):
        out = folder / f"{run}.json"
        assert main([*argv, "--json", str(out)]) == 0
        reports.append(json.loads(out.read_text()))
    return reports, folder / "kept"


def test_the_rendered_face_is_found_in_every_frame_and_its_mouth_followed(bench):
    # The keys video as the benchmark tracked it (facecast track's .npz): the neutral held,
    # then each key held at 1, the jaw's among them.
    (points_file,) = bench[1].glob("keys*.npz")
    performer = ict_performer(ARCHIVE)
    act = key_clips(performer.names, keys=KEYS, ramp=0, hold=HOLD).activations
    jaw = act[:, performer.names.index("jawOpen")] == 1.0

    with np.load(points_file) as tracked:
        found, points = tracked["found"], tracked["points"]

    assert len(found) == len(act) and found.all()
    gap = points[:, INNER_UPPER, 1] - points[:, INNER_LOWER, 1]
    exact = performer.landmark_points(act)
    exact_gap = exact[:, INNER_UPPER, 1] - exact[:, INNER_LOWER, 1]
    # The tracker's face frame is about centimetres (eye-centre distance 6.3), as ICT's.
    opened = gap[jaw].mean() - gap[:HOLD].mean()
    assert 0.5 * np.ptp(exact_gap) < opened < 2.0 * np.ptp(exact_gap)


#: Upper bounds on each path's error against the truth: eq. 4.1's worst axis, %, as the
#: benchmark prints it. Measured on 3 runs, identical to 4 decimals (the render and the
#: tracker are deterministic here): tracked personal 1.454, generic 1.645; exact personal
#: 1.417, generic 0.379 (2026-12-05, the generic row on the shipped set of option (z):
#: 1.557, its ICT-landmark twin 1.634; personal 1.443); with the eyeballs turning at ARKit's
#: 35° a unit, the default since 2026-12-05 17:25 UTC: tracked personal 1.477, generic 1.566
#: (1.443 / 1.549 unturned, the blink curve in), exact 1.417 / 0.334 (the exact rows do not
#: depend on the render). Broken paths, measured on the unturned videos: weights zeroed (the
#: neutral) 2.37 on every row; the take's points shuffled: tracked personal 2.63, generic
#: 26; every point (keys' and take's) shuffled: generic 2.36 tracked, 2.37 exact (the
#: personal rig, fitted on the same points, cannot tell a consistent relabelling); landmark
#: 5 read as 6: generic 2.04 tracked, 1.84 exact; the inner lips swapped: exact generic
#: 0.815 (tracked 1.70, under its bound: caught on exact landmarks only); the take played
#: backwards: personal 2.93 tracked, 3.04 exact.
BOUNDS = {
    "tracked": {"personal": 1.75, "generic": 1.8},
    "exact": {"personal": 1.6, "generic": 0.6},
}


def max_axis(row: dict[str, Any]) -> float:
    return max(row["eq41_percent"].values())


def test_bench_on_tracked_videos_scores_every_path_near_the_truth_and_reuses_what_it_kept(bench):
    reports, _ = bench

    first, again = (report["tracked"] for report in reports)
    assert first["take_found"] == FRAMES and first["key_found"] == HOLD * (1 + len(KEYS))
    assert first["keys_captured"] == 1 + len(KEYS)  # the neutral and the keys
    assert set(first["rows"]) == {
        "personal", "nnls", "personal on keys' mix", "generic", "generic (ICT landmarks)",
        "generic exact", "generic noise", "personal live kalman 480", "generic live kalman 480",
    }  # fmt: skip
    # The live Kalman filter, as a channel with ``smoothing`` runs it on the published
    # points: less jitter on both paths (the full take: 0.242 -> 0.076 personal).
    for path in ("personal", "generic"):
        live = first["rows"][f"{path} live kalman 480"]
        assert live["jitter_percent"] < first["rows"][path]["jitter_percent"], path
    errors = {
        landmarks: {path: max_axis(reports[0][landmarks]["rows"][path]) for path in bounds}
        for landmarks, bounds in BOUNDS.items()
    }
    assert all(
        errors[landmarks][path] < bound
        for landmarks, bounds in BOUNDS.items()
        for path, bound in bounds.items()
    ), errors
    assert set(first["render_seconds"]) == set(first["track_seconds"]) == {"take", "keys", "eyes"}
    # Issue 34's take goals, judged on the rows viewers get (the live filter's).
    goals = reports[0]["take_goals"]
    assert {path: goal["goal"] for path, goal in goals.items()} == {"personal": 2.0, "generic": 2.5}
    for path, goal in goals.items():
        assert goal["row"] == f"{path} live kalman 480"
        assert goal["figure"] == max_axis(first["rows"][goal["row"]])
        assert goal["pass"] == (goal["figure"] <= goal["goal"])
    # The eyeballs turn as ARKit's weights say on a real face, unless asked otherwise.
    assert reports[0]["gaze_degrees"] == ARKIT_GAZE_DEGREES == 35.0
    # The eyes clip, its own video (another face's keys, then the clip), tracked once too.
    eyes = reports[0]["eyes_tracked"]
    assert eyes["performer"] == "person12" and eyes["keys_captured"] == 1 + len(KEYS)
    assert eyes["short"] and eyes["clip_frames"] == 102  # one of each event, 3-frame holds
    assert eyes["clip_found"] == eyes["clip_frames"] and eyes["render_seconds"] > 0
    assert {len(row["gaze"]) for row in eyes["rows"].values()} == {4}
    # The second run renders and tracks nothing: it scores the kept points, to the same figures.
    assert again["render_seconds"] == again["track_seconds"] == {}
    assert again["rows"] == first["rows"]
    assert reports[1]["eyes_tracked"]["rows"] == eyes["rows"]
    assert reports[1]["eyes_tracked"]["render_seconds"] is None

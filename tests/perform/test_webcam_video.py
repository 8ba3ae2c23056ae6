"""The webcam benchmark's rendered face through ``facecast track``: found, and followed.

A short clip of the benchmark's camera video (an ICT head, Lambert on grey) tracked by the
/perform page's own pipeline in a real Chromium: the face is found in every frame and the
tracked points move the way the rendered face does.
"""

from __future__ import annotations

import json

import numpy as np

from facecast.cli.bench.facevideo import head_scene, write_video
from facecast.cli.main import main
from facecast.cli.track import track_video
from facecast.rig.evaluation.webcam import ict_performer
from facecast.rig.sources.ict import ict_regions

from .conftest import ICT_ARCHIVE as ARCHIVE
from .conftest import ICT_TRACKING

pytestmark = ICT_TRACKING
HOLD = 4
#: Feature positions of the inner upper and lower lip (Multi-PIE 62, 66) in the layout.
INNER_UPPER, INNER_LOWER = 17, 18


def test_the_rendered_face_is_found_in_every_frame_and_its_mouth_followed(tmp_path):
    performer = ict_performer(ARCHIVE)
    regions, landmarks68 = ict_regions(ARCHIVE)
    act = np.zeros((2 * HOLD, len(performer.names)))
    act[HOLD:, performer.names.index("jawOpen")] = 0.6
    path = write_video(tmp_path / "clip.y4m", head_scene(performer, regions, landmarks68),
                       performer, act, fps=30.0, sway_degrees=1.5, progress=False)  # fmt: skip

    result = track_video(path, progress=False)

    assert result.found.all()
    gap = result.points[:, INNER_UPPER, 1] - result.points[:, INNER_LOWER, 1]
    exact = performer.landmark_points(act)
    exact_gap = exact[:, INNER_UPPER, 1] - exact[:, INNER_LOWER, 1]
    # The tracker's face frame is about centimetres (eye-centre distance 6.3), as ICT's.
    opened = gap[HOLD:].mean() - gap[:HOLD].mean()
    assert 0.5 * np.ptp(exact_gap) < opened < 2.0 * np.ptp(exact_gap)


def test_bench_on_tracked_videos_scores_every_path_and_reuses_what_it_kept(tmp_path):
    argv = ["bench", "webcam", "--frames", "8", "--keys", "jawOpen,mouthSmileLeft,eyeBlinkLeft",
            "--ramp", "0", "--hold", "3", "--videos", str(tmp_path / "kept")]  # fmt: skip

    reports = []
    for run in ("first", "again"):
        out = tmp_path / f"{run}.json"
        assert main([*argv, "--json", str(out)]) == 0
        reports.append(json.loads(out.read_text()))

    first, again = (report["tracked"] for report in reports)
    assert first["take_found"] == 8 and first["key_found"] == 3 + 3 * 3
    assert first["keys_captured"] == 4  # the neutral and the three keys
    assert set(first["rows"]) == {
        "personal", "nnls", "personal on keys' mix", "generic", "generic exact", "generic noise"
    }  # fmt: skip
    assert set(first["render_seconds"]) == set(first["track_seconds"]) == {"take", "keys", "eyes"}
    # The eyes clip, its own video (another face's keys, then the clip), tracked once too.
    eyes = reports[0]["eyes_tracked"]
    assert eyes["performer"] == "person12" and eyes["keys_captured"] == 4
    assert eyes["clip_found"] == eyes["clip_frames"] and eyes["render_seconds"] > 0
    assert {len(row["gaze"]) for row in eyes["rows"].values()} == {4}
    # The second run renders and tracks nothing: it scores the kept points, to the same figures.
    assert again["render_seconds"] == again["track_seconds"] == {}
    assert again["rows"] == first["rows"]
    assert reports[1]["eyes_tracked"]["rows"] == eyes["rows"]
    assert reports[1]["eyes_tracked"]["render_seconds"] is None

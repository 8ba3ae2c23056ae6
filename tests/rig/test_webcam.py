"""The webcam benchmark's numbers: key clips, captures, lost frames, and the exact pipeline."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.rig.characters.character_examples import generic_pairing
from facecast.rig.characters.generic import GAZE_SHAPES
from facecast.rig.errors import InputError
from facecast.rig.evaluation.webcam import (
    captured_keys,
    eye_closures,
    hold_last_found,
    ict_performer,
    key_clips,
    on_generic_set,
    source_on_neutral,
    superposition,
)
from facecast.rig.examples import ExampleSet
from facecast.rig.sources.ict import DEFAULT_LANDMARKS, ict_regions, locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set

ARCHIVE = locate_ict()
needs_ict = pytest.mark.skipif(
    ARCHIVE is None, reason="ICT-FaceKit not found (../shared/data/ict-facekit)"
)
NAMES = ("neutral", "a", "b", "c")


def test_key_clips_hold_each_expression_alone_at_weight_one():
    clips = key_clips(NAMES, ramp=3, hold=5)

    assert clips.activations.shape == (5 + 3 * (3 + 5), 4)
    assert (clips.activations[:, 0] == 0).all()
    for i, (start, stop) in enumerate(clips.held):
        assert stop - start == 5
        expected = np.zeros(4)
        expected[i] = 1.0 if i else 0.0
        assert (clips.activations[start:stop] == expected).all()
    rise = clips.activations[5:8, 1]
    assert 0 < rise[0] < rise[1] < rise[2] < 1  # the ramp rises from rest


def test_key_clips_perform_only_the_keys_asked_for_in_their_order():
    clips = key_clips(NAMES, keys=["c", "a"], ramp=0, hold=3)

    assert clips.names == ("neutral", "c", "a")
    assert clips.activations.shape == (3 + 2 * 3, 4)
    assert (clips.activations[3:6] == [0, 0, 0, 1]).all()  # "c" first, in its own column
    assert (clips.activations[6:9] == [0, 1, 0, 0]).all()
    assert not clips.activations[:, 2].any()  # "b" skipped


@pytest.mark.parametrize("keys", [["neutral"], ["z"], ["a", "a"]])
def test_key_clips_refuse_keys_the_face_cannot_make(keys):
    with pytest.raises(InputError) as info:
        key_clips(NAMES, keys=keys)
    assert info.value.code == "unknown_expression"


def test_captured_keys_are_the_held_frames_medians():
    clips = key_clips(NAMES, ramp=2, hold=5)
    rng = np.random.default_rng(0)
    shapes = rng.normal(size=(4, 6, 3))
    points = np.einsum("fm,mkc->fkc", clips.activations[:, 1:], shapes[1:]) + shapes[0]
    points += rng.normal(0, 0.01, points.shape)

    keys, held = captured_keys(points, clips)

    assert list(keys) == list(NAMES)
    for name, shape, (start, stop) in zip(NAMES, shapes, clips.held, strict=True):
        expected = shape if name == "neutral" else shape + shapes[0]
        assert np.abs(keys[name] - expected).max() < 0.05
        assert len(held[name]) <= stop - start


def test_a_key_seen_in_fewer_than_three_frames_is_not_captured():
    clips = key_clips(NAMES, ramp=0, hold=4)
    points = np.zeros((len(clips.activations), 6, 3))
    found = np.ones(len(points), dtype=bool)
    start, stop = clips.held[2]
    found[start : stop - 2] = False  # "b" is in view for 2 of its held frames

    keys, _ = captured_keys(points, clips, found)

    assert "b" not in keys and {"neutral", "a", "c"} <= set(keys)


def test_no_neutral_in_view_is_an_error():
    clips = key_clips(NAMES, ramp=0, hold=4)
    points = np.zeros((len(clips.activations), 6, 3))
    points[:4] = np.nan

    with pytest.raises(InputError) as info:
        captured_keys(points, clips)
    assert info.value.code == "no_neutral"


def test_superposition_splits_a_steady_offset_from_frame_noise():
    rng = np.random.default_rng(2)
    keys = {name: rng.normal(size=(5, 3)) for name in NAMES}
    activations = np.zeros((40, 4))
    activations[:, 1:] = rng.uniform(0, 1, (40, 3))
    mix = keys["neutral"] + np.einsum(
        "fm,mkc->fkc", activations[:, 1:], np.stack([keys[n] - keys["neutral"] for n in NAMES[1:]])
    )
    flicker = np.where(np.arange(40) % 2, 0.1, -0.1)[:, None, None] * np.ones((1, 5, 3))

    got, rms, slow = superposition(mix + 0.3 + flicker, keys, activations, NAMES)

    assert np.allclose(got, mix)
    assert rms == pytest.approx(np.sqrt(0.3**2 + 0.1**2))
    assert slow == pytest.approx(0.3, abs=0.02)  # the flicker averages out, the offset stays


def test_a_lost_frame_keeps_the_last_frame_with_a_face():
    points = np.arange(5, dtype=float)[:, None, None] * np.ones((5, 2, 3))
    found = np.array([False, True, False, False, True])

    held = hold_last_found(points, found)

    assert held[:, 0, 0].tolist() == [1.0, 1.0, 1.0, 1.0, 4.0]


@pytest.mark.ict
@needs_ict
def test_performer_landmarks_are_its_mesh_vertices():
    performer = ict_performer(ARCHIVE)
    activations = np.zeros((2, len(performer.names)))
    activations[1, performer.names.index("jawOpen")] = 0.7

    vertices = performer.vertices(activations)
    points = performer.landmark_points(activations)

    assert np.allclose(points, vertices[:, performer.landmarks], atol=1e-4)
    chin = DEFAULT_LANDMARKS.index(8)  # Multi-PIE 8, the chin
    assert points[1, chin, 1] < points[0, chin, 1] - 1.0  # the jaw opens downwards (cm)


@pytest.mark.ict
@needs_ict
def test_bench_on_exact_landmarks_scores_every_path(tmp_path, capsys):
    out = tmp_path / "webcam.json"

    status = main(
        ["bench", "webcam", "--exact-only", "--frames", "12", "--ramp", "1", "--hold", "3",
         "--no-eyes", "--json", str(out)]
    )  # fmt: skip

    assert status == 0
    report = json.loads(out.read_text())
    assert "eyes_exact" not in report
    rows = report["exact"]["rows"]
    assert list(rows) == [
        "personal", "nnls", "personal on keys' mix", "generic", "generic exact", "generic noise",
        "personal live kalman 480", "generic live kalman 480",
    ]  # fmt: skip
    assert report["exact"]["superposition_rms"] < 1e-9  # exact points are the keys' mix
    assert report["exact"]["keys_captured"] == report["exact"]["keys"] == 52
    # Exact landmarks of a linear face: NNLS on the captured keys is exact; the personal rig,
    # fitted for the server's noise floor, is close; re-basing moves the generic rig's
    # deltas by the identities' similarity, so it is off by more.
    assert max(rows["nnls"]["eq41_percent"].values()) < 1e-3
    assert 0 < max(rows["personal"]["eq41_percent"].values()) < 1.0
    for row in rows.values():
        assert set(row["weight_rms"]) == set(ict_performer(ARCHIVE).names[1:])
        assert set(row["closures"]) == {"eyeBlinkLeft", "eyeBlinkRight"}
    assert "personal" in capsys.readouterr().out


@pytest.mark.ict
@needs_ict
def test_bench_eyes_clip_on_exact_landmarks_scores_each_event_on_both_paths(tmp_path, capsys):
    out = tmp_path / "webcam.json"

    status = main(["bench", "webcam", "--exact-only", "--eyes-only", "--ramp", "1", "--hold", "3",
                   "--kalman", "480,2000", "--json", str(out)])  # fmt: skip

    assert status == 0
    report = json.loads(out.read_text())
    assert "exact" not in report  # --eyes-only: no take
    eyes = report["eyes_exact"]
    assert eyes["performer"] == "person12" and eyes["keys_captured"] == 52
    rows = eyes["rows"]
    assert list(rows) == [
        f"{path} {label}" for path in ("personal", "generic")
        for label in ("live", "live kalman 480", "live kalman 2000", "offline")
    ]  # fmt: skip
    for row in rows.values():
        assert len(row["blinks"]) == 3 and len(row["winks"]) == 2 and len(row["gaze"]) == 4
        # Exact landmarks: every gaze hold reads the right way, and a wink stays on its eye.
        assert all(g["right"] for g in row["gaze"]), row["gaze"]
        assert max(w["other"] for w in row["winks"]) < 0.05, row["winks"]

    # Two points a lid (the 24-point layout) tell a blink from a look down: the personal
    # path's live blinks and winks reach 0.94 of the truth (0.74 with one point a lid, the
    # 20-point layout; 1.00 since each captured blink is read as closed), the generic
    # path's 0.61 (0.37; 0.52 at half the identity residual; 1.00 since the captured closed
    # eyes go with its neutral, PROTOCOL.md §5.1.3 blinks),
    # offline too: the offline smoother keeps the re-base's identity share, as live
    # (refitted without it, offline reached 1.00 on these exact points and 0.03 on the
    # tracked ones).
    def least_blink(row: str) -> float:
        return min(v for blink in rows[row]["blinks"] for v in blink.values())

    assert least_blink("personal live") > 0.9
    assert min(w["peak"] for w in rows["personal live"]["winks"]) > 0.9
    assert least_blink("generic live") > 0.45 and least_blink("generic offline") > 0.45
    # The re-base's share of the identity residual (rebase.IDENTITY_NOISE_FACTOR, 0.35):
    # live, the generic path's winks and jaw + smile reach issue 34's goals (a wink >= 0.6
    # on its eye and <= 0.3 on the other, each part >= 60 %: 0.61, 89 / 68 %); at half
    # the residual they did not (0.52, 84 / 56 %).
    generic = rows["generic live"]["goals"]
    assert generic["winks"] and generic["combo"], rows["generic live"]
    # Each filter is run: the live Kalman and the offline smoother move the personal
    # path's wink peaks; the generic path's winks are whole on every row (its blink curve,
    # rebase.REBASE_BLINK_CONTRAST), so there they move the combination's shares.
    for path, figure in (("personal", "winks"), ("generic", "combo")):
        live = rows[f"{path} live"][figure]
        assert rows[f"{path} live kalman 480"][figure] != live != rows[f"{path} offline"][figure]
    assert all(w["peak"] == 1.0 for w in rows["generic live kalman 480"]["winks"])
    assert "personal live kalman 2000" in capsys.readouterr().out


@pytest.mark.ict
@needs_ict
def test_bench_blink_contrast_reaches_the_generic_rows(tmp_path):
    # --blink-contrast reads the generic path's closed eyes as a calibrate's blink_contrast
    # asks (without it, the server's curve). One that closes any reading above 0.01: the
    # held look down, which ICT's shape makes with the lids, then reads shut (exact
    # landmarks).
    shut = {}
    for curve in (None, "0,0.01"):
        out = tmp_path / f"{curve}.json"
        given = [] if curve is None else ["--blink-contrast", curve]
        assert main(["bench", "webcam", "--exact-only", "--eyes-only", "--eyes-short", "--ramp",
                     "1", "--hold", "3", *given, "--json", str(out)]) == 0  # fmt: skip
        report = json.loads(out.read_text())
        gaze = report["eyes_exact"]["rows"]["generic live"]["gaze"]
        shut[curve] = {g["direction"]: g["shut"] for g in gaze}
    assert report["blink_contrast"] == [0.0, 0.01]
    assert shut[None]["down"] < 0.1 and shut["0,0.01"]["down"] > 0.9, shut


@pytest.mark.ict
@needs_ict
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--take", "/nonexistent.csv"], "no such file"),
        (["--performer", "person01"], "both person01"),
        (["--performer", "nobody"], "no ICT identity named 'nobody'"),
        (["--frames", "2"], "at least 3"),
        (["--sway", "30"], "--sway"),
        (["--gaze-degrees", "50"], "--gaze-degrees"),
        (["--generic-neutral", "tracked"], "not with --exact-only"),
        (["--eyes-performer", "person07"], "another face"),
        (["--eyes-only", "--no-eyes"], "nothing to measure"),
        (["--kalman", "0"], "finite and > 0"),
        (["--landmarks", "17,70"], "positions must lie in [0, 68)"),
        (["--as-uploaded", "--generic-neutral", "ict"], "only with --generic-neutral shipped"),
    ],
)
def test_bench_refuses_bad_arguments_with_a_message(argv, message, capsys):
    status = main(["bench", "webcam", "--exact-only", *argv])

    assert status == 2
    assert message in capsys.readouterr().err


@pytest.mark.ict
@needs_ict
def test_as_uploaded_the_character_is_paired_as_an_upload_pairs_it():
    examples = arkit_example_set(ARCHIVE)

    every = on_generic_set(examples)
    uploaded = on_generic_set(examples, uploaded=True)

    paired, unpaired = generic_pairing(examples.names[1:])
    assert uploaded.names == ("neutral", *paired)
    assert set(every.names) - set(uploaded.names) == set(GAZE_SHAPES) <= set(unpaired)
    # The same source points for the shapes both keep: only the pairing differs.
    kept = [every.names.index(name) for name in uploaded.names]
    np.testing.assert_array_equal(uploaded.source_points, every.source_points[kept])


def test_bench_refuses_an_unusable_blink_contrast_before_rendering(capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "webcam", "--exact-only", "--blink-contrast", "0.9,0.5"])
    assert stopped.value.code == 2
    assert "expected 0 <= LOW < HIGH <= 1" in capsys.readouterr().err


@pytest.mark.ict
@needs_ict
def test_ict_regions_tile_the_mesh_and_name_its_landmarks():
    regions, landmarks68 = ict_regions(ARCHIVE)

    ranges = sorted(regions.values())
    assert ranges[0][0] == 0 and ranges[-1][1] == len(ict_performer(ARCHIVE).neutral)
    assert all(a[1] == b[0] for a, b in itertools.pairwise(ranges))  # no gap
    assert {"face", "teeth", "eyeball_left", "eyelashes_right"} <= set(regions)
    assert landmarks68.shape == (68,) and (landmarks68 < regions["face"][1]).all()


def _turned(points: np.ndarray, degrees: float, scale: float, shift) -> np.ndarray:
    angle = np.radians(degrees)
    turn = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    return scale * points @ turn.T + np.asarray(shift)


def test_source_on_neutral_keeps_each_shape_and_takes_the_other_rest_pose():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(4, 6, 3))
    examples = ExampleSet(names=("neutral", "a", "b", "c"), source_points=source,
                          target_vertices=source, target_faces=np.array([[0, 1, 2]]))  # fmt: skip
    seen = source[0].copy()
    seen[2] += (0.3, -0.2, 0.1)  # one landmark defined elsewhere by the tracker

    # The same face seen turned, larger and elsewhere (a tracker's frame and unit).
    moved = source_on_neutral(examples, _turned(seen, 30.0, 2.5, (1.0, -4.0, 7.0)))

    out = moved.source_points
    np.testing.assert_allclose(out - out[0], source - source[0], atol=1e-12)  # shapes kept
    offset = np.linalg.norm(out[0] - source[0], axis=1)
    assert offset[2] > 0.5 * np.linalg.norm((0.3, -0.2, 0.1))  # the one defined elsewhere
    assert np.delete(offset, 2).max() < 0.5 * offset[2]  # moved most (the fit spreads some)
    same = source_on_neutral(examples, _turned(source[0], -20.0, 0.5, (3.0, 0.0, 0.0)))
    np.testing.assert_allclose(same.source_points, source, atol=1e-9)


def test_eye_closures_finds_each_run_and_its_peak_share_within_the_margin():
    truth = np.zeros(40)
    truth[5:9] = [0.6, 0.9, 0.9, 0.6]  # a closure of 4 frames
    truth[20:30] = 0.8  # a held one
    truth[38:] = 0.7  # cut by the take's end
    late = np.zeros(40)
    late[2:] = 0.5 * truth[:-2]  # half as far, two frames late (within the margin)
    late[38:] = 0.35  # the cut one: half as far, on time

    got = eye_closures(late, truth)

    assert [(e["start"], e["frames"]) for e in got["events"]] == [(5, 4), (20, 10), (38, 2)]
    assert [e["share"] for e in got["events"]] == pytest.approx([0.5, 0.5, 0.5])
    assert 0.5 < got["correlation"] < 1.0
    # A closure missed entirely reads 0; a steady estimate has no correlation.
    flat = eye_closures(np.zeros(40), truth)
    assert [e["share"] for e in flat["events"]] == [0.0, 0.0, 0.0]
    assert flat["correlation"] is None
    # Frames below the level are no closure; the peak is looked for `margin` frames out only.
    later = np.zeros(40)
    later[8:] = truth[:-8]  # the first closure starts after its run and margin have ended
    assert eye_closures(later, truth, margin=3)["events"][0]["share"] == 0.0
    assert eye_closures(later, truth, margin=8)["events"][0]["share"] == 1.0
    assert eye_closures(truth, truth * 0.4)["events"] == []
    with pytest.raises(InputError, match="closures"):
        eye_closures(np.zeros(3), np.zeros(4))

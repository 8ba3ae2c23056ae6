"""Live Link Face CSV takes and MediaPipe NDJSON takes: parsed values and line-numbered errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecast.rig.errors import InputError
from facecast.rig.sources.loading import load_source_animation
from facecast.rig.sources.source_rig import ARKIT_NAMES, HEAD_POSE_NAMES, arkit_index
from facecast.rig.sources.trackers import (
    MEDIAPIPE_FEATURES,
    livelink_csv_animation,
    load_mediapipe_mapping,
    mediapipe_animation,
    parse_timecode,
    read_livelink_csv,
    read_mediapipe_ndjson,
)

# The app writes PascalCase columns, and not in the UDP packet's order (JawRight first).
_PASCAL = [n[0].upper() + n[1:] for n in ARKIT_NAMES]
_JAW = _PASCAL.index("JawLeft")
_COLUMNS = [*_PASCAL[:_JAW], "JawRight", "JawLeft", *_PASCAL[_JAW + 2 :]]
_HEAD = [n[0].upper() + n[1:] for n in HEAD_POSE_NAMES]
HEADER = ",".join(["Timecode", "BlendShapeCount", *_COLUMNS, *_HEAD])


def _row(timecode: str, weights: np.ndarray, head: np.ndarray) -> str:
    by_name = {p: weights[i] for i, p in enumerate(_PASCAL)}
    cells = [timecode, "61", *(f"{by_name[c]:.6f}" for c in _COLUMNS), *(f"{h:.6f}" for h in head)]
    return ",".join(cells)


@pytest.fixture
def take(tmp_path):
    rng = np.random.default_rng(3)
    weights = np.round(rng.uniform(size=(3, 52)), 6)
    head = np.round(rng.uniform(-0.3, 0.3, size=(3, 9)), 6)
    codes = ["17:43:50:29.500", "17:43:50:30.500", "17:43:50:31.000"]
    lines = [HEADER, *(_row(c, w, h) for c, w, h in zip(codes, weights, head, strict=True))]
    path = tmp_path / "take.csv"
    path.write_text("\n".join(lines) + "\n")
    return path, weights, head


def test_csv_weights_are_read_by_column_name(take):
    path, weights, head = take
    read = read_livelink_csv(path, fps=60.0)
    assert np.allclose(read.weights, weights)
    assert read.weights[0, arkit_index("jawLeft")] == pytest.approx(
        weights[0, arkit_index("jawLeft")]
    )
    assert np.allclose(read.head, head)


def test_csv_timestamps_come_from_the_timecodes_at_the_take_fps(take):
    path, _, _ = take
    read = read_livelink_csv(path, fps=60.0)
    assert np.allclose(read.timestamps, [0.0, 1.0 / 60, 1.5 / 60])


def test_timecode_fraction_is_a_fraction_of_a_frame():
    assert parse_timecode("01:02:03:30.5", 60.0) == pytest.approx(3723 + 30.5 / 60)
    assert parse_timecode("00:00:01:15", 30.0) == pytest.approx(1.5)


def test_csv_animation_points_come_through_the_source_rig(take, source_rig):
    path, weights, head = take
    animation = livelink_csv_animation(path, source_rig, head_pose=True)
    assert np.allclose(animation.points, source_rig.points(weights, head=head[:, :3]), atol=1e-9)
    assert np.allclose(animation.timestamps, [0.0, 1.0 / 60, 1.5 / 60])


def _write(tmp_path, lines, name="bad.csv"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _good_row(code="00:00:00:01.000"):
    return _row(code, np.zeros(52), np.zeros(9))


@pytest.mark.parametrize(
    ("mutate", "code", "line"),
    [
        (lambda r: r.rsplit(",", 1)[0], "wrong_column_count", 3),
        (lambda r: r.replace(",0.000000", ",nan", 1), "non_finite", 3),
        (lambda r: r.replace(",0.000000", ",inf", 1), "non_finite", 3),
        (lambda r: r.replace(",0.000000", ",abc", 1), "bad_csv", 3),
        (lambda r: "00:00:61:00" + r[len("00:00:00:02.000") :], "bad_timecode", 3),
        (lambda r: "yesterday" + r[len("00:00:00:02.000") :], "bad_timecode", 3),
        (lambda r: "00:00:00:00.500" + r[len("00:00:00:02.000") :], "bad_timecode", 3),
    ],
)
def test_malformed_csv_rows_name_their_line(tmp_path, mutate, code, line):
    path = _write(tmp_path, [HEADER, _good_row(), mutate(_good_row("00:00:00:02.000"))])
    with pytest.raises(InputError) as info:
        read_livelink_csv(path)
    assert info.value.code == code
    assert f"line {line}" in str(info.value)


def test_csv_without_a_blendshape_column_names_it(tmp_path):
    header = HEADER.replace(",MouthClose", ",Mouth_Closed")
    with pytest.raises(InputError) as info:
        read_livelink_csv(_write(tmp_path, [header, _good_row()]))
    assert info.value.code == "missing_column"
    assert "MouthClose" in str(info.value)


def test_csv_without_rows_or_file_is_an_error(tmp_path):
    with pytest.raises(InputError) as empty:
        read_livelink_csv(_write(tmp_path, [HEADER]))
    with pytest.raises(InputError) as missing:
        read_livelink_csv(tmp_path / "nope.csv")
    assert (empty.value.code, missing.value.code) == ("bad_csv", "missing_file")


def test_csv_with_more_rows_than_allowed_is_refused(tmp_path):
    path = _write(tmp_path, [HEADER, _good_row("00:00:00:01"), _good_row("00:00:00:02")])
    with pytest.raises(InputError) as info:
        read_livelink_csv(path, max_frames=1)
    assert info.value.code == "too_many_frames" and "line 3" in str(info.value)


def test_head_pose_without_head_columns_is_an_error(tmp_path, source_rig):
    header = ",".join(["Timecode", "BlendShapeCount", *_COLUMNS])
    row = ",".join(["00:00:00:01", "52", *["0"] * 52])
    path = _write(tmp_path, [header, row])
    assert read_livelink_csv(path).head is None
    with pytest.raises(InputError) as info:
        livelink_csv_animation(path, source_rig, head_pose=True)
    assert info.value.code == "missing_column"


# -- MediaPipe ----------------------------------------------------------------------------


def _landmarks(seed: int, count: int = 478) -> np.ndarray:
    return np.round(np.random.default_rng(seed).uniform(size=(count, 3)), 6)


def _ndjson(tmp_path, docs, name="take.ndjson"):
    path = tmp_path / name
    path.write_text("\n".join(d if isinstance(d, str) else json.dumps(d) for d in docs) + "\n")
    return path


def test_mediapipe_points_are_the_mapped_landmarks_with_y_up(tmp_path):
    marks = [_landmarks(i) for i in range(3)]
    docs = [{"landmarks": m.tolist(), "t": 0.5 + i / 30} for i, m in enumerate(marks)]
    take = read_mediapipe_ndjson(_ndjson(tmp_path, docs))
    indices = [index for _, _, index in MEDIAPIPE_FEATURES]
    expected = np.stack([m[indices] for m in marks]) * [1.0, -1.0, -1.0]
    assert np.allclose(take.points, expected)
    assert np.allclose(take.timestamps, [0.0, 1 / 30, 2 / 30])
    assert take.transforms is None


def test_mediapipe_custom_mapping_file_and_transforms(tmp_path):
    mapping = tmp_path / "map.txt"
    mapping.write_text("# three points\n1, 4\n152\n")
    docs = [{"landmarks": _landmarks(0, 468).tolist(), "transform": list(range(16))}]
    take = read_mediapipe_ndjson(
        _ndjson(tmp_path, docs), mapping=load_mediapipe_mapping(mapping), y_up=False
    )
    assert np.allclose(take.points[0], _landmarks(0, 468)[[1, 4, 152]])
    assert take.transforms.shape == (1, 4, 4) and take.transforms[0, 1, 0] == 4
    assert take.timestamps is None


def _turned(marks: np.ndarray, yaw: float, shift) -> np.ndarray:
    """The same mesh with the head turned about y and moved (normalised image units)."""
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    centre = marks.mean(axis=0)
    return (marks - centre) @ rotation.T + centre + shift


def test_mediapipe_face_frame_is_the_shared_normalisation_and_ignores_head_turns(tmp_path):
    from facecast.rig.sources.facemesh import image_to_mesh, normalise_mesh
    from facecast.rig.sources.layouts import load_layout

    marks = _landmarks(3, 478)
    turned = _turned(marks, 0.4, [0.05, -0.02, 0.0])
    docs = [{"landmarks": m.tolist()} for m in (marks, turned)]
    take = read_mediapipe_ndjson(_ndjson(tmp_path, docs), face_frame=True)
    layout = load_layout("mediapipe_face_mesh")
    expected = normalise_mesh(image_to_mesh(marks, 1.0, 1.0), layout)
    np.testing.assert_allclose(take.points[0], expected, atol=1e-9)
    np.testing.assert_allclose(take.points[1], take.points[0], atol=1e-6)


@pytest.mark.parametrize("face_frame", [False, True])
def test_a_mediapipe_take_without_irises_gives_the_layouts_first_24_points(tmp_path, face_frame):
    """468-landmark lines (MediaPipe without its iris refinement) have no iris centres,
    the layout's last two features: they give the first 24, what the same lines with the
    iris give first; a take mixing the two is refused by the line that changes."""
    marks = [_landmarks(i) for i in range(2)]
    full = read_mediapipe_ndjson(
        _ndjson(tmp_path, [{"landmarks": m.tolist()} for m in marks]), face_frame=face_frame
    )
    short = read_mediapipe_ndjson(
        _ndjson(tmp_path, [{"landmarks": m[:468].tolist()} for m in marks], "short.ndjson"),
        face_frame=face_frame,
    )
    assert full.points.shape == (2, 26, 3) and short.points.shape == (2, 24, 3)
    np.testing.assert_allclose(short.points, full.points[:, :24], atol=1e-12)
    mixed = [{"landmarks": marks[0].tolist()}, {"landmarks": marks[1][:468].tolist()}]
    with pytest.raises(InputError) as info:
        read_mediapipe_ndjson(_ndjson(tmp_path, mixed, "mixed.ndjson"), face_frame=face_frame)
    assert info.value.code == "wrong_landmark_count" and "line 2" in info.value.message


def test_mediapipe_face_frame_refuses_a_mapping_and_a_degenerate_mesh(tmp_path):
    flat = np.zeros((468, 3))
    path = _ndjson(tmp_path, [{"landmarks": flat.tolist()}])
    with pytest.raises(InputError) as degenerate:
        read_mediapipe_ndjson(path, face_frame=True)
    with pytest.raises(InputError) as mapped:
        read_mediapipe_ndjson(path, face_frame=True, mapping=[1, 2, 3])
    assert degenerate.value.code == "degenerate_face" and "line 1" in degenerate.value.message
    assert mapped.value.code == "bad_mapping"


def test_mediapipe_animation_has_one_frame_per_line(tmp_path):
    docs = [{"landmarks": _landmarks(i).tolist()} for i in range(4)]
    animation = mediapipe_animation(_ndjson(tmp_path, ["", *docs]), fps=30.0)
    assert animation.points.shape == (4, len(MEDIAPIPE_FEATURES), 3) and animation.fps == 30.0


def test_a_mediapipe_take_drives_a_rig_of_the_layouts_earlier_twenty_points(tmp_path):
    """An NDJSON take gives the layout's 26 points; a rig fitted on its earlier 20 or 24 (the
    layout grew by appending) takes the first 20 or 24, as /perform sends them."""
    docs = [{"landmarks": _landmarks(i).tolist()} for i in range(3)]
    path = _ndjson(tmp_path, docs)

    full = load_source_animation(path, num_points=len(MEDIAPIPE_FEATURES))
    first = load_source_animation(path, num_points=20)
    lids = load_source_animation(path, num_points=24)

    assert full.points.shape == (3, 26, 3)
    np.testing.assert_array_equal(first.points, full.points[:, :20])
    np.testing.assert_array_equal(lids.points, full.points[:, :24])
    with pytest.raises(InputError) as info:
        load_source_animation(path, num_points=21)
    assert info.value.code == "point_count_mismatch"


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("{not json", "bad_ndjson"),
        ("[1, 2, 3]", "bad_ndjson"),
        (json.dumps({"points": []}), "bad_ndjson"),
        (json.dumps({"landmarks": [[0, 0, 0]] * 477}), "wrong_landmark_count"),
        (json.dumps({"landmarks": [[0, 0]] * 478}), "bad_ndjson"),
        ('{"landmarks": [' + ",".join(["[NaN, 0, 0]"] * 478) + "]}", "non_finite"),
        (json.dumps({"landmarks": [[0, 0, 1e999]] * 478}), "non_finite"),
        (json.dumps({"landmarks": [[0, 0, 0]] * 478, "transform": [1] * 15}), "bad_ndjson"),
        (json.dumps({"landmarks": [[0, 0, 0]] * 478, "t": "soon"}), "bad_ndjson"),
        (json.dumps({"landmarks": [[0, 0, 0]] * 478, "t": -5}), "bad_time"),
    ],
)
def test_malformed_ndjson_lines_name_their_line(tmp_path, line, code):
    good = json.dumps({"landmarks": _landmarks(0).tolist(), "t": 1.0})
    path = _ndjson(tmp_path, [good, "", line])
    with pytest.raises(InputError) as info:
        read_mediapipe_ndjson(path)
    assert info.value.code == code
    assert "line 3" in str(info.value)


@pytest.mark.parametrize("text", ["[1, 2, 2]", "[]", "[478]", '{"indices": ["a"]}', "1 2 x"])
def test_bad_mapping_files_are_refused(tmp_path, text):
    path = tmp_path / "map.json"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_mediapipe_mapping(path)
    assert info.value.code == "bad_mapping"


# -- the takes wherever a source animation is read ------------------------------------
def test_load_source_animation_reads_a_livelink_take_through_a_source_rig(take, source_rig):
    from facecast.rig.sources.loading import load_source_animation

    path, _, _ = take
    loaded = load_source_animation(path, source_rig=source_rig)
    expected = livelink_csv_animation(path, source_rig)
    np.testing.assert_array_equal(loaded.points, expected.points)


def test_load_source_animation_refuses_a_livelink_take_without_a_source_rig(take):
    from facecast.rig.sources.loading import load_source_animation

    path, _, _ = take
    with pytest.raises(InputError, match="--source-rig") as info:
        load_source_animation(path)
    assert info.value.code == "source_rig_required"


def test_load_source_animation_reads_a_mediapipe_take(tmp_path):
    from facecast.rig.sources.loading import load_source_animation

    rng = np.random.default_rng(4)
    landmarks = rng.uniform(size=(2, 478, 3))
    path = tmp_path / "take.ndjson"
    path.write_text("\n".join(json.dumps({"landmarks": f.tolist()}) for f in landmarks) + "\n")
    loaded = load_source_animation(path)
    np.testing.assert_array_equal(loaded.points, mediapipe_animation(path).points)
    assert loaded.points.shape == (2, len(MEDIAPIPE_FEATURES), 3)


def test_clone_command_clones_a_livelink_take_through_a_source_rig(take, tmp_path, example_set):
    from facecast.cli.main import main
    from facecast.rig import fit
    from facecast.rig.sources.source_rig import SourceRig

    path, _, _ = take
    example_set.save_npz(tmp_path / "source_rig.npz")
    rig = fit(example_set)
    rig.save(tmp_path / "face.rig")
    out = tmp_path / "cloned.npz"
    status = main(
        ["clone", str(tmp_path / "face.rig"), str(path), "--source-rig",
         str(tmp_path / "source_rig.npz"), "-o", str(out)]
    )  # fmt: skip

    assert status == 0
    points = livelink_csv_animation(path, SourceRig.from_example_set(example_set)).points
    np.testing.assert_allclose(np.load(out)["weights"], rig.weights(points), atol=1e-12)

"""Landmark layouts load from package data, validate, and normalise a mesh's head pose away."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from facecast.rig.errors import InputError
from facecast.rig.sources.facemesh import image_to_mesh, normalise_mesh
from facecast.rig.sources.ict import DEFAULT_LANDMARKS
from facecast.rig.sources.layouts import layout_from_dict, layout_names, load_layout
from facecast.rig.sources.trackers import MEDIAPIPE_FEATURES

from .._perform_venv import track_images


@pytest.fixture(scope="module")
def layout():
    return load_layout("mediapipe_face_mesh")


def test_shipped_mediapipe_layout_maps_the_ict_default_landmarks_in_order(layout):
    assert "mediapipe_face_mesh" in layout_names()
    assert layout.tracker_points == 478 and layout.multipie_count == len(DEFAULT_LANDMARKS)
    k = layout.multipie_count
    assert layout.multipie68[:k] == DEFAULT_LANDMARKS and layout.features[:k].max() < 468
    # Then the iris centres, MediaPipe's 478-point mesh's (the subject's right eye first),
    # which the 68 landmarks lack.
    assert layout.multipie68[k:] == (None, None) and layout.features[k:].tolist() == [468, 473]
    assert layout.feature_names[k:] == ("right_iris", "left_iris")
    assert layout.counts == (20, 24, 26)


def test_a_mesh_without_the_iris_gives_the_first_24_points(layout):
    assert layout.count_within(478) == 26 and layout.count_within(468) == 24
    rng = np.random.default_rng(3)
    full = _face_mesh(layout, rng)
    mesh = full[:468]  # MediaPipe's mesh without the iris
    assert np.allclose(normalise_mesh(mesh, layout), normalise_mesh(full, layout)[:24])
    with pytest.raises(InputError) as info:
        normalise_mesh(mesh[:380], layout)  # lacks stable and feature points
    assert info.value.code == "wrong_landmark_count" and "380 points" in info.value.message


def test_ndjson_reader_uses_the_layout_table(layout):
    assert [index for _, _, index in MEDIAPIPE_FEATURES] == layout.features.tolist()
    assert [name for name, _, _ in MEDIAPIPE_FEATURES] == list(layout.feature_names)


def test_stable_points_avoid_brows_lids_lips_and_chin(layout):
    moving = {n for n in layout.feature_names if n != "nose_tip"}
    moving_indices = {
        i for n, i in zip(layout.feature_names, layout.features, strict=True) if n in moving
    }
    eyelids = {layout.eyes[s][p] for s in ("left", "right") for p in ("upper", "lower")}
    assert not (set(layout.stable.tolist()) & (moving_indices | eyelids))
    for part in ("left", "right", "top", "bottom"):
        assert set(layout.frame[part].tolist()) <= set(layout.stable.tolist())


def test_the_layout_grew_by_appending_so_twenty_point_rigs_take_its_prefix(layout):
    """The 24-point layout (two points a lid) is the 20-point one with 4 lid points
    appended, the 26-point one the 24 with the iris centres appended: a rig or capture of
    20 or 24 points is driven by the first 20 or 24, any other count not."""
    assert layout.earlier_counts == (20, 24) and layout.counts == (20, 24, 26)
    assert layout.drives(20) and layout.drives(24) and layout.drives(26)
    assert not any(layout.drives(k) for k in (0, 19, 21, 23, 25, 27, 68))
    # A rig of an earlier count takes the first of a later count's points; nothing else does.
    takes = {(n, k) for n in range(30) for k in range(30) if layout.takes_first(n, k)}
    assert takes == {(24, 20), (26, 20), (26, 24)}
    first20 = [
        70,
        105,
        107,
        336,
        334,
        300,
        160,
        144,
        387,
        373,
        4,
        75,
        305,
        61,
        0,
        291,
        17,
        13,
        14,
        152,
    ]
    assert layout.features[:20].tolist() == first20  # the 20-point version, unchanged
    lids = {layout.feature_names[i]: int(layout.features[i]) for i in range(20, 24)}
    # FaceMesh's upper / lower lid a third in from each inner corner (Multi-PIE 38, 40 / 43, 47)
    assert lids == {"right_upper_lid_inner": 158, "right_lower_lid_inner": 153,
                    "left_upper_lid_inner": 385, "left_lower_lid_inner": 380}  # fmt: skip


def test_layout_round_trips_through_its_dict(layout):
    again = layout_from_dict(layout.to_dict())
    assert again.to_dict() == layout.to_dict()


def test_unknown_layout_name_is_refused():
    with pytest.raises(InputError) as info:
        load_layout("dlib_68")
    assert info.value.code == "unknown_layout" and "mediapipe_face_mesh" in info.value.message


def _broken(layout, path, value):
    doc = copy.deepcopy(layout.to_dict())
    node = doc
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


@pytest.mark.parametrize(
    ("path", "value", "needle"),
    [
        (("features",), [70, 70], "twice"),
        (("features",), [70, 478], "outside [0, 478)"),
        (("features",), [70, 1.5], "integer"),
        (("feature_names",), ["a"], "name the 26 features"),
        (("earlier_counts",), [26], "earlier_counts"),
        (("earlier_counts",), [20, 12], "earlier_counts"),
        (("earlier_counts",), [0], "earlier_counts"),
        (("earlier_counts",), 20, "earlier_counts"),
        (("stable",), [1, 2], "at least 3"),
        (("eyes", "left", "upper"), KeyError, "eyes.left"),
        (("frame", "span"), 0, "frame.span"),
        (("frame", "top"), [], "frame.top"),
        (("multipie68",), [0] * 19, "multipie68"),
        (("multipie68",), [None] + [0] * 25, "nulls"),
        (("multipie68",), [None] * 26, "nulls"),
        (("name",), "Bad Name", "name must match"),
        (("tracker_points",), True, "tracker_points"),
        (("extra",), 1, "unknown key"),
        (("stable",), KeyError, "missing key 'stable'"),
    ],
)
def test_bad_layouts_name_the_field_at_fault(layout, path, value, needle):
    with pytest.raises(InputError) as info:
        layout_from_dict(_broken(layout, path, value), "test")
    assert info.value.code == "bad_layout" and needle in info.value.message


def _face_mesh(layout, rng):
    """A synthetic 478-point mesh: random points with the frame points placed like a face."""
    mesh = rng.normal(scale=4.0, size=(layout.tracker_points, 3))
    frame = layout.frame
    mesh[frame["right"]] = np.array([-3.2, 0.0, 0.0]) + rng.normal(scale=0.3, size=(2, 3))
    mesh[frame["left"]] = np.array([3.2, 0.0, 0.0]) + rng.normal(scale=0.3, size=(2, 3))
    mesh[frame["top"]] = np.array([0.0, 6.0, 0.5]) + rng.normal(scale=0.3, size=(2, 3))
    mesh[frame["bottom"]] = np.array([0.0, -4.0, 2.0]) + rng.normal(scale=0.3, size=(2, 3))
    return mesh


def _rotation(yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (np.cos, np.sin))
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return rz @ rx @ ry


def test_normalised_points_do_not_move_when_the_head_turns_or_backs_away(layout):
    rng = np.random.default_rng(3)
    mesh = _face_mesh(layout, rng)
    moved = 0.4 * mesh @ _rotation(0.5, -0.3, 0.2).T + [120.0, -40.0, 7.0]
    still = normalise_mesh(np.stack([mesh, moved]), layout)
    np.testing.assert_allclose(still[1], still[0], atol=1e-9)


def test_normalised_points_move_when_a_feature_moves(layout):
    rng = np.random.default_rng(4)
    mesh = _face_mesh(layout, rng)
    opened = mesh.copy()
    chin = layout.feature_names.index("chin")
    opened[layout.features[chin], 1] -= 2.0
    before, after = normalise_mesh(np.stack([mesh, opened]), layout)
    moved = np.linalg.norm(after - before, axis=1)
    assert moved[chin] > 1.0 and np.delete(moved, chin).max() < 1e-9


def test_normalised_eye_span_is_the_layout_span(layout):
    rng = np.random.default_rng(5)
    mesh = 37.0 * _face_mesh(layout, rng)
    frame_points = np.concatenate([mesh[layout.frame["left"]], mesh[layout.frame["right"]]])
    extended = np.vstack([mesh, frame_points])  # a mesh may carry points after the layout's
    features = normalise_mesh(extended, layout)
    assert features.shape == (26, 3)
    # The eye centres are not features; map them through the same frame by hand.
    left = mesh[layout.frame["left"]].mean(axis=0)
    right = mesh[layout.frame["right"]].mean(axis=0)
    ratio = layout.span / np.linalg.norm(left - right)
    raw = mesh[layout.features]
    assert np.isclose(
        np.linalg.norm(features[0] - features[1]), ratio * np.linalg.norm(raw[0] - raw[1])
    )


def test_image_landmarks_become_isotropic_and_y_up():
    marks = np.array([[0.5, 0.25, -0.1]])
    np.testing.assert_allclose(image_to_mesh(marks, 640, 480), [[320.0, -120.0, 64.0]])


@pytest.mark.parametrize(
    ("mutate", "code"),
    [
        (lambda m: m[:380], "wrong_landmark_count"),
        (lambda m: np.where(np.arange(478)[:, None] == 5, np.nan, m), "non_finite"),
        (lambda m: np.zeros_like(m), "degenerate_face"),
    ],
)
def test_bad_meshes_are_refused_by_code(layout, mutate, code):
    mesh = _face_mesh(layout, np.random.default_rng(6))
    with pytest.raises(InputError) as info:
        normalise_mesh(mutate(mesh), layout)
    assert info.value.code == code


@pytest.mark.ict
def test_layout_points_land_on_icts_landmarks_on_a_real_tracked_face(layout, photo_mesh):
    """MediaPipe's mesh of a real photo, aligned onto ICT's neutral by the 24 features:
    each feature lands near its ICT landmark, and for the parts a smile does not move
    (brows, lids, nose, chin, eye corners) no other mesh point is much nearer to it (a
    wrong index - the other lid, the other side - would be centimetres off). The mesh is
    ``facecast perform``'s: FaceMesh's 468 points, the lids and irises the attention
    mesh's (its own nose wings land 1.10 cm from ICT's, FaceMesh's 0.95: measured)."""
    aligned, ict68 = photo_mesh["aligned"], photo_mesh["ict68"]
    k = layout.multipie_count  # the features with a Multi-PIE position (not the irises)
    multipie = np.asarray(layout.multipie68[:k])
    features = layout.features[:k]
    residual = np.linalg.norm(aligned[features] - ict68[multipie], axis=1)
    assert np.sqrt(np.mean(residual**2)) < 1.0  # cm, on a face that is not ICT's
    pairs = [
        (f, m)
        for f, m, name in zip(features, multipie, layout.feature_names[:k], strict=True)
        if "mouth" not in name and "lip" not in name
    ]
    eyes = layout.eyes
    pairs += [(eyes["right"]["outer"], 36), (eyes["right"]["inner"], 39)]
    pairs += [(eyes["left"]["inner"], 42), (eyes["left"]["outer"], 45)]
    for mesh_index, landmark in pairs:
        distance = np.linalg.norm(aligned[:468] - ict68[landmark], axis=1)
        assert distance[mesh_index] < 1.0, (mesh_index, landmark)
        assert distance[mesh_index] - distance.min() < 0.4, (mesh_index, landmark)


@pytest.fixture(scope="module")
def photo_mesh(layout, perform_python, tmp_path_factory):
    """The astronaut photo's mesh through ``facecast perform``'s tracker, aligned onto ICT's
    neutral 68 landmarks by the layout's features that have a Multi-PIE position."""
    from skimage import data as skimage_data

    from facecast.rig.pose import similarity_transform
    from facecast.rig.sources.ict import locate_ict

    archive = locate_ict()
    if archive is None:
        pytest.skip("needs ../shared/data/ict-facekit (or FACECAST_ICT)")
    with np.load(archive) as data:
        ict68 = data["neutral"][data["landmarks68"]].astype(np.float64)
    # MediaPipe runs in the perform venv (numpy < 2), never in this process.
    photo = [skimage_data.astronaut()]
    mesh = track_images(perform_python, photo, tmp_path_factory.mktemp("photo"))["meshes"][0]
    k = layout.multipie_count
    features, multipie = layout.features[:k], np.asarray(layout.multipie68[:k])
    rotation, scale, shift = similarity_transform(mesh[None, features], ict68[multipie], scale=True)
    return {"aligned": scale[0] * mesh @ rotation[0].T + shift[0], "ict68": ict68}


@pytest.mark.ict
def test_the_iris_features_lie_in_their_own_eyes_on_a_real_tracked_face(layout, photo_mesh):
    """The layout's last two features, MediaPipe's iris centres (``facecast perform``'s
    iris model): each lies inside its own eye's ICT landmarks - between the corners,
    between the lids - on a photo looking at the camera (the other eye is 6 cm away)."""
    aligned, ict68 = photo_mesh["aligned"], photo_mesh["ict68"]
    assert aligned.shape[0] == 478
    eyes = {"right_iris": range(36, 42), "left_iris": range(42, 48)}  # Multi-PIE, subject's
    for name, landmarks in eyes.items():
        iris = aligned[layout.features[layout.feature_names.index(name)]]
        eye = ict68[list(landmarks)]
        centre = eye.mean(axis=0)
        width = np.linalg.norm(eye[0] - eye[3])  # corner to corner
        assert np.linalg.norm(iris[:2] - centre[:2]) < 0.2 * width, name

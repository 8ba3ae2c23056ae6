"""The procedural demo: example set shape and character, performance, ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from facecast.rig.demo import (
    DEMO_EMOTIONS,
    DEMO_FEATURE_NAMES,
    DEMO_NAMES,
    DEMO_VISEMES,
    demo_activations,
    demo_animation,
    demo_example_set,
    demo_landmarks,
    demo_target_frames,
)
from facecast.rig.errors import InputError


@pytest.fixture(scope="module")
def example_set():
    return demo_example_set()


@pytest.fixture(scope="module")
def animation():
    return demo_animation(12.0, 60.0)


def _edges_shared_twice(faces: np.ndarray) -> bool:
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool((counts == 2).all())


def _nearest(vertices: np.ndarray, point: np.ndarray) -> int:
    return int(np.linalg.norm(vertices - point, axis=1).argmin())


def test_example_set_is_deterministic(example_set):
    again = demo_example_set()
    assert again.names == example_set.names
    np.testing.assert_array_equal(again.source_points, example_set.source_points)
    np.testing.assert_array_equal(again.target_vertices, example_set.target_vertices)
    np.testing.assert_array_equal(again.feature_indices, example_set.feature_indices)


def test_example_set_shapes_and_dtypes(example_set):
    m, k = len(DEMO_NAMES), len(DEMO_FEATURE_NAMES)
    assert example_set.names == DEMO_NAMES
    assert example_set.source_points.shape == (m, k, 3)
    assert example_set.source_points.dtype == np.float64
    assert example_set.source_vertices.shape[0] == m
    assert example_set.target_vertices.shape[0] == m
    assert example_set.feature_indices.shape == (k,)
    assert np.issubdtype(example_set.target_faces.dtype, np.integer)
    assert np.issubdtype(example_set.source_faces.dtype, np.integer)
    assert 15 <= k <= 25
    assert 2000 <= example_set.source_vertices.shape[1] <= 12000


def test_source_and_target_meshes_differ_in_size_and_topology(example_set):
    assert example_set.source_vertices.shape[1] != example_set.target_vertices.shape[1]
    assert example_set.source_faces.shape[0] != example_set.target_faces.shape[0]
    # A UV sphere has valence-4/6 grid vertices and two fans; an icosphere has valence 5/6.
    src_valence = np.bincount(example_set.source_faces.ravel())
    tgt_valence = np.bincount(example_set.target_faces.ravel())
    assert set(np.unique(src_valence)) != set(np.unique(tgt_valence))


def test_both_meshes_are_closed_surfaces(example_set):
    assert _edges_shared_twice(example_set.source_faces)
    assert _edges_shared_twice(example_set.target_faces)


def test_example_names_cover_emotions_and_visemes(example_set):
    assert example_set.names[0] == "neutral"
    emotions = {"happy", "sad", "surprise", "fear", "anger"}
    visemes = {"aa", "oo", "ee", "mbp", "fv"}
    assert emotions <= set(example_set.names) and emotions <= set(DEMO_EMOTIONS)
    assert visemes <= set(example_set.names) and visemes <= set(DEMO_VISEMES)


def test_feature_points_sit_on_their_landmarks(example_set):
    marks = demo_landmarks("source")
    neutral = example_set.source_vertices[0]
    for name, index in zip(DEMO_FEATURE_NAMES, example_set.feature_indices, strict=True):
        assert np.linalg.norm(neutral[index] - marks[name]) < 0.4, name
    assert len(set(example_set.feature_indices.tolist())) == len(DEMO_FEATURE_NAMES)


def test_examples_feature_displacements_are_well_separated(example_set):
    params = (example_set.source_points - example_set.source_points[0]).reshape(
        example_set.num_examples, -1
    )
    distances = np.linalg.norm(params[:, None] - params[None], axis=2)
    np.fill_diagonal(distances, np.inf)
    largest = np.linalg.norm(params, axis=1).max()
    assert distances.min() / largest > 0.1


def test_every_target_example_moves_the_target(example_set):
    deltas = example_set.target_vertices[1:] - example_set.target_vertices[0]
    assert (np.abs(deltas).max(axis=(1, 2)) > 0.3).all()


def test_target_expressions_are_not_a_scaled_copy_of_the_source(example_set):
    names = example_set.names
    src_corner = _nearest(
        example_set.source_vertices[0], demo_landmarks("source")["mouth_corner_l"]
    )
    tgt_corner = _nearest(
        example_set.target_vertices[0], demo_landmarks("target")["mouth_corner_l"]
    )

    def lift(vertices, index, name):
        return vertices[names.index(name), index, 1] - vertices[0, index, 1]

    happy = lift(example_set.target_vertices, tgt_corner, "happy") / lift(
        example_set.source_vertices, src_corner, "happy"
    )
    sad = lift(example_set.target_vertices, tgt_corner, "sad") / lift(
        example_set.source_vertices, src_corner, "sad"
    )
    assert happy > 0 and sad > 0  # same direction of motion: both smile, both frown
    assert happy / sad > 1.5  # the cartoon grins far more than it frowns, relatively


def test_target_ears_move_only_on_the_target(example_set):
    sad = example_set.names.index("sad")
    target_motion = np.linalg.norm(
        example_set.target_vertices[sad] - example_set.target_vertices[0], axis=1
    )
    ears = np.abs(example_set.target_vertices[0][:, 0]) > 8.5  # beyond the cartoon's cheeks
    assert target_motion[ears].max() > 1.0


def test_animation_is_at_least_ten_seconds_at_sixty_fps(animation, example_set):
    assert animation.fps == 60.0
    assert animation.points.shape == (720, len(DEMO_FEATURE_NAMES), 3)
    assert animation.points.shape[0] / animation.fps >= 10.0
    assert animation.source_vertices.shape == (720, example_set.source_vertices.shape[1], 3)
    assert animation.source_vertices.dtype == np.float32


def test_animation_points_are_the_feature_vertices_of_its_meshes(animation, example_set):
    np.testing.assert_allclose(
        animation.points,
        animation.source_vertices[:, example_set.feature_indices, :],
        atol=1e-5,
    )


def test_animation_moves_smoothly(animation):
    steps = np.linalg.norm(np.diff(animation.points, axis=0), axis=2)  # cm per frame
    excursion = np.linalg.norm(animation.points - animation.points[0], axis=2).max()
    assert excursion > 2.0
    assert steps.max() < 1.0  # no jumps: under 60 cm/s anywhere
    assert steps.max() < 0.2 * excursion
    jerk = np.linalg.norm(np.diff(animation.points, 2, axis=0), axis=2)
    assert jerk.max() < 0.6 * steps.max()  # a jump would give about twice the step


def test_animation_is_deterministic_and_seeded():
    first = demo_animation(2.0, 30.0, with_vertices=False)
    second = demo_animation(2.0, 30.0, with_vertices=False)
    other = demo_animation(2.0, 30.0, with_vertices=False, seed=8)
    np.testing.assert_array_equal(first.points, second.points)
    assert first.source_vertices is None
    assert not np.allclose(first.points, other.points)


def test_points_only_animation_matches_the_mesh_animation(animation):
    points_only = demo_animation(12.0, 60.0, with_vertices=False)
    np.testing.assert_allclose(points_only.points, animation.points, atol=1e-9)


def test_activations_mix_expressions_beyond_single_examples():
    act = demo_activations(12.0, 60.0)
    assert act.shape == (720, len(DEMO_NAMES))
    assert (act[:, 0] == 0).all()
    assert (act >= 0).all()
    assert (act[:, 1:].max(axis=0) > 0.5).all()  # every example takes part
    assert act.max() > 1.0 and act.max() <= 1.25  # slightly beyond the examples
    emotion_cols = [DEMO_NAMES.index(n) for n in DEMO_EMOTIONS]
    viseme_cols = [DEMO_NAMES.index(n) for n in DEMO_VISEMES]
    speaking_with_feeling = (act[:, emotion_cols].max(axis=1) > 0.3) & (
        act[:, viseme_cols].max(axis=1) > 0.3
    )
    assert speaking_with_feeling.mean() > 0.1
    assert np.abs(np.diff(act, axis=0)).max() < 0.3  # the fastest is a blink


def test_target_frames_reproduce_each_target_example(example_set):
    one_hot = np.eye(len(DEMO_NAMES))
    frames = demo_target_frames(one_hot)
    assert frames.dtype == np.float32
    np.testing.assert_allclose(frames, example_set.target_vertices, atol=1e-4)


def test_target_frames_follow_the_animation_frames():
    act = demo_activations(3.0, 20.0)
    frames = demo_target_frames(act)
    assert frames.shape == (60, demo_example_set().num_vertices, 3)
    moving = np.linalg.norm(frames - frames[0], axis=2).max(axis=1)
    assert moving.max() > 1.0


@settings(max_examples=15, deadline=None)
@given(arrays(np.float64, (3, len(DEMO_NAMES)), elements=st.floats(-0.5, 2.0)))
def test_target_frames_stay_finite_and_bounded(activations):
    frames = demo_target_frames(activations)
    assert np.isfinite(frames).all()
    assert np.abs(frames).max() < 40.0  # a 17 cm head never flies apart


@pytest.mark.parametrize(
    ("seconds", "fps", "code"),
    [
        (0.0, 60.0, "bad_demo_argument"),
        (float("nan"), 60.0, "bad_demo_argument"),
        (5.0, -1.0, "bad_demo_argument"),
        ("long", 60.0, "bad_demo_argument"),
        (3600.0, 60.0, "too_many_frames"),
    ],
)
def test_bad_durations_are_refused_with_a_code(seconds, fps, code):
    with pytest.raises(InputError) as info:
        demo_activations(seconds, fps)
    assert info.value.code == code


def test_mesh_animation_is_bounded_in_length():
    with pytest.raises(InputError) as info:
        demo_animation(120.0, 60.0)
    assert info.value.code == "too_many_frames"


@pytest.mark.parametrize(
    "activations",
    [np.zeros((4, 5)), np.full((2, len(DEMO_NAMES)), np.nan), "x", np.zeros((2, 2, 2))],
)
def test_bad_activations_are_refused_with_a_code(activations):
    with pytest.raises(InputError) as info:
        demo_target_frames(activations)
    assert info.value.code in {"bad_activations", "non_finite"}


def test_unknown_character_is_refused():
    with pytest.raises(InputError) as info:
        demo_landmarks("dragon")
    assert info.value.code == "bad_demo_argument"


def test_exact_demo_rig_does_not_warn_about_noise_amplification(example_set):
    import warnings

    from facecast.rig import fit

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rig = fit(example_set)

    assert rig.fit_report["warnings"] == []
    assert rig.fit_report["noise_tolerance"] > 1e-4 * rig.fit_report["feature_extent"]

"""The source rig: ARKit weights -> points, name matching, head rotation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from facecast.rig.errors import ExampleSetError, InputError
from facecast.rig.sources.source_rig import (
    ARKIT_NAMES,
    ARKIT_TO_ICT,
    NUM_ARKIT,
    SourceRig,
    arkit_from_ict,
    arkit_index,
    head_rotation,
)

from ._helpers import arkit_example_set


def test_arkit_table_lists_the_52_shapes_once_each():
    assert len(ARKIT_NAMES) == NUM_ARKIT == 52 == len(set(ARKIT_NAMES))
    assert set(ARKIT_TO_ICT) == set(ARKIT_NAMES)


def test_ict_halves_are_summed_into_one_arkit_shape_and_missing_parts_are_told():
    ict_names = sorted({part for parts in ARKIT_TO_ICT.values() for part in parts})
    rng = np.random.default_rng(3)
    neutral = rng.normal(size=(4, 3))
    shapes = neutral + rng.normal(size=(len(ict_names), 4, 3))
    at = {name: i for i, name in enumerate(ict_names)}

    names, meshes = arkit_from_ict(ict_names, neutral, shapes)

    assert names[0] == "neutral" and "tongueOut" not in names  # no ICT shape for it
    assert names[1:] == tuple(n for n in ARKIT_NAMES if ARKIT_TO_ICT[n])
    halves = ARKIT_TO_ICT["cheekPuff"]
    assert len(halves) == 2
    expected = neutral + sum(shapes[at[p]] - neutral for p in halves)
    np.testing.assert_array_equal(meshes[names.index("cheekPuff")], expected)
    np.testing.assert_array_equal(meshes[names.index("jawOpen")], shapes[at["jawOpen"]])
    without = [n for n in ict_names if n != halves[0]]
    kept = [at[n] for n in without]
    lenient, _ = arkit_from_ict(without, neutral, shapes[kept])
    assert "cheekPuff" not in lenient and "jawOpen" in lenient
    with pytest.raises(ExampleSetError, match=f"no ICT shape '{halves[0]}' \\(for cheekPuff\\)"):
        arkit_from_ict(without, neutral, shapes[kept], strict=True)


def test_names_match_case_insensitively_and_through_ict_spelling(source_rig):
    shapes = dict(zip(ARKIT_NAMES, source_rig.shapes, strict=True))
    assert shapes["eyeBlinkLeft"] == ("eyeBlinkLeft",)
    assert shapes["jawOpen"] == ("JawOpen",)
    assert shapes["mouthSmileLeft"] == ("mouthSmile_L",)
    assert shapes["browInnerUp"] == ("browInnerUp_L", "browInnerUp_R")
    assert "tongueOut" in source_rig.missing and "eyeBlinkLeft" not in source_rig.missing


def test_zero_weights_give_the_neutral(example_set, source_rig):
    assert np.allclose(source_rig.points(np.zeros(NUM_ARKIT)), example_set.source_points[0])


def test_unit_weight_gives_that_example(example_set, source_rig):
    w = np.zeros(NUM_ARKIT)
    w[arkit_index("JAWOPEN")] = 1.0
    assert np.allclose(source_rig.points(w), example_set.source_points[2])


def test_split_shape_weight_drives_both_halves(example_set, source_rig):
    w = np.zeros(NUM_ARKIT)
    w[arkit_index("browInnerUp")] = 0.5
    neutral = example_set.source_points[0]
    expected = (
        neutral
        + 0.5 * (example_set.source_points[4] - neutral)
        + 0.5 * (example_set.source_points[5] - neutral)
    )
    assert np.allclose(source_rig.points(w), expected)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, (3, NUM_ARKIT), elements=st.floats(-2, 2)))
def test_points_are_linear_in_the_weights_and_batched_like_single_frames(weights):
    rig = SourceRig.from_example_set(arkit_example_set())
    batch = rig.points(weights)
    singles = np.stack([rig.points(w) for w in weights])
    assert np.allclose(batch, singles)
    mixed = rig.points(weights[0] + weights[1]) - rig.neutral
    assert np.allclose(mixed, (batch[0] - rig.neutral) + (batch[1] - rig.neutral))


def test_head_angles_rotate_rigidly_about_the_neutral_centroid(source_rig):
    w = np.zeros(NUM_ARKIT)
    w[0] = 0.7
    still = source_rig.points(w)
    turned = source_rig.points(w, head=[0.3, -0.2, 0.1])
    centroid = source_rig.neutral.mean(axis=0)
    # Pairwise distances are kept and the neutral's centroid is the pivot.
    d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)  # noqa: E731
    assert np.allclose(d(still), d(turned))
    r = head_rotation(np.array([0.3, -0.2, 0.1]))
    assert np.allclose(turned, (still - centroid) @ r.T + centroid)


def test_head_rotation_yaw_turns_about_the_vertical_axis():
    r = head_rotation(np.array([np.pi / 2, 0.0, 0.0]))
    assert np.allclose(r @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    assert np.allclose(r @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0])


def test_wrong_weight_count_and_nan_are_input_errors(source_rig):
    with pytest.raises(InputError) as count:
        source_rig.points(np.zeros(51))
    with pytest.raises(InputError) as nan:
        source_rig.points(np.full(NUM_ARKIT, np.nan))
    assert (count.value.code, nan.value.code) == ("bad_weights", "non_finite")


def test_a_set_without_arkit_names_is_refused():
    es = arkit_example_set()
    from facecast.rig import ExampleSet

    other = ExampleSet(
        ("neutral", "a", "b", "c", "d", "e"), es.source_points, es.target_vertices, es.target_faces
    )
    with pytest.raises(ExampleSetError) as info:
        SourceRig.from_example_set(other)
    assert info.value.code == "no_arkit_shapes"


def test_names_differing_only_in_case_are_ambiguous():
    es = arkit_example_set()
    from facecast.rig import ExampleSet

    clash = ExampleSet(
        ("neutral", "jawOpen", "JawOpen", "c", "d", "e"),
        es.source_points,
        es.target_vertices,
        es.target_faces,
    )
    with pytest.raises(ExampleSetError) as info:
        SourceRig.from_example_set(clash)
    assert info.value.code == "ambiguous_shape_name"

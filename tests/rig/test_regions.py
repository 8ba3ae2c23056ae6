"""Region rigs: each region follows its own feature points, and the regions join without a seam."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig import FitError, rig_from_bytes
from facecast.rig.regions import Region, fit_regions, split_masks

from .test_fit import make_set

UPPER, LOWER = [0, 1, 2], [3, 4, 5]


@pytest.fixture(scope="module")
def example_set():
    return make_set(m=9, k=6, v=60, seed=11)


@pytest.fixture(scope="module")
def masks(example_set):
    return split_masks(example_set.target_neutral, axis=1, at=0.0, width=1.5)


@pytest.fixture(scope="module")
def rig(example_set, masks):
    lower, upper = masks
    return fit_regions(
        example_set,
        [
            Region("upper", UPPER, ["e1", "e2", "e3", "e4"], upper),
            Region("lower", LOWER, ["e5", "e6", "e7", "e8"], lower),
        ],
    )


def _frame(example_set, upper_example, lower_example):
    frame = example_set.source_neutral.copy()
    frame[UPPER] = example_set.source_points[upper_example][UPPER]
    frame[LOWER] = example_set.source_points[lower_example][LOWER]
    return frame


def test_split_masks_are_smooth_and_sum_to_one(example_set, masks):
    lower, upper = masks
    np.testing.assert_allclose(lower + upper, 1.0)
    y = example_set.target_neutral[:, 1]
    assert upper[y > 1.0].min() == 1.0 and upper[y < -1.0].max() == 0.0


def test_regions_combine_independent_expressions(example_set, masks, rig):
    lower, upper = masks
    frame = _frame(example_set, 2, 6)
    deltas = example_set.target_vertices - example_set.target_neutral
    expected = example_set.target_neutral + upper[:, None] * deltas[2] + lower[:, None] * deltas[6]
    np.testing.assert_allclose(rig.clone(frame), expected, atol=1e-5)


def test_weights_name_region_and_example_and_sum_to_one(example_set, rig):
    assert rig.names[:2] == ("neutral", "upper.e1")
    weights = rig.weights(_frame(example_set, 3, 7))
    assert weights[rig.names.index("upper.e3")] == pytest.approx(1.0)
    assert weights[rig.names.index("lower.e7")] == pytest.approx(1.0)
    assert weights.sum() == pytest.approx(1.0)


def test_an_expression_in_every_region_has_no_seam(example_set, masks):
    lower, upper = masks
    rig = fit_regions(
        example_set,
        [Region("upper", UPPER, ["e1", "e2"], upper), Region("lower", LOWER, ["e1", "e3"], lower)],
    )
    np.testing.assert_allclose(
        rig.clone(example_set.source_points[1]), example_set.target_vertices[1], atol=1e-5
    )


def test_region_rig_round_trips_through_the_rig_file(example_set, rig):
    loaded = rig_from_bytes(rig.to_bytes())
    frames = example_set.source_points + 0.05
    np.testing.assert_array_equal(loaded.weights(frames), rig.weights(frames))
    assert loaded.summary()["regions"] == ["upper", "lower"]


def test_region_with_unknown_example_is_refused(example_set, masks):
    with pytest.raises(FitError, match="'nope'"):
        fit_regions(example_set, [Region("upper", UPPER, ["nope"], masks[1])])


def test_region_mask_of_wrong_length_is_refused(example_set):
    with pytest.raises(FitError, match="vertex_mask"):
        fit_regions(example_set, [Region("upper", UPPER, ["e1"], np.ones(3))])

"""Refitting a rig on a performer's own source examples, and the robust capture average."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig import ExampleSet, fit
from facecast.rig.errors import ExampleSetError, InputError
from facecast.rig.retarget import fit_performer, target_examples
from facecast.rig.sources.capture import robust_example

NAMES = ("neutral", "smile", "frown", "jawOpen")


@pytest.fixture(scope="module")
def character():
    rng = np.random.default_rng(0)
    m, k, v = len(NAMES), 6, 12
    source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.4, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, v, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, v, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(v - 2)])
    example_set = ExampleSet(NAMES, source, target, faces)
    return example_set, fit(example_set)


def _performer(k: int = 6, seed: int = 9) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(k, 3))
    return {
        name: neutral + (rng.normal(scale=0.5, size=(k, 3)) if name != "neutral" else 0.0)
        for name in NAMES
    }


def test_target_examples_are_rebuilt_from_the_blend_basis(character):
    example_set, rig = character
    np.testing.assert_allclose(target_examples(rig), example_set.target_vertices, atol=1e-6)


def test_performer_rig_is_cardinal_on_the_captured_points(character):
    _, rig = character
    points = _performer()
    mine = fit_performer(rig, points)
    weights = mine.weights(np.stack([points[n] for n in NAMES]))
    np.testing.assert_allclose(weights, np.eye(len(NAMES)), atol=1e-9)


def test_points_after_the_characters_are_the_performers_own_and_fitted_too(character):
    """A later layout appends points (the iris centres after the lids): a capture of more
    points than the character's fits a rig of the capture's count, its first K the
    character's - here the appended points alone tell the smile from the neutral."""
    _, rig = character
    points = {n: np.vstack([p, p[:2] + 0.1]) for n, p in _performer().items()}
    points["smile"] = points["neutral"].copy()
    points["smile"][6:] += [0.5, 0.0, 0.0]
    mine = fit_performer(rig, points)
    assert mine.num_points == 8 and rig.num_points == 6
    weights = mine.weights(np.stack([points[n] for n in NAMES]))
    np.testing.assert_allclose(weights, np.eye(len(NAMES)), atol=1e-9)


def test_noise_bounds_the_weights_and_is_recorded(character):
    _, rig = character
    mine = fit_performer(rig, _performer(), noise=0.02)
    assert mine.summary()["noise"] == 0.02 and mine.summary()["clamp"] == "unit"


def test_skipped_expressions_are_left_out_in_the_rigs_order(character):
    _, rig = character
    points = _performer()
    del points["frown"]
    mine = fit_performer(rig, dict(reversed(list(points.items()))))
    assert mine.names == ("neutral", "smile", "jawOpen")


@pytest.mark.parametrize(
    ("change", "code"),
    [
        (lambda p: p.pop("neutral"), "no_neutral"),
        (lambda p: p.update(wink=p["smile"]), "unknown_expression"),
        (lambda p: p.update(smile=p["smile"][:5]), "wrong_point_count"),
        (lambda p: p.update(smile=np.vstack([p["smile"], p["smile"][:1]])), "wrong_point_count"),
        (lambda p: p.update(smile=np.full((6, 3), np.nan)), "non_finite"),
        (lambda p: [p.pop(n) for n in NAMES[1:]], "too_few_examples"),
    ],
)
def test_bad_captures_are_refused_by_code(character, change, code):
    _, rig = character
    points = _performer()
    change(points)
    with pytest.raises(InputError) as info:
        fit_performer(rig, points)
    assert info.value.code == code


def test_a_capture_whose_neutral_has_no_extent_is_refused(character):
    # Before: fitted and stored, a rig refusing every frame but its neutral (issue 25).
    _, rig = character
    points = _performer()
    points["neutral"] = np.full((6, 3), 0.3)
    with pytest.raises(ExampleSetError) as info:
        fit_performer(rig, points)
    assert info.value.code == "degenerate_neutral"


def test_robust_example_drops_a_blink_and_measures_the_spread():
    rng = np.random.default_rng(1)
    held = rng.normal(size=(20, 3))
    frames = held + rng.normal(scale=0.01, size=(40, 20, 3))
    frames[7] += 2.0  # a blink or a tracking slip
    points, spread, kept = robust_example(frames)
    assert not kept[7] and kept.sum() == 39
    np.testing.assert_allclose(points, held, atol=0.01)
    assert 0.008 < spread < 0.012


def test_robust_example_refuses_too_few_frames():
    with pytest.raises(InputError) as info:
        robust_example(np.zeros((2, 20, 3)))
    assert info.value.code == "wrong_point_count"

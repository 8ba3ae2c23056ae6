"""The fit defaults of a character paired with the generic ARKit set: live-ready rigs."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facecast.rig import fit
from facecast.rig.characters.character_examples import character_fit_options
from facecast.rig.characters.generic import (
    CHARACTER_FIT_DEFAULTS,
    GAZE_SHAPES,
    PART_COMPOSITIONS,
    PRESET_CHECK_ORDER,
    VRM_COMPOSITIONS,
    composed_captures,
    generic_sources,
    is_gaze,
)
from facecast.rig.examples import ExampleSet


def test_no_noise_given_takes_the_live_defaults_a_given_noise_keeps_fits_bound():
    assert character_fit_options() == dict(CHARACTER_FIT_DEFAULTS)
    assert character_fit_options({"noise": None, "clamp": None, "kernel": "gaussian"}) == {
        **CHARACTER_FIT_DEFAULTS,
        "kernel": "gaussian",
    }
    # A clamp alone is the uploader's; the noise is still the default.
    assert character_fit_options({"clamp": "nonneg"}) == {
        "noise": CHARACTER_FIT_DEFAULTS["noise"],
        "clamp": "nonneg",
    }
    # A given noise (0 too: exact interpolation, the thesis's) is taken as it is.
    assert character_fit_options({"noise": 0.0}) == {"noise": 0.0}
    assert character_fit_options({"noise": 0.1, "clamp": "none"}) == {"noise": 0.1, "clamp": "none"}


def _mixes(names, points, frames: int = 200, seed: int = 0):
    """Frames mixing three random expressions each (weights in [0, 1]) and their weights."""
    rng = np.random.default_rng(seed)
    weights = np.zeros((frames, len(names)))
    for row in weights:
        row[rng.choice(np.arange(1, len(names)), 3, replace=False)] = rng.uniform(0, 1, 3)
    mixed = points[0] + np.einsum("fm,mkd->fkd", weights[:, 1:], points[1:] - points[0])
    return mixed, weights


#: Exact interpolation (noise 0) of the shipped set amplifies 0.2 mm of noise into weights
#: 0.26 RMS off (noise gain 98; 1,099 and 2.18 on the 24 exact landmarks before the eyes
#: were taken as tracked, option (z)); the defaults keep them 0.07 off (gain 12).
@pytest.mark.parametrize(
    ("options", "gain", "error"),
    [({"noise": 0.0}, (50, np.inf), (0.2, np.inf)), (None, (0, 20), (0, 0.15))],
)
def test_the_defaults_keep_tracker_noise_out_of_the_weights(options, gain, error):
    generic = generic_sources()
    points = generic.points
    examples = ExampleSet(
        names=generic.names,
        source_points=points,
        target_vertices=points.copy(),  # the weights depend on the source side alone
        target_faces=np.array([[0, 1, 2]]),
        stable_points=generic.stable_points,
    )
    mixed, truth = _mixes(generic.names, points)
    noisy = mixed + np.random.default_rng(1).normal(0.0, 0.02, mixed.shape)  # 0.2 mm

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact fit's noise-gain advice: the point here
        rig = fit(examples, **character_fit_options(options))
    weights = rig.weights(noisy)[:, 1:]

    rms = float(np.sqrt(np.mean((weights - truth[:, 1:]) ** 2)))
    assert gain[0] < rig.fit_report["noise_gain"] < gain[1]
    assert error[0] <= rms < error[1], rms
    if options is None:  # bounded to [0, 1]: no wild weights reach a character
        assert weights.min() >= 0.0 and weights.max() <= 1.0 + 1e-9


def test_presets_not_captured_are_composed_from_the_performers_own_shapes():
    rng = np.random.default_rng(2)
    neutral = rng.normal(size=(20, 3))
    captured = {"neutral": neutral}
    for shape in ("jawOpen", "mouthLowerDownLeft", "mouthLowerDownRight", "eyeBlinkLeft"):
        captured[shape] = neutral + rng.normal(scale=0.3, size=(20, 3))
    captured["happy"] = neutral + 1.0  # captured itself: kept as the performer made it
    wanted = ("neutral", "aa", "happy", "ou", "blinkLeft", "sad")

    composed = composed_captures(wanted, captured)

    assert sorted(composed) == ["aa", "blinkLeft"]  # ou and sad need shapes not captured
    expected = neutral + sum(w * (captured[s] - neutral) for s, w in VRM_COMPOSITIONS["aa"].items())
    np.testing.assert_allclose(composed["aa"], expected)
    # blinkLeft is eyeBlinkLeft: composed for a rig without it, left out for one with it.
    np.testing.assert_array_equal(composed["blinkLeft"], captured["eyeBlinkLeft"])
    assert "blinkLeft" not in composed_captures((*wanted, "eyeBlinkLeft"), captured)
    assert composed_captures(wanted, {k: v for k, v in captured.items() if k != "neutral"}) == {}


def test_every_composed_preset_is_checked_and_gaze_is_the_eight_look_shapes():
    assert sorted(PRESET_CHECK_ORDER) == sorted({**VRM_COMPOSITIONS, **PART_COMPOSITIONS})
    generic = generic_sources()
    assert set(GAZE_SHAPES) == {n for n in generic.names if n.startswith("eyeLook")}
    assert len(GAZE_SHAPES) == 8
    # Gaze: the eight shapes and the presets composed of them, nothing else.
    gaze = {n for n in (*generic.names, *PRESET_CHECK_ORDER) if is_gaze(n)}
    assert gaze == {*GAZE_SHAPES, "lookUp", "lookDown", "lookLeft", "lookRight"}


def test_the_default_noise_keeps_the_generic_sets_own_poses_at_full_strength():
    # The generic set's own exact poses, gaze unpaired as characters pair it: a closed eye,
    # an open jaw and a smile reach their shapes (docs/characters.md "Full strength").
    generic = generic_sources()
    keep = [i for i, n in enumerate(generic.names) if n not in GAZE_SHAPES]
    names = tuple(generic.names[i] for i in keep)
    points = generic.points[keep]
    examples = ExampleSet(names, points, points.copy(), np.array([[0, 1, 2]]))
    rig = fit(examples, **character_fit_options())
    neutral = points[0]

    def weight(shapes: tuple[str, ...]) -> np.ndarray:
        pose = neutral + sum(points[names.index(s)] - neutral for s in shapes)
        return rig.weights(pose)[[names.index(s) for s in shapes]]

    assert weight(("eyeBlinkLeft", "eyeBlinkRight")).min() >= 0.9
    assert weight(("jawOpen",)).min() >= 0.9
    assert weight(("mouthSmileLeft", "mouthSmileRight")).min() >= 0.8
    assert np.abs(rig.weights(neutral)[1:]).max() <= 0.03

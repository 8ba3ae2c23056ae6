"""The demo performance on the generic ARKit set, and the generic set as a source rig."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facecast.rig import fit
from facecast.rig.characters.character import character_example_set, load_character
from facecast.rig.characters.character_examples import character_fit_options
from facecast.rig.characters.expression_names import ARKIT_NAMES
from facecast.rig.characters.generic import generic_sources
from facecast.rig.demo import (
    DEMO_NAMES,
    arkit_demo_animation,
    arkit_demo_weights,
    demo_activations,
    demo_example_set,
    performance_for,
)
from facecast.rig.errors import ExampleSetError
from facecast.rig.sources.loading import load_source_animation
from facecast.rig.sources.source_rig import generic_source_rig, load_source_rig

from ..viewer._character import build_character

GENERIC_NPZ = Path(__file__).parents[2] / "rig" / "characters" / "generic_arkit" / "points.npz"
TAKE = Path(__file__).parents[1] / "data" / "livelink" / "llv_dao.csv"


@pytest.fixture(scope="module")
def character_rig():
    """The tests' small VRM 1.0 character, paired with the generic set and fitted with
    the upload's live defaults: what ``PUT /v1/characters`` stores."""
    character = load_character(build_character("vrm1").glb, label="face.vrm")
    example_set, _ = character_example_set(character)
    return fit(example_set, **character_fit_options({}))


def test_generic_source_rig_is_the_generic_set_under_arkit_names():
    generic = generic_sources()
    source_rig = generic_source_rig()
    weights = np.zeros(len(ARKIT_NAMES))
    weights[ARKIT_NAMES.index("jawOpen")] = 1.0

    np.testing.assert_array_equal(source_rig.neutral, generic.points[0])
    np.testing.assert_allclose(source_rig.points(weights), generic.source_points("jawOpen"))
    assert source_rig.missing == ("tongueOut",)


@pytest.mark.parametrize("spec", ["generic", str(GENERIC_NPZ)])
def test_load_source_rig_takes_the_word_generic_and_the_shipped_file(spec):
    loaded = load_source_rig(spec)

    np.testing.assert_array_equal(loaded.deltas, generic_source_rig().deltas)


def test_a_generic_layout_npz_whose_first_name_is_not_neutral_is_refused(tmp_path):
    generic = generic_sources()
    bad = tmp_path / "points.npz"
    np.savez(
        bad,
        names=np.array(["jawOpen", *generic.names[1:]]),
        points=generic.points,
        landmarks68=generic.landmarks68,
        stable_points=generic.stable_points,
    )

    with pytest.raises(ExampleSetError, match="neutral"):
        load_source_rig(bad)


def test_the_bundled_livelink_take_loads_on_the_shipped_generic_file():
    animation = load_source_animation(TAKE, source_rig=str(GENERIC_NPZ), num_points=24)

    assert animation.points.shape == (180, 24, 3)
    assert np.isfinite(animation.points).all()


def test_arkit_demo_weights_follow_the_demo_activations_within_unit_bounds():
    weights = arkit_demo_weights(12.0, 60.0)
    activations = demo_activations(12.0, 60.0)
    blink = activations[:, DEMO_NAMES.index("blink")]

    assert weights.shape == (720, len(ARKIT_NAMES))
    assert weights.min() >= 0.0 and weights.max() <= 1.0
    # Every blink of the demo closes both eyes.
    left = weights[:, ARKIT_NAMES.index("eyeBlinkLeft")]
    assert left[blink > 0.95].min() >= 0.95


def test_the_arkit_demo_is_on_the_generic_sets_points():
    animation = arkit_demo_animation(2.0, 30.0)

    assert animation.points.shape == (60, 26, 3)
    assert animation.fps == 30.0
    assert performance_for(generic_sources().points[0]) == "generic"
    assert performance_for(demo_example_set().source_points[0]) == "demo"
    assert performance_for(generic_sources().points[0] + 0.5) is None


def test_a_character_rig_plays_the_arkit_demo_with_plausible_weights(character_rig):
    """Each expression the character has moves with the performance's own weight for it."""
    truth = arkit_demo_weights()
    weights = character_rig.weights(arkit_demo_animation().points)

    assert performance_for(character_rig.model.source_neutral) == "generic"
    for name in ("jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp"):
        got = weights[:, character_rig.names.index(name)]
        want = truth[:, ARKIT_NAMES.index(name)]
        assert np.corrcoef(got, want)[0, 1] > 0.8, name
        assert got.max() > 0.8, name  # at full strength where the performance is
        # Near rest where it is not (this small face has 4 shapes: other mouth motion
        # leaks into its smile, 0.16 on average).
        assert got[want < 0.02].mean() < 0.25, name

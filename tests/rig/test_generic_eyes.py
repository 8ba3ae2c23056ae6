"""``with_tracked_eyes``: the generic set's exact points with its lids and irises as the
tracker sees the same face (scripts/make_generic_sources.py; README, option (z))."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig.characters.generic import generic_sources
from facecast.rig.sources.ict_arkit import with_tracked_eyes
from facecast.rig.sources.layouts import load_layout


def _turn(points: np.ndarray, degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    about_z = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1]])
    return points @ about_z.T


def test_the_eyes_take_the_tracked_displacements_in_the_exact_frame_and_the_rest_stays():
    rng = np.random.default_rng(0)
    exact = rng.normal(scale=3.0, size=(1, 6, 3)).repeat(4, axis=0)
    exact[1:] += rng.normal(scale=0.3, size=(3, 6, 3))
    eyes = [1, 4]
    # The tracker's own view of the face: its eyes move otherwise, two points more (the
    # irises), and all of it in its own frame (turned, scaled by 0.9, shifted).
    seen = np.concatenate([exact, rng.normal(size=(1, 2, 3)).repeat(4, axis=0)], axis=1)
    seen[1:, eyes] += rng.normal(scale=0.2, size=(3, 2, 3))
    seen[1:, 6:] += rng.normal(scale=0.2, size=(3, 2, 3))
    tracked = 0.9 * _turn(seen, 30.0) + np.array([5.0, -2.0, 1.0])

    out = with_tracked_eyes(exact, tracked, eyes)

    rest = [0, 2, 3, 5]
    assert out.shape == (4, 8, 3)
    np.testing.assert_array_equal(out[:, rest], exact[:, rest])
    np.testing.assert_allclose(
        out[:, eyes] - out[:1, eyes], seen[:, eyes] - seen[:1, eyes], atol=1e-9
    )
    np.testing.assert_allclose(out[0, eyes], exact[0, eyes], atol=1e-12)
    np.testing.assert_allclose(out[:, 6:], seen[:, 6:], atol=1e-9)  # back in the exact frame


def test_fewer_tracked_points_than_exact_ones_are_refused():
    with pytest.raises(ValueError, match="tracked"):
        with_tracked_eyes(np.zeros((2, 5, 3)), np.zeros((2, 4, 3)), [1])


def test_the_shipped_set_has_the_layouts_points_its_lids_and_irises_as_tracked():
    """The shipped set: ICT's 24 landmarks, their neutral unchanged (rigs fitted before it
    grew are still the generic set's), with the layout's 26 points."""
    generic = generic_sources()
    names = load_layout().feature_names
    assert generic.points.shape[1] == len(names) == 26
    lids = [i for i, n in enumerate(names[:24]) if "_lid" in n]
    assert len(lids) == 8
    # A blink closes each eye's lids: the upper lid comes down towards the lower.
    blink = generic.points[generic.names.index("eyeBlinkLeft")] - generic.points[0]
    upper, lower = names.index("left_upper_lid"), names.index("left_lower_lid")
    assert blink[upper, 1] < -0.2 and blink[upper, 1] < blink[lower, 1]
    # A look towards the nose moves that eye's iris nasally, 4-6 mm, and the other barely:
    # the tracker follows a turn to the nose (a turn to the ear it hardly sees: 1 mm the
    # wrong way, tests/perform/test_iris.py), and the set is the tracker's view of it.
    for eye, nasal in (("Left", -1.0), ("Right", 1.0)):
        turn = generic.points[generic.names.index(f"eyeLookIn{eye}")] - generic.points[0]
        own, other = (
            names.index(f"{eye.lower()}_iris"),
            names.index(f"{'right' if eye == 'Left' else 'left'}_iris"),
        )
        assert nasal * turn[own, 0] > 0.3 and abs(turn[other, 0]) < 0.1, (eye, turn[[own, other]])

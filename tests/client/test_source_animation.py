"""The SOURCE loading that ``clone``, ``stream`` and ``publish`` share."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.commands._animation import load_animation
from facecast.cli.errors import CommandError


def _no_indices():
    raise AssertionError("feature indices asked for")


def test_demo_source_never_asks_for_feature_indices():
    animation = load_animation("demo", num_points=21, feature_indices=_no_indices, seconds=0.5)

    assert animation.points.shape[1:] == (21, 3)


def test_missing_source_is_a_command_error_before_feature_indices(tmp_path):
    with pytest.raises(CommandError, match=r"nope\.npy: no such file or folder"):
        load_animation(str(tmp_path / "nope.npy"), num_points=3, feature_indices=_no_indices)


def test_points_file_loads_with_the_rigs_feature_indices(tmp_path):
    path = tmp_path / "points.npy"
    np.save(path, np.zeros((4, 3, 3)))
    asked = []

    animation = load_animation(
        str(path), num_points=3, feature_indices=lambda: asked.append(1) or None
    )

    assert animation.points.shape == (4, 3, 3)
    assert asked == [1]


def test_point_count_mismatch_names_who_expects_how_many():
    expected = (
        r"^demo: the demo performance comes on the demo rig's 21 points and on the generic "
        r"ARKit set's 26 \(characters uploaded as files\), rig 'x' needs 5: give the rig's own "
        r"source animation instead$"
    )
    with pytest.raises(CommandError, match=expected):
        load_animation(
            "demo",
            num_points=5,
            feature_indices=_no_indices,
            seconds=0.5,
            expected_by="rig 'x' needs",
        )

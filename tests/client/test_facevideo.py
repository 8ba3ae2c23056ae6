"""The webcam benchmark's camera video: an ICT head on grey, its parts told apart, as Y4M."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.bench.facevideo import BACKGROUND, head_scene, render_frames, write_video
from facecast.cli.y4m import open_y4m
from facecast.rig.evaluation.webcam import ict_performer
from facecast.rig.sources.ict import ict_regions, locate_ict

ARCHIVE = locate_ict()
pytestmark = [
    pytest.mark.ict,
    pytest.mark.skipif(
        ARCHIVE is None, reason="ICT-FaceKit not found (../shared/data/ict-facekit)"
    ),
]
GREY = round(255 * BACKGROUND[0])


@pytest.fixture(scope="module")
def scene():
    performer = ict_performer(ARCHIVE)
    regions, landmarks68 = ict_regions(ARCHIVE)
    return performer, head_scene(performer, regions, landmarks68)


def _activations(performer, **weights) -> np.ndarray:
    act = np.zeros((1, len(performer.names)))
    for name, value in weights.items():
        act[0, performer.names.index(name)] = value
    return act


def _frame(scene, sway=0.0, **weights) -> np.ndarray:
    performer, head = scene
    act = _activations(performer, **weights)
    return next(render_frames(head, performer, act, fps=30.0, sway_degrees=sway))


def test_the_head_stands_out_of_a_grey_background(scene):
    image = _frame(scene)

    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    background = (image == GREY).all(axis=2)
    assert background[:, :60].all() and background[:, -60:].all()  # the sides are grey
    face = image[170:300, 270:370]  # brows to lips (the landmarks lie in x 254-387, y 175-346)
    assert (face != GREY).any(axis=2).mean() > 0.99  # the face fills the middle
    assert face[..., 0].mean() > face[..., 2].mean() + 30  # skin: red above blue


def test_the_eyes_show_dark_pupils_on_white(scene):
    image = _frame(scene).astype(int)
    eyes = image[195:225, 260:380].sum(axis=2)  # the band of the eyes

    assert eyes.min() < 60  # pupils (and lashes)
    assert eyes.max() > 600  # the white of the eyes


def test_an_open_jaw_shows_the_mouth_inside(scene):
    closed = _frame(scene).astype(int)
    opened = _frame(scene, jawOpen=1.0).astype(int)
    mouth = (slice(280, 340), slice(290, 350))

    changed = np.abs(opened[mouth] - closed[mouth]).sum(axis=2) > 60
    assert changed.mean() > 0.1
    assert opened[mouth].sum(axis=2).min() < closed[mouth].sum(axis=2).min()  # darker inside


def test_frames_are_deterministic_and_the_sway_moves_the_head(scene):
    performer, head = scene
    act = np.repeat(_activations(performer), 3, axis=0)

    first = list(render_frames(head, performer, act, fps=2.0, sway_degrees=2.0))
    again = list(render_frames(head, performer, act, fps=2.0, sway_degrees=2.0))

    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    assert not np.array_equal(first[0], first[2])


def test_a_clip_is_written_as_y4m_at_its_rate(scene, tmp_path):
    performer, head = scene
    act = np.repeat(_activations(performer), 2, axis=0)

    path = write_video(tmp_path / "clip.y4m", head, performer, act, fps=30.0, progress=False)

    video = open_y4m(path)
    assert (video.width, video.height, video.num_frames, video.fps) == (640, 480, 2, 30.0)


def _iris_shift(still: np.ndarray, turned: np.ndarray, columns: slice) -> np.ndarray:
    """(dy, dx) pixels from where the dark iris left to where it arrived, in one eye's box."""
    change = turned[195:225, columns].astype(int).sum(axis=2) - still[195:225, columns].sum(axis=2)
    arrived, left = np.argwhere(change < -150), np.argwhere(change > 150)
    assert len(arrived) > 10 and len(left) > 10  # the iris moved, not a pixel's noise
    shift: np.ndarray = arrived.mean(axis=0) - left.mean(axis=0)
    return shift


@pytest.mark.parametrize(
    ("weights", "direction"),
    [
        ({"eyeLookUpLeft": 0.5, "eyeLookUpRight": 0.5}, (-1, 0)),  # image y grows downwards
        ({"eyeLookOutLeft": 0.5, "eyeLookInRight": 0.5}, (0, 1)),  # the subject's left: +x
        ({"eyeLookInLeft": 0.5, "eyeLookOutRight": 0.5}, (0, -1)),
    ],
)
def test_a_gaze_turns_both_irises_its_way(scene, weights, direction):
    performer, head = scene
    act = _activations(performer, **weights)
    still = next(render_frames(head, performer, act, fps=30.0, sway_degrees=0.0))
    turned = next(render_frames(head, performer, act, fps=30.0, sway_degrees=0.0,
                                gaze_degrees=20.0))  # fmt: skip

    for eye in (slice(250, 320), slice(320, 390)):  # the subject's right eye, then left
        shift = _iris_shift(still, turned, eye)
        along = shift @ np.asarray(direction, dtype=float)
        assert along > 2.0  # pixels, the weights' way
        assert along > 2.0 * abs(shift @ np.asarray(direction[::-1], dtype=float))  # not across


def test_a_look_up_and_down_at_once_leave_the_irises_where_they_were(scene):
    # (a look down alone hides the iris's motion under the lowered lid: this is its check)
    performer, head = scene
    act = _activations(performer, eyeLookUpLeft=0.5, eyeLookUpRight=0.5, eyeLookDownLeft=0.5,
                       eyeLookDownRight=0.5)  # fmt: skip
    still = next(render_frames(head, performer, act, fps=30.0, sway_degrees=0.0))
    turned = next(render_frames(head, performer, act, fps=30.0, sway_degrees=0.0,
                                gaze_degrees=20.0))  # fmt: skip

    changed = np.abs(turned.astype(int) - still).sum(axis=2) > 30
    assert changed.sum() < 5

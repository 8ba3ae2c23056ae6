"""Landmark noise measured from held frames and from a take's stillest segment."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig.errors import InputError
from facecast.rig.noise import estimate_noise, still_segment


def _held(frames: int, sigma: float, drift: float = 0.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    face = rng.normal(size=(20, 3)) * 5.0
    ramp = np.linspace(0.0, drift, frames)[:, None, None]
    return face + ramp + rng.normal(0.0, sigma, (frames, 20, 3))


def test_noise_of_held_frames_is_the_trackers_sigma():
    assert estimate_noise(_held(120, 0.05)) == pytest.approx(0.05, rel=0.05)


def test_slow_drift_of_a_held_face_does_not_count_as_noise():
    # 0.5 cm of drift over two seconds: ten times sigma, yet sigma is read within 5 %.
    drifting = _held(120, 0.05, drift=0.5)
    assert drifting.std(axis=0).mean() > 0.1
    assert estimate_noise(drifting) == pytest.approx(0.05, rel=0.05)


def test_still_segment_finds_the_held_stretch_of_a_take():
    rng = np.random.default_rng(1)
    take = np.cumsum(rng.normal(0.0, 0.3, (200, 20, 3)), axis=0)  # a face moving all along
    take[120:150] = take[120] + rng.normal(0.0, 0.01, (30, 20, 3))  # held for 30 frames
    start, stop = still_segment(take, 20)
    assert start >= 120 and stop <= 150
    assert estimate_noise(take[start:stop]) == pytest.approx(0.01, rel=0.2)


@pytest.mark.parametrize(
    ("frames", "code"),
    [
        (np.zeros((1, 20, 3)), "bad_noise_input"),
        (np.zeros((10, 20)), "bad_noise_input"),
        (np.full((10, 20, 3), np.nan), "non_finite"),
        ([["a"]], "bad_noise_input"),
    ],
)
def test_bad_frames_are_refused_with_a_code(frames, code):
    with pytest.raises(InputError) as caught:
        estimate_noise(frames)
    assert caught.value.code == code


@pytest.mark.parametrize("window", [1, 11])
def test_still_segment_window_must_fit_the_take(window):
    with pytest.raises(InputError, match="window"):
        still_segment(np.zeros((10, 4, 3)), window)

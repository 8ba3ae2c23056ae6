"""Jitter against lag: the lag measure, the Kalman filter, and the default's place on a take."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facecast.protocol.messages import Smoothing
from facecast.rig import fit
from facecast.rig.errors import InputError
from facecast.rig.evaluation.takes import take_experiment
from facecast.rig.evaluation.temporal import best_under_one_frame, lag_frames, temporal_tradeoff
from facecast.rig.filters import KALMAN_ACCELERATION, KalmanFilter, OneEuroFilter
from facecast.rig.sources.ict_arkit import arkit_example_set
from facecast.rig.sources.trackers import read_livelink_csv

from ._real_take import ARCHIVE, TAKE, noisy_take


def _wave(frames: int = 240) -> np.ndarray:
    t = np.arange(frames) / 60.0
    return np.stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 1.3 * t)], axis=1)


@pytest.mark.parametrize("delay", [0, 3, 7])
def test_lag_of_a_delayed_copy_is_its_delay(delay):
    wave = _wave(300)
    truth, delayed = wave[10:250], wave[10 - delay : 250 - delay]
    assert lag_frames(truth, delayed) == pytest.approx(delay, abs=0.05)


def test_lag_of_a_copy_running_ahead_is_negative():
    wave = _wave(300)
    assert lag_frames(wave[10:250], wave[11:251]) == pytest.approx(-1.0, abs=0.05)


def test_lag_refuses_mismatched_or_short_series():
    with pytest.raises(InputError, match="shapes"):
        lag_frames(np.zeros((50, 2)), np.zeros((50, 3)))
    with pytest.raises(InputError, match="frames"):
        lag_frames(np.zeros((10, 2)), np.zeros((10, 2)))


def test_kalman_filter_smooths_noise_and_follows_a_ramp_without_steady_lag():
    t = np.arange(600) / 60.0
    ramp = np.stack([2.0 * t, -t], axis=1)
    noisy = ramp + np.random.default_rng(0).normal(0.0, 0.05, ramp.shape)
    out = KalmanFilter(noise=0.05, acceleration=5.0).filter_series(noisy, t)
    settled = slice(300, None)
    # A constant-velocity model tracks a ramp with no lag once settled, and cuts the noise.
    assert np.abs((out - ramp)[settled].mean(axis=0)).max() < 0.01
    assert (out - ramp)[settled].std() < 0.5 * (noisy - ramp)[settled].std()


def test_kalman_first_sample_passes_and_bad_settings_are_refused():
    assert KalmanFilter(0.1, 10.0)(np.array([1.0, 2.0]), 0.0).tolist() == [1.0, 2.0]
    with pytest.raises(InputError):
        KalmanFilter(0.0, 10.0)
    with pytest.raises(InputError, match="backwards"):
        f = KalmanFilter(0.1, 10.0)
        f(np.zeros(2), 1.0)
        f(np.zeros(2), 0.5)


def test_protocol_and_filter_defaults_agree():
    smoothing = Smoothing()
    one_euro = OneEuroFilter()
    assert (smoothing.min_cutoff, smoothing.beta) == (one_euro.min_cutoff, one_euro.beta)
    assert smoothing.acceleration == KALMAN_ACCELERATION


@pytest.mark.ict
@pytest.mark.slow
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
@pytest.mark.parametrize("sigma", [0.01, 0.05])  # cm: 0.1 and 0.5 mm
def test_default_kalman_has_less_jitter_and_lag_than_the_default_one_euro_on_a_real_take(sigma):
    data = noisy_take(sigma)
    one_euro = OneEuroFilter()
    table = temporal_tradeoff(
        data.rig, data.noisy, data.experiment.truth, fps=data.fps, noise=sigma,
        one_euro=[(one_euro.min_cutoff, one_euro.beta)], kalman=[KALMAN_ACCELERATION],
    )  # fmt: skip
    euro, kalman = (
        next(r for r in table["rows"] if r["family"] == f) for f in ("one-euro", "kalman")
    )
    assert kalman["lag_frames"] < euro["lag_frames"] < 1.0
    assert kalman["jitter"] < euro["jitter"]


@pytest.mark.ict
@pytest.mark.slow
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
def test_default_one_euro_is_the_best_one_euro_under_one_frame_of_lag_on_a_real_take():
    examples = arkit_example_set(ARCHIVE)
    livelink = read_livelink_csv(TAKE)
    take = take_experiment(examples, livelink.weights, livelink.fps)
    sigma = 0.05
    noisy = take.points + np.random.default_rng(0).normal(0.0, sigma, take.points.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = fit(examples, noise=sigma, clamp="nonneg")
    default = OneEuroFilter()
    table = temporal_tradeoff(rig, noisy, take.truth, fps=livelink.fps, noise=sigma)
    best = best_under_one_frame(table)["one-euro"]
    assert best["settings"] == {"min_cutoff": default.min_cutoff, "beta": default.beta}
    raw = next(row for row in table["rows"] if row["family"] == "raw")
    assert best["jitter"] < 0.5 * raw["jitter"]

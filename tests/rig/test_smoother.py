"""The offline RTS smoother: a textbook reference, its forward pass, no lag, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig import fit, smooth_points
from facecast.rig.demo import demo_example_set
from facecast.rig.errors import InputError
from facecast.rig.evaluation.temporal import lag_frames
from facecast.rig.filters import KALMAN_ACCELERATION, KalmanFilter, RTSSmoother

NOISE = 0.05
ACCELERATION = 40.0


def _reference_rts(z: np.ndarray, t: np.ndarray, noise: float, acceleration: float) -> np.ndarray:
    """Rauch-Tung-Striebel written plainly: one channel at a time, a loop over frames,
    full matrices and inverses, the textbook equations (strictly increasing times)."""
    frames, channels = z.shape
    h = np.array([[1.0, 0.0]])
    r = noise**2
    q = acceleration**2
    out = np.empty_like(z)
    for c in range(channels):
        x_f = np.zeros((frames, 2))
        p_f = np.zeros((frames, 2, 2))
        x_p = np.zeros((frames, 2))
        p_p = np.zeros((frames, 2, 2))
        transitions = np.zeros((frames, 2, 2))
        # KalmanFilter's start: the first measurement, at rest, velocity variance q * 1 s^2.
        x_f[0] = [z[0, c], 0.0]
        p_f[0] = np.diag([r, q])
        for i in range(1, frames):
            dt = t[i] - t[i - 1]
            a = np.array([[1.0, dt], [0.0, 1.0]])
            g = np.array([[dt * dt / 2.0], [dt]])
            transitions[i] = a
            x_p[i] = a @ x_f[i - 1]
            p_p[i] = a @ p_f[i - 1] @ a.T + q * (g @ g.T)
            s = h @ p_p[i] @ h.T + r
            k = p_p[i] @ h.T @ np.linalg.inv(s)
            x_f[i] = x_p[i] + (k @ (z[i, c] - h @ x_p[i])).ravel()
            p_f[i] = (np.eye(2) - k @ h) @ p_p[i]
        x_s = x_f.copy()
        for i in range(frames - 2, -1, -1):
            gain = p_f[i] @ transitions[i + 1].T @ np.linalg.inv(p_p[i + 1])
            x_s[i] = x_f[i] + gain @ (x_s[i + 1] - x_p[i + 1])
        out[:, c] = x_s[:, 0]
    return out


def _irregular_take(frames: int = 200, channels: int = 4, seed: int = 0, *, clean=False):
    """Noisy sines (F, C) at jittered times (F,) (and the sines, with ``clean``)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.008, 0.04, frames))
    sines = np.stack([np.sin(2 * np.pi * (0.3 + 0.2 * c) * t) for c in range(channels)], axis=1)
    noisy = sines + rng.normal(0.0, NOISE, sines.shape)
    return (noisy, t, sines) if clean else (noisy, t)


def test_smoother_agrees_with_a_textbook_rts_to_rounding():
    z, t = _irregular_take()

    smoothed = RTSSmoother(NOISE, ACCELERATION).smooth(z, t)

    np.testing.assert_allclose(smoothed, _reference_rts(z, t, NOISE, ACCELERATION), atol=1e-12)


def test_forward_pass_is_the_live_kalman_filters_output():
    z, t = _irregular_take()
    t[50] = t[49]  # a repeated time, which the live filter ignores

    forward = RTSSmoother(NOISE, ACCELERATION).filter_series(z, t)

    live = KalmanFilter(NOISE, ACCELERATION).filter_series(z, t)
    np.testing.assert_allclose(forward, live, atol=1e-12)


def test_a_repeated_time_is_smoothed_as_the_frame_it_repeats():
    z, t = _irregular_take()
    t[50] = t[49]

    smoothed = RTSSmoother(NOISE, ACCELERATION).smooth(z, t)

    np.testing.assert_array_equal(smoothed[49], smoothed[50])
    assert np.isfinite(smoothed).all()


def test_smoothing_cuts_noise_more_than_the_causal_filter():
    z, t, sines = _irregular_take(frames=600, seed=1, clean=True)

    smoothed = RTSSmoother(NOISE, ACCELERATION).smooth(z, t)
    filtered = KalmanFilter(NOISE, ACCELERATION).filter_series(z, t)

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x - sines)[20:] ** 2)))

    assert rms(filtered) < rms(z)
    assert rms(smoothed) < 0.7 * rms(filtered)


@pytest.mark.parametrize("shape", ["step", "ramp"])
def test_smoothed_series_is_not_delayed(shape):
    t = np.arange(360) / 60.0
    change = np.where(t < 3.0, 0.0, 1.0) if shape == "step" else np.clip(t - 2.0, 0.0, 1.5)
    truth = np.stack([change, -0.5 * change], axis=1)
    noisy = truth + np.random.default_rng(2).normal(0.0, 0.01, truth.shape)
    # A low acceleration (heavy smoothing), so that a causal filter clearly trails.
    smoother = RTSSmoother(0.01, 0.3)

    smoothed = smoother.smooth(noisy, t)
    filtered = smoother.filter_series(noisy, t)

    # The causal filter trails the change by frames; the smoother sees both sides of it.
    assert lag_frames(truth, filtered) > 1.0
    assert abs(lag_frames(truth, smoothed)) < 0.1


def test_empty_and_one_frame_series_pass_through():
    smoother = RTSSmoother(NOISE, ACCELERATION)

    assert smoother.smooth(np.zeros((0, 3)), np.zeros(0)).shape == (0, 3)
    one = np.array([[1.0, -2.0, 3.0]])
    np.testing.assert_array_equal(smoother.smooth(one, np.array([0.5])), one)


def test_input_is_not_modified():
    z, t = _irregular_take(frames=20)
    before = z.copy()

    RTSSmoother(NOISE, ACCELERATION).smooth(z, t)

    np.testing.assert_array_equal(z, before)


@pytest.mark.parametrize(
    ("values", "times", "code", "match"),
    [
        (np.zeros((4, 2)), np.arange(3.0), "bad_input", "one per frame"),
        (np.zeros(4), np.arange(4.0), "bad_input", r"\(F, C\)"),
        (np.zeros((4, 0)), np.arange(4.0), "bad_input", "C >= 1"),
        ([[0.0], [np.nan], [0.0]], np.arange(3.0), "non_finite", "frame 1"),
        ([[0.0], [0.0], [np.inf]], np.arange(3.0), "non_finite", "frame 2"),
        (np.zeros((3, 1)), [0.0, np.nan, 1.0], "non_finite", "time 1"),
        (np.zeros((3, 1)), [0.0, 1.0, 0.5], "bad_time", "frame 2 at 0.5 s"),
        ([["a"], ["b"]], np.arange(2.0), "bad_input", "numeric"),
    ],
)
def test_bad_input_gets_a_clear_error(values, times, code, match):
    with pytest.raises(InputError, match=match) as raised:
        RTSSmoother(NOISE, ACCELERATION).smooth(values, times)
    assert raised.value.code == code


def test_bad_settings_are_refused():
    with pytest.raises(InputError, match="noise"):
        RTSSmoother(0.0, 1.0)
    with pytest.raises(InputError, match="acceleration"):
        RTSSmoother(1.0, float("nan"))


@pytest.fixture(scope="module")
def demo_rigs():
    examples = demo_example_set()
    return fit(examples), fit(examples, noise=0.01)


def test_smooth_points_defaults_to_rts_on_a_noise_rig_only(demo_rigs):
    exact, noisy_rig = demo_rigs
    rng = np.random.default_rng(3)
    points = exact.source_neutral + rng.normal(0.0, 0.01, (30, exact.num_points, 3))
    t = np.arange(30) / 30.0

    smoothed = smooth_points(noisy_rig, points, t)

    expected = RTSSmoother(0.01, KALMAN_ACCELERATION * 0.01).smooth(points.reshape(30, -1), t)
    np.testing.assert_allclose(smoothed.reshape(30, -1), expected, atol=1e-15)
    np.testing.assert_array_equal(smooth_points(exact, points, t), points)
    np.testing.assert_array_equal(smooth_points(noisy_rig, points, t, smoothing="none"), points)


def test_smooth_points_refuses_rts_without_a_noise(demo_rigs):
    exact, _ = demo_rigs
    points = np.repeat(exact.source_neutral[None], 5, axis=0)

    with pytest.raises(InputError, match="--noise") as raised:
        smooth_points(exact, points, np.arange(5.0), smoothing="rts")
    assert raised.value.code == "no_noise"
    with pytest.raises(InputError, match="one of") as raised:
        smooth_points(exact, points, np.arange(5.0), smoothing="gaussian")
    assert raised.value.code == "bad_smoothing"

"""The offline RTS smoother: a textbook reference, its forward pass, no lag, bad input; the
acceleration read off a take, and the rig regularised for what the smoother leaves."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facecast.rig import IdentifiabilityWarning, fit, refit_noise, smooth_take
from facecast.rig.demo import demo_activations, demo_animation, demo_example_set, demo_target_frames
from facecast.rig.errors import FitError, InputError
from facecast.rig.evaluation.evaluate import cloning_error
from facecast.rig.evaluation.temporal import lag_frames
from facecast.rig.filters import KalmanFilter
from facecast.rig.smoother import RTSSmoother, estimate_acceleration

from ._real_take import ARCHIVE, noisy_take

NOISE = 0.05
ACCELERATION = 40.0


def _reference_rts(
    z: np.ndarray, t: np.ndarray, noise: float, acceleration: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel written plainly: one channel at a time, a loop over frames,
    full matrices and inverses, the textbook equations (strictly increasing times).
    Returns the smoothed positions (F, C), their variance (F,), and each channel's mean
    log-likelihood of the innovations (C,)."""
    frames, channels = z.shape
    h = np.array([[1.0, 0.0]])
    r = noise**2
    q = acceleration**2
    out = np.empty_like(z)
    variance = np.empty(frames)
    log_likelihood = np.zeros(channels)
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
            innovation = z[i, c] - (h @ x_p[i])[0]
            density = np.exp(-0.5 * innovation**2 / s[0, 0]) / np.sqrt(2 * np.pi * s[0, 0])
            log_likelihood[c] += np.log(density) / (frames - 1)
            k = p_p[i] @ h.T @ np.linalg.inv(s)
            x_f[i] = x_p[i] + (k @ (z[i, c] - h @ x_p[i])).ravel()
            p_f[i] = (np.eye(2) - k @ h) @ p_p[i]
        x_s = x_f.copy()
        p_s = p_f.copy()
        for i in range(frames - 2, -1, -1):
            gain = p_f[i] @ transitions[i + 1].T @ np.linalg.inv(p_p[i + 1])
            x_s[i] = x_f[i] + gain @ (x_s[i + 1] - x_p[i + 1])
            p_s[i] = p_f[i] + gain @ (p_s[i + 1] - p_p[i + 1]) @ gain.T
        out[:, c] = x_s[:, 0]
        variance[:] = p_s[:, 0, 0]
    return out, variance, log_likelihood


def _irregular_take(frames: int = 200, channels: int = 4, seed: int = 0, *, clean=False):
    """Noisy sines (F, C) at jittered times (F,) (and the sines, with ``clean``)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.008, 0.04, frames))
    sines = np.stack([np.sin(2 * np.pi * (0.3 + 0.2 * c) * t) for c in range(channels)], axis=1)
    noisy = sines + rng.normal(0.0, NOISE, sines.shape)
    return (noisy, t, sines) if clean else (noisy, t)


def test_smoother_agrees_with_a_textbook_rts_to_rounding():
    z, t = _irregular_take()

    smoother = RTSSmoother(NOISE, ACCELERATION)

    smoothed = smoother.smooth(z, t)
    std = smoother.smoothed_std(t)

    reference, variance, _ = _reference_rts(z, t, NOISE, ACCELERATION)
    np.testing.assert_allclose(smoothed, reference, atol=1e-12)
    np.testing.assert_allclose(std[:, 0], np.sqrt(variance), rtol=1e-9)


def test_forward_pass_is_the_live_kalman_filters_output():
    z, t = _irregular_take()
    t[50] = t[49]  # a repeated time, which the live filter ignores

    forward = RTSSmoother(NOISE, ACCELERATION).filter_series(z, t)

    live = KalmanFilter(NOISE, ACCELERATION).filter_series(z, t)
    np.testing.assert_allclose(forward, live, atol=1e-12)


def test_the_live_kalman_at_an_acceleration_in_noise_units_does_not_depend_on_the_noise():
    # The server's auto smoothing takes a re-base's σ for a generic rig (PROTOCOL.md
    # §5.2.5): with the process noise acceleration × σ, every covariance scales with σ²
    # and the gain not at all, so any σ > 0 filters alike.
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.normal(0.0, 0.1, (40, 6)), axis=0)
    t = np.cumsum(rng.uniform(0.02, 0.05, 40))
    outputs = [KalmanFilter(noise=s, acceleration=480.0 * s).filter_series(x, t)
               for s in (0.001, 0.05, 3.0)]  # fmt: skip
    np.testing.assert_allclose(outputs[0], outputs[1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(outputs[2], outputs[1], rtol=0, atol=1e-9)
    unfiltered = np.abs(np.diff(x, 2, axis=0)).mean()
    assert np.abs(np.diff(outputs[1], 2, axis=0)).mean() < 0.7 * unfiltered  # it filters


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


def test_log_likelihood_is_the_innovations_gaussian_density():
    z, t = _irregular_take(frames=40, channels=3)

    value = RTSSmoother(NOISE, ACCELERATION).log_likelihood(z, t)

    np.testing.assert_allclose(value, _reference_rts(z, t, NOISE, ACCELERATION)[2], rtol=1e-10)


def test_estimated_acceleration_recovers_each_channels_own():
    rng = np.random.default_rng(5)
    frames, dt = 3000, 1 / 60.0
    acceleration = np.repeat([2.0, 20.0], 4)
    velocity = np.cumsum(rng.normal(0.0, 1.0, (frames, 8)) * acceleration * dt, axis=0)
    position = np.cumsum(velocity * dt, axis=0)
    t = np.arange(frames) * dt

    estimate = estimate_acceleration(position + rng.normal(0.0, 0.001, position.shape), t, 0.001)

    assert ((acceleration / 1.4 < estimate) & (estimate < acceleration * 1.4)).all()


def test_a_shared_acceleration_smooths_the_same_in_any_orthonormal_basis():
    z, t = _irregular_take()
    rotation = np.linalg.qr(np.random.default_rng(6).normal(size=(4, 4)))[0]
    smoother = RTSSmoother(NOISE, ACCELERATION)

    rotated = smoother.smooth(z @ rotation.T, t) @ rotation

    np.testing.assert_allclose(rotated, smoother.smooth(z, t), atol=1e-12)


def test_one_acceleration_per_channel_smooths_each_as_alone():
    z, t = _irregular_take()
    each = np.array([5.0, 40.0, 5.0, 400.0])  # two channels share one: 3 recursions

    together = RTSSmoother(NOISE, each).smooth(z, t)

    for c, a in enumerate(each):
        alone = RTSSmoother(NOISE, a).smooth(z[:, c : c + 1], t)
        np.testing.assert_allclose(together[:, c : c + 1], alone, atol=1e-13)
    with pytest.raises(InputError, match="4 channels"):
        RTSSmoother(NOISE, each[:3]).smooth(z, t)


def test_estimating_the_acceleration_needs_three_distinct_times():
    with pytest.raises(InputError, match="3 or more frames"):
        estimate_acceleration(np.zeros((3, 2)), [0.0, 0.0, 1.0], 0.1)


@pytest.fixture(scope="module")
def demo_rigs():
    examples = demo_example_set()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)  # neutral and fv at 0.2
        return examples, fit(examples), fit(examples, noise=0.2)


def test_refit_noise_gives_the_rig_fit_would_at_that_noise(demo_rigs):
    examples, _, noise_rig = demo_rigs
    points = demo_animation(1.0, 30.0).points

    refitted = refit_noise(noise_rig, 0.05)

    direct = fit(examples, noise=0.05)
    np.testing.assert_allclose(refitted.weights(points), direct.weights(points), atol=1e-9)
    assert refitted.fit_report["noise"] == 0.05 and refitted.fit_report["fitted_noise"] == 0.2
    with pytest.raises(FitError, match="> 0"):
        refit_noise(noise_rig, 0.0)


def test_smooth_take_defaults_to_rts_and_a_rig_for_the_noise_left(demo_rigs):
    _, _, noise_rig = demo_rigs
    clean = demo_animation(4.0, 60.0).points
    points = clean + np.random.default_rng(3).normal(0.0, 0.2, clean.shape)
    t = np.arange(len(points)) / 60.0

    take = smooth_take(noise_rig, points, t)

    assert take.method == "rts" and take.acceleration is not None
    # Smoothed along the take's principal directions, each at its own acceleration.
    flat = points.reshape(len(t), -1)
    mean = flat.mean(axis=0)
    directions = np.linalg.svd(flat - mean, full_matrices=False)[2]
    assert take.acceleration.shape == (flat.shape[1],) and np.ptp(take.acceleration) > 0
    smoother = RTSSmoother(0.2, take.acceleration * 0.2)
    expected = smoother.smooth((flat - mean) @ directions.T, t) @ directions + mean
    np.testing.assert_allclose(take.points.reshape(len(t), -1), expected, atol=1e-12)
    assert 0.0 < take.noise < 0.2 and take.rig.fit_report["noise"] == take.noise

    truth = demo_target_frames(demo_activations(4.0, 60.0))

    def error(rig, pts) -> float:
        return float(np.sqrt(np.mean((rig.clone(pts) - truth) ** 2)))

    # Against the ideal clone: the smoothed points beat the noisy ones, and the rig
    # regularised for the noise left beats the rig as it was.
    assert error(take.rig, take.points) < error(noise_rig, take.points) < error(noise_rig, points)


def test_smooth_take_with_an_acceleration_runs_the_live_model_both_ways(demo_rigs):
    _, _, noise_rig = demo_rigs
    rng = np.random.default_rng(7)
    points = noise_rig.source_neutral + rng.normal(0.0, 0.2, (30, noise_rig.num_points, 3))
    t = np.arange(30) / 30.0

    take = smooth_take(noise_rig, points, t, acceleration=480.0)

    expected = RTSSmoother(0.2, 480.0 * 0.2).smooth(points.reshape(30, -1), t)
    np.testing.assert_allclose(take.points.reshape(30, -1), expected, atol=1e-15)
    assert take.acceleration is not None and take.acceleration.tolist() == [480.0]


def test_smooth_take_passes_an_exact_rig_none_and_short_takes_through(demo_rigs):
    _, exact, noise_rig = demo_rigs
    rng = np.random.default_rng(4)
    points = exact.source_neutral + rng.normal(0.0, 0.2, (30, exact.num_points, 3))
    t = np.arange(30) / 30.0

    for take, rig, method in (
        (smooth_take(exact, points, t), exact, "none"),
        (smooth_take(noise_rig, points, t, smoothing="none"), noise_rig, "none"),
        (smooth_take(noise_rig, points[:2], t[:2]), noise_rig, "rts"),
    ):
        np.testing.assert_array_equal(take.points, points[: len(take.points)])
        assert take.rig is rig and take.method == method


def test_smooth_take_refuses_rts_without_a_noise_or_an_unknown_method(demo_rigs):
    _, exact, _ = demo_rigs
    points = np.repeat(exact.source_neutral[None], 5, axis=0)

    with pytest.raises(InputError, match="--noise") as raised:
        smooth_take(exact, points, np.arange(5.0), smoothing="rts")
    assert raised.value.code == "no_noise"
    with pytest.raises(InputError, match="one of") as raised:
        smooth_take(exact, points, np.arange(5.0), smoothing="gaussian")
    assert raised.value.code == "bad_smoothing"


@pytest.mark.ict
@pytest.mark.slow
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found")
@pytest.mark.parametrize("sigma", [0.01, 0.05])  # cm: 0.1 and 0.5 mm
def test_clone_default_smoothing_cuts_the_error_on_a_real_take_without_lag(sigma):
    data = noisy_take(sigma)
    times = np.arange(len(data.noisy)) / data.fps

    take = smooth_take(data.rig, data.noisy, times)

    per_frame = data.rig.clone(data.noisy)
    smoothed = take.rig.clone(take.points)
    truth = data.experiment.truth

    def max_axis(vertices: np.ndarray) -> float:
        return max(cloning_error(truth, vertices)["eq41_percent"].values())

    # The goal: at most 0.85 x the per-frame error on the largest axis, no lag added.
    assert max_axis(smoothed) <= 0.85 * max_axis(per_frame)
    assert abs(lag_frames(truth[:, ::16], smoothed[:, ::16])) < 0.1

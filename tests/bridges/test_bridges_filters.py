"""The one-euro filter: steps settle, noise shrinks by the low-pass factor, ramps lag little."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.rig.errors import InputError
from facecast.rig.filters import OneEuroFilter, smoothing_alpha

FPS = 60.0
DT = 1.0 / FPS


def _times(seconds: float) -> np.ndarray:
    return np.arange(round(seconds * FPS)) * DT


def test_first_sample_passes_through_unchanged():
    f = OneEuroFilter(min_cutoff=1.0, beta=0.5)
    x = np.array([1.5, -2.0, 3.25])
    assert np.array_equal(f(x, 0.0), x)


def test_step_settles_within_the_low_pass_time_bound():
    # beta = 0: a first-order low-pass, error (1 - alpha)^n after n samples, so 1 % is
    # reached after ln(0.01) / ln(1 - alpha) samples (46 at 1 Hz, 60 fps: 0.77 s).
    alpha = float(smoothing_alpha(1.0, DT))
    bound = math.ceil(math.log(0.01) / math.log(1.0 - alpha)) * DT
    t = _times(3.0)
    x = np.where(t >= 1.0, 1.0, 0.0)[:, None].repeat(4, axis=1)
    y = OneEuroFilter(min_cutoff=1.0, beta=0.0).filter_series(x, t)
    settled = t >= 1.0 + bound
    assert np.all(np.abs(y[settled] - 1.0) <= 0.01)
    assert np.all(np.abs(y[(t >= 1.0) & (t < 1.0 + bound - 2 * DT)] - 1.0) > 0.01)


def test_speed_coefficient_makes_a_step_settle_faster():
    t = _times(3.0)
    x = np.where(t >= 1.0, 1.0, 0.0)[:, None]
    slow = OneEuroFilter(min_cutoff=1.0, beta=0.0).filter_series(x, t)[:, 0]
    fast = OneEuroFilter(min_cutoff=1.0, beta=1.0).filter_series(x, t)[:, 0]
    first = lambda y: t[np.argmax(np.abs(y - 1.0) <= 0.01)]  # noqa: E731
    assert first(fast) < first(slow) - 0.2


def test_white_noise_on_a_constant_shrinks_by_the_low_pass_factor():
    # A first-order low-pass y += a (x - y) on white noise has output variance
    # a / (2 - a) of the input's: std ratio 0.223 at 1 Hz and 60 fps.
    rng = np.random.default_rng(7)
    t = _times(60.0)
    noise = rng.normal(scale=0.05, size=(t.size, 8))
    y = OneEuroFilter(min_cutoff=1.0, beta=0.0).filter_series(5.0 + noise, t)
    alpha = float(smoothing_alpha(1.0, DT))
    expected = math.sqrt(alpha / (2.0 - alpha))
    ratio = float((y[int(FPS) :] - 5.0).std() / noise.std())
    assert ratio < 0.3
    assert ratio == pytest.approx(expected, rel=0.15)
    assert abs(float(y[60:].mean()) - 5.0) < 0.01


def test_slow_ramp_is_followed_with_the_predicted_small_lag():
    # Steady-state lag of the low-pass on a ramp of slope r: r * dt * (1 - a) / a.
    slope = 0.5
    t = _times(10.0)
    x = (slope * t)[:, None]
    y = OneEuroFilter(min_cutoff=1.0, beta=0.0).filter_series(x, t)[:, 0]
    alpha = float(smoothing_alpha(1.0, DT))
    lag = slope * DT * (1.0 - alpha) / alpha
    late = t > 5.0
    assert np.allclose(x[late, 0] - y[late], lag, rtol=1e-3)
    tuned = OneEuroFilter(min_cutoff=1.0, beta=5.0).filter_series(x, t)[:, 0]
    assert np.all(x[late, 0] - tuned[late] < lag / 2)


def test_channels_are_filtered_independently():
    rng = np.random.default_rng(1)
    t = _times(2.0)
    x = rng.normal(size=(t.size, 3))
    together = OneEuroFilter(1.0, 0.3).filter_series(x, t)
    alone = OneEuroFilter(1.0, 0.3).filter_series(x[:, 1:2], t)
    assert np.allclose(together[:, 1:2], alone)


def test_repeated_time_returns_the_previous_output():
    f = OneEuroFilter()
    f(np.zeros(2), 0.0)
    y = f(np.ones(2), 0.1)
    assert np.array_equal(f(np.full(2, 9.0), 0.1), y)


@pytest.mark.parametrize(
    ("kwargs", "code"),
    [
        ({"min_cutoff": 0.0}, "bad_filter"),
        ({"beta": -1.0}, "bad_filter"),
        ({"d_cutoff": math.nan}, "bad_filter"),
    ],
)
def test_bad_parameters_are_refused(kwargs, code):
    with pytest.raises(InputError) as info:
        OneEuroFilter(**kwargs)
    assert info.value.code == code


def test_time_going_backwards_is_refused():
    f = OneEuroFilter()
    f(np.zeros(2), 1.0)
    with pytest.raises(InputError) as info:
        f(np.zeros(2), 0.5)
    assert info.value.code == "bad_time"


def test_nan_input_and_changed_channel_count_are_refused():
    f = OneEuroFilter()
    f(np.zeros(2), 0.0)
    with pytest.raises(InputError) as nan:
        f(np.array([0.0, np.nan]), 0.1)
    with pytest.raises(InputError) as shape:
        f(np.zeros(3), 0.2)
    assert (nan.value.code, shape.value.code) == ("non_finite", "bad_input")


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40),
    st.floats(0.01, 10.0),
    st.floats(0.0, 5.0),
)
def test_output_stays_within_the_range_of_the_inputs(values, min_cutoff, beta):
    x = np.asarray(values)[:, None]
    t = np.arange(x.shape[0]) * DT
    y = OneEuroFilter(min_cutoff, beta).filter_series(x, t)
    span = 1e-9 * max(1.0, float(np.abs(x).max()))
    assert np.all(y >= x.min() - span) and np.all(y <= x.max() + span)

"""The one-euro filter (Casiez, Roussel & Vogel, CHI 2012) and a Kalman filter, over channels.

Smooths tracker jitter with little lag on fast motion; pure numpy, no I/O, and it must
not know what its channels mean (points, weights, angles are all just C numbers).

The filter, per channel, at a sample ``x`` arriving ``dt`` seconds after the last::

    alpha(fc) = 1 / (1 + tau / dt),  tau = 1 / (2 pi fc)     # smoothing factor, eq. (1)
    dx   = (x - x_hat_prev) / dt                             # speed estimate
    dx_hat = alpha(d_cutoff) dx + (1 - alpha(d_cutoff)) dx_hat_prev
    fc   = min_cutoff + beta |dx_hat|                        # adaptive cutoff
    x_hat = alpha(fc) x + (1 - alpha(fc)) x_hat_prev

With ``beta = 0`` it is a first-order low-pass at ``min_cutoff`` Hz.

``KalmanFilter`` is the alternative the jitter-against-lag study compares it with
(``rig.temporal``): a constant-velocity model per channel whose measurement noise is the
fit's landmark noise, so its one knob is how hard the face may accelerate.

Its offline twin for a whole recorded series is ``rig.smoother.RTSSmoother``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from .errors import InputError

__all__ = [
    "KALMAN_ACCELERATION",
    "KalmanFilter",
    "OneEuroFilter",
    "smoothing_alpha",
]

#: The Kalman filter's default process noise as ``hello.smoothing`` gives it: the std of the
#: face's acceleration in units of the landmark noise per s^2 (acceleration = this x noise).
#: Less jitter and less lag than the one-euro defaults on both real takes at 0.1-0.5 mm of
#: noise (README "Temporal coherence").
KALMAN_ACCELERATION = 480.0


def smoothing_alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray:
    """Exponential smoothing factor of a first-order low-pass at ``cutoff`` Hz, step ``dt`` s."""
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff, dtype=np.float64))
    return 1.0 / (1.0 + tau / dt)


def check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}", code="bad_filter") from None
    ok = number >= 0 if allow_zero else number > 0
    if not (math.isfinite(number) and ok):
        bound = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name} must be finite and {bound}, got {number}", code="bad_filter")
    return number


def _sanitize_sample(
    x: npt.ArrayLike, t: float, shape: tuple[int, ...] | None, last_t: float | None
) -> tuple[np.ndarray, float]:
    """A sample (C,) and its time, checked against the channels and time before them."""
    try:
        sample = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("filter input is not a numeric array", code="bad_input") from None
    if sample.ndim != 1 or sample.shape[0] < 1:
        raise InputError(
            f"filter input: expected shape (C,) with C >= 1, got {sample.shape}",
            code="bad_input",
        )
    if shape is not None and sample.shape != shape:
        raise InputError(
            f"filter input: expected {shape[0]} channels as before, got {sample.shape[0]}",
            code="bad_input",
        )
    if not np.isfinite(sample).all():
        raise InputError("filter input has NaN or Inf values", code="non_finite")
    try:
        when = float(t)
    except (TypeError, ValueError):
        raise InputError(f"filter time must be a number, got {t!r}", code="bad_input") from None
    if not math.isfinite(when):
        raise InputError(f"filter time must be finite, got {when}", code="non_finite")
    if last_t is not None and when < last_t:
        raise InputError(f"filter time went backwards: {when} s after {last_t} s", code="bad_time")
    return sample, when


class OneEuroFilter:
    """A one-euro filter over C channels at once; state is kept between calls.

    Parameters
    ----------
    min_cutoff : float
        Cutoff frequency (Hz) at rest; lower is smoother and laggier. > 0. Default 2 and
        ``beta`` 2: the least jitter at a lag under one frame on real takes (centimetres;
        ``rig.temporal``), as the protocol's ``smoothing`` defaults.
    beta : float
        Speed coefficient: how fast the cutoff rises with speed (per unit/s). >= 0.
    d_cutoff : float
        Cutoff frequency (Hz) of the speed estimate. > 0.

    Examples
    --------
    >>> f = OneEuroFilter(min_cutoff=2.0, beta=2.0)
    >>> y = f(np.zeros(3), t=0.0)
    """

    def __init__(self, min_cutoff: float = 2.0, beta: float = 2.0, d_cutoff: float = 1.0) -> None:
        self.min_cutoff = check_positive("min_cutoff", min_cutoff)
        self.beta = check_positive("beta", beta, allow_zero=True)
        self.d_cutoff = check_positive("d_cutoff", d_cutoff)
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next sample passes through unchanged."""
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t: float | None = None

    @property
    def num_channels(self) -> int | None:
        """C, once the first sample fixed it; None before."""
        return None if self._x is None else int(self._x.shape[0])

    def _sanitize(self, x: npt.ArrayLike, t: float) -> tuple[np.ndarray, float]:
        shape = None if self._x is None else self._x.shape
        return _sanitize_sample(x, t, shape, self._t)

    def __call__(self, x: npt.ArrayLike, t: float) -> np.ndarray:
        """Filter one sample.

        Parameters
        ----------
        x : (C,) float
        t : float
            Seconds; never less than the previous call's. A repeated ``t`` returns the
            previous output (no time passed, so nothing can change).

        Returns
        -------
        (C,) float64
        """
        sample, when = self._sanitize(x, t)
        if self._x is None or self._dx is None or self._t is None:
            self._x = sample.copy()
            self._dx = np.zeros_like(sample)
            self._t = when
            return sample.copy()
        dt = when - self._t
        if dt == 0.0:
            return self._x.copy()
        speed = (sample - self._x) / dt
        a_d = smoothing_alpha(self.d_cutoff, dt)
        self._dx += a_d * (speed - self._dx)
        cutoff = self.min_cutoff + self.beta * np.abs(self._dx)
        a = smoothing_alpha(cutoff, dt)
        self._x += a * (sample - self._x)
        self._t = when
        return self._x.copy()

    def filter_series(self, x: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        """Filter a whole series, continuing from the current state.

        Parameters
        ----------
        x : (F, C) float
        t : (F,) float
            Non-decreasing seconds.

        Returns
        -------
        (F, C) float64
        """
        series = np.asarray(x, dtype=np.float64)
        times = np.asarray(t, dtype=np.float64)
        if series.ndim != 2:
            raise InputError(
                f"filter series: expected shape (F, C), got {series.shape}", code="bad_input"
            )
        if times.shape != (series.shape[0],):
            raise InputError(
                f"filter series: expected {series.shape[0]} times, got shape {times.shape}",
                code="bad_input",
            )
        out = np.empty_like(series)
        # The filter is recursive in time, so frames are a loop; channels stay vectorised.
        for i in range(series.shape[0]):
            out[i] = self(series[i], times[i])
        return out


class KalmanFilter:
    """A constant-velocity Kalman filter over C channels at once; state kept between calls.

    Each channel is a position and a speed driven by white acceleration of standard
    deviation ``acceleration`` (units/s^2) and measured with white noise ``noise`` (units):
    the fit's landmark noise, so the filter weighs a sample by what the rig was fitted to
    expect. Every channel shares the noise model and the sample times, hence one 2 x 2
    covariance and one gain for all of them: a step costs a few array operations, like the
    one-euro filter's.

    Parameters
    ----------
    noise : float
        Measurement noise std, > 0.
    acceleration : float
        Process noise: std of the acceleration, > 0; higher follows faster motion with less
        lag and smooths less.
    """

    def __init__(self, noise: float, acceleration: float) -> None:
        self.noise = check_positive("noise", noise)
        self.acceleration = check_positive("acceleration", acceleration)
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next sample passes through unchanged."""
        self._x: np.ndarray | None = None
        self._v: np.ndarray | None = None
        self._p = np.zeros((2, 2))
        self._t: float | None = None

    def __call__(self, x: npt.ArrayLike, t: float) -> np.ndarray:
        """Filter one sample (C,) at ``t`` seconds; returns the position estimate (C,)."""
        shape = None if self._x is None else self._x.shape
        sample, when = _sanitize_sample(x, t, shape, self._t)
        r = self.noise * self.noise
        if self._x is None or self._t is None or self._v is None:
            self._x = sample.copy()
            self._v = np.zeros_like(sample)
            self._p = np.array([[r, 0.0], [0.0, (self.acceleration * 1.0) ** 2]])
            self._t = when
            return sample.copy()
        dt = when - self._t
        if dt == 0.0:
            return self._x.copy()
        q = self.acceleration * self.acceleration
        transition = np.array([[1.0, dt], [0.0, 1.0]])
        process = q * np.array([[dt**4 / 4.0, dt**3 / 2.0], [dt**3 / 2.0, dt * dt]])
        p = transition @ self._p @ transition.T + process  # predict
        self._x = self._x + dt * self._v
        gain = p[:, 0] / (p[0, 0] + r)  # update with the position measurement
        innovation = sample - self._x
        self._x += gain[0] * innovation
        self._v += gain[1] * innovation
        self._p = p - np.outer(gain, p[0])
        self._t = when
        return self._x.copy()

    def filter_series(self, x: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        """Filter a whole series (F, C) at times (F,), continuing from the current state."""
        series = np.asarray(x, dtype=np.float64)
        times = np.asarray(t, dtype=np.float64)
        if series.ndim != 2 or times.shape != (series.shape[0],):
            raise InputError(
                f"filter series: expected (F, C) values and (F,) times, got {series.shape} "
                f"and {times.shape}",
                code="bad_input",
            )
        out = np.empty_like(series)
        for i in range(series.shape[0]):
            out[i] = self(series[i], times[i])
        return out

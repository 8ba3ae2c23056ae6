"""The one-euro filter (Casiez, Roussel & Vogel, CHI 2012), vectorised over channels.

Smooths tracker jitter with little lag on fast motion; pure numpy, no I/O, and it must
not know what its channels mean (points, weights, angles are all just C numbers).

The filter, per channel, at a sample ``x`` arriving ``dt`` seconds after the last::

    alpha(fc) = 1 / (1 + tau / dt),  tau = 1 / (2 pi fc)     # smoothing factor, eq. (1)
    dx   = (x - x_hat_prev) / dt                             # speed estimate
    dx_hat = alpha(d_cutoff) dx + (1 - alpha(d_cutoff)) dx_hat_prev
    fc   = min_cutoff + beta |dx_hat|                        # adaptive cutoff
    x_hat = alpha(fc) x + (1 - alpha(fc)) x_hat_prev

With ``beta = 0`` it is a first-order low-pass at ``min_cutoff`` Hz.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError

__all__ = ["OneEuroFilter", "smoothing_alpha"]


def smoothing_alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray:
    """Exponential smoothing factor of a first-order low-pass at ``cutoff`` Hz, step ``dt`` s."""
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff, dtype=np.float64))
    return 1.0 / (1.0 + tau / dt)


def _positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}", code="bad_filter") from None
    ok = number >= 0 if allow_zero else number > 0
    if not (math.isfinite(number) and ok):
        bound = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name} must be finite and {bound}, got {number}", code="bad_filter")
    return number


class OneEuroFilter:
    """A one-euro filter over C channels at once; state is kept between calls.

    Parameters
    ----------
    min_cutoff : float
        Cutoff frequency (Hz) at rest; lower is smoother and laggier. > 0.
    beta : float
        Speed coefficient: how fast the cutoff rises with speed. >= 0.
    d_cutoff : float
        Cutoff frequency (Hz) of the speed estimate. > 0.

    Examples
    --------
    >>> f = OneEuroFilter(min_cutoff=1.0, beta=0.1)
    >>> y = f(np.zeros(3), t=0.0)
    """

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0) -> None:
        self.min_cutoff = _positive("min_cutoff", min_cutoff)
        self.beta = _positive("beta", beta, allow_zero=True)
        self.d_cutoff = _positive("d_cutoff", d_cutoff)
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

    def _sanitize(self, x, t) -> tuple[np.ndarray, float]:
        try:
            sample = np.asarray(x, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("filter input is not a numeric array", code="bad_input") from None
        if sample.ndim != 1 or sample.shape[0] < 1:
            raise InputError(
                f"filter input: expected shape (C,) with C >= 1, got {sample.shape}",
                code="bad_input",
            )
        if self._x is not None and sample.shape != self._x.shape:
            raise InputError(
                f"filter input: expected {self._x.shape[0]} channels as before, got "
                f"{sample.shape[0]}",
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
        if self._t is not None and when < self._t:
            raise InputError(
                f"filter time went backwards: {when} s after {self._t} s", code="bad_time"
            )
        return sample, when

    def __call__(self, x, t: float) -> np.ndarray:
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

    def filter_series(self, x, t) -> np.ndarray:
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

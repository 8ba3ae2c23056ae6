"""The fixed-interval (Rauch-Tung-Striebel) smoother: the live Kalman filter's offline twin.

Smooths a whole recorded series over channels (points, weights: just C numbers, as in
``filters``): the same constant-velocity model as ``filters.KalmanFilter`` run forward and
then backward (Rauch, Tung & Striebel, AIAA J. 1965), so each frame is estimated from the
frames after it as well as before: less noise, and no lag. Offline only, the model can
also read its process noise off the series (maximum likelihood). Pure numpy, no I/O.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .filters import check_positive

__all__ = ["RTSSmoother", "estimate_acceleration"]

# ``estimate_acceleration``'s search, in units of the noise per s^2: a coarse grid of
# factor 4 from 16 to 4^10 (a face at 0.1-0.5 mm of noise lands near 10^3-10^4), then two
# refinements around the best (factors sqrt 2 and 2^(1/4)): 13 forward passes.
_SEARCH_LOW = 16.0
_SEARCH_STEPS = 9
_SEARCH_FACTOR = 4.0


def _sanitize_series(x: npt.ArrayLike, t: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """A series (F, C) float64 (a private copy) and its times (F,); F may be 0 or 1."""
    try:
        series = np.array(x, dtype=np.float64)
        times = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("smoother input is not a numeric array", code="bad_input") from None
    if series.ndim != 2 or series.shape[1] < 1:
        raise InputError(
            f"smoother input: expected shape (F, C) with C >= 1, got {series.shape}",
            code="bad_input",
        )
    if times.shape != (series.shape[0],):
        raise InputError(
            f"smoother times: expected shape ({series.shape[0]},), one per frame, got "
            f"{times.shape}",
            code="bad_input",
        )
    finite = np.isfinite(series).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise InputError(f"smoother input: frame {bad} has NaN or Inf values", code="non_finite")
    if not np.isfinite(times).all():
        bad = int(np.flatnonzero(~np.isfinite(times))[0])
        raise InputError(f"smoother times: time {bad} is {times[bad]}", code="non_finite")
    back = np.flatnonzero(np.diff(times) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(
            f"smoother times went backwards: frame {i} at {times[i]} s after {times[i - 1]} s",
            code="bad_time",
        )
    return series, times


class _Covariances:
    """The 2 x 2 recursion, per frame, once per distinct process noise q (Q of them).

    It depends on the times and q only: one recursion serves every channel of one
    acceleration, on (Q,) arrays, and ``channel`` spreads a (..., Q) result over the C
    channels (Q stays small when channels share few accelerations, as
    ``estimate_acceleration``'s grid makes them, so memory is F x Q, not F x C). ``gain``
    (F, 2, Q): the update's Kalman gain at frame i (0 where nothing was measured: frame 0,
    repeated times); ``innovation_var`` (F, Q): the predicted measurement's variance S;
    ``smoother_gain`` (F, 2, 2, Q): G[i] = P[i] A[i+1]^T P_pred[i+1]^-1; ``filtered`` and
    ``predicted`` (F, 3, Q): P and P_pred as (p00, p01, p11).
    """

    def __init__(self, times: np.ndarray, r: float, channel_q: np.ndarray) -> None:
        q, inverse = np.unique(channel_q, return_inverse=True)
        # Channel c's recursion is column inverse[c]; None: every channel shares one.
        self.inverse = None if q.size == 1 else inverse.reshape(-1)
        frames, size = times.shape[0], q.shape[0]
        self.gain = np.zeros((frames, 2, size))
        self.innovation_var = np.ones((frames, size))
        self.smoother_gain = np.zeros((frames, 2, 2, size))
        self.filtered = np.zeros((frames, 3, size))
        self.predicted = np.zeros((frames, 3, size))
        # KalmanFilter's start: the first sample, at rest with the velocity of one second
        # of the acceleration std.
        p00, p01, p11 = np.full(size, r), np.zeros(size), q.copy()
        if frames:
            self.filtered[0] = self.predicted[0] = (p00, p01, p11)
        for i in range(1, frames):
            dt = float(times[i] - times[i - 1])
            if dt == 0.0:
                # A repeated time: nothing happened (the live filter returns the previous
                # estimate); the backward pass copies the next frame (G = I).
                self.smoother_gain[i - 1, 0, 0] = self.smoother_gain[i - 1, 1, 1] = 1.0
                self.filtered[i] = self.predicted[i] = (p00, p01, p11)
                continue
            # predict: P_pred = A P A^T + Q, A = [[1, dt], [0, 1]], Q = q g g^T, g = (dt^2/2, dt)
            a00 = p00 + dt * (2.0 * p01 + dt * p11) + q * (dt**4 / 4.0)
            a01 = p01 + dt * p11 + q * (dt**3 / 2.0)
            a11 = p11 + q * (dt * dt)
            # G[i-1] = P A^T P_pred^-1, P frame i-1's; P_pred^-1 = [[a11, -a01], [-a01, a00]] / det
            inv = 1.0 / (a00 * a11 - a01 * a01)
            m00, m10 = p00 + dt * p01, p01 + dt * p11
            self.smoother_gain[i - 1] = (
                ((m00 * a11 - p01 * a01) * inv, (p01 * a00 - m00 * a01) * inv),
                ((m10 * a11 - p11 * a01) * inv, (p11 * a00 - m10 * a01) * inv),
            )
            # update with the position measurement
            s = a00 + r
            k0, k1 = a00 / s, a01 / s
            self.gain[i] = (k0, k1)
            self.innovation_var[i] = s
            self.predicted[i] = (a00, a01, a11)
            p00, p01, p11 = a00 - k0 * a00, a01 - k0 * a01, a11 - k1 * a01
            self.filtered[i] = (p00, p01, p11)

    def channel(self, values: np.ndarray) -> np.ndarray:
        """(..., Q) per distinct q -> (..., C) per channel (as is when all share one q)."""
        return values if self.inverse is None else values[..., self.inverse]

    def smoothed_position_var(self) -> np.ndarray:
        """(F, Q) variance of the smoothed position: P_s = P + G (P_s[i+1] - P_pred[i+1]) G^T."""
        frames = self.filtered.shape[0]
        out = np.empty((frames, self.filtered.shape[2]))
        if frames == 0:
            return out
        s00, s01, s11 = self.filtered[-1]
        out[-1] = s00
        for i in range(frames - 2, -1, -1):
            f00, f01, f11 = self.filtered[i]
            b00, b01, b11 = self.predicted[i + 1]
            d00, d01, d11 = s00 - b00, s01 - b01, s11 - b11
            (g00, g01), (g10, g11) = self.smoother_gain[i]
            # G D G^T for a symmetric D
            h00, h01 = g00 * d00 + g01 * d01, g00 * d01 + g01 * d11
            h10, h11 = g10 * d00 + g11 * d01, g10 * d01 + g11 * d11
            s00 = f00 + h00 * g00 + h01 * g01
            s01 = f01 + h00 * g10 + h01 * g11
            s11 = f11 + h10 * g10 + h11 * g11
            out[i] = s00
        return out


class RTSSmoother:
    """A fixed-interval (Rauch-Tung-Striebel) smoother over C channels: ``KalmanFilter`` offline.

    The same constant-velocity model, parameters and start as ``filters.KalmanFilter`` (the
    first sample taken as it is, at rest; a repeated time ignored); its forward pass is
    that filter's output. The backward pass then corrects every frame with what came after
    it, ``x_s[i] = x[i] + G[i] (x_s[i+1] - A[i+1] x[i])`` with ``G[i] = P[i] A[i+1]^T
    P_pred[i+1]^-1``, so a step or a ramp is not delayed. As in the filter, every channel
    shares the covariances (one noise model, one clock): the 2 x 2 recursion runs once per
    frame on scalars and the channels are whole-array operations. Frames are a loop: both
    passes are recursive in time.

    Parameters
    ----------
    noise : float
        Measurement noise std, > 0.
    acceleration : float or (C,) float
        Process noise: std of the acceleration, > 0 (units/s^2, as ``KalmanFilter``'s);
        one per channel for channels that move differently (``estimate_acceleration``).

    Examples
    --------
    >>> t = np.arange(5) / 60.0
    >>> RTSSmoother(noise=0.01, acceleration=4.8).smooth(np.zeros((5, 3)), t).shape
    (5, 3)
    """

    def __init__(self, noise: float, acceleration: float | npt.ArrayLike) -> None:
        self.noise = check_positive("noise", noise)
        if isinstance(acceleration, int | float | np.floating | np.integer):
            self.acceleration: float | np.ndarray = check_positive(
                "acceleration", float(acceleration)
            )
        else:
            values = np.asarray(acceleration, dtype=np.float64)
            if (
                values.ndim != 1
                or values.size < 1
                or not (np.isfinite(values) & (values > 0)).all()
            ):
                raise InputError(
                    "acceleration must be a number or a (C,) array, finite and > 0",
                    code="bad_filter",
                )
            self.acceleration = values

    def _covariances(self, times: np.ndarray, channels: int) -> _Covariances:
        q = np.atleast_1d(np.square(np.asarray(self.acceleration, dtype=np.float64)))
        if q.size > 1 and q.size != channels:
            raise InputError(
                f"smoother: {q.size} accelerations for {channels} channels", code="bad_input"
            )
        return _Covariances(times, self.noise * self.noise, q)

    def smooth(self, x: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        """The smoothed series: each frame estimated from the whole series.

        Parameters
        ----------
        x : (F, C) float
            Finite; F = 0 or 1 passes through (one sample is its own best estimate).
        t : (F,) float
            Seconds, finite and non-decreasing (variable steps are fine).

        Returns
        -------
        (F, C) float64

        Raises
        ------
        InputError
            ``bad_input`` for a shape, ``non_finite`` for a NaN or Inf (naming the frame),
            ``bad_time`` for times that go backwards.
        """
        series, times = _sanitize_series(x, t)
        covariances = self._covariances(times, series.shape[1])
        position, velocity, _ = _forward(series, times, covariances)
        _backward(position, velocity, times, covariances)
        return position

    def filter_series(self, x: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        """The forward pass alone (F, C): ``KalmanFilter(noise, acceleration)``'s output."""
        series, times = _sanitize_series(x, t)
        return _forward(series, times, self._covariances(times, series.shape[1]))[0]

    def smoothed_std(self, t: npt.ArrayLike) -> np.ndarray:
        """The model's std of each smoothed position: the noise the smoothing leaves.

        It depends on the times only: (F, 1) for a shared acceleration, (F, C) for one per
        channel.
        """
        _, times = _sanitize_series(np.zeros((np.size(t), 1)), t)
        channels = np.size(self.acceleration)
        covariances = self._covariances(times, channels)
        std: np.ndarray = np.sqrt(covariances.channel(covariances.smoothed_position_var()))
        return std

    def log_likelihood(self, x: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        """(C,) each channel's mean log-likelihood per measured sample under the model.

        From the forward pass's innovations (prediction errors) and their variance; the
        frames that measure nothing new (the first, repeated times) do not count. NaN with
        fewer than two distinct times.
        """
        series, times = _sanitize_series(x, t)
        covariances = self._covariances(times, series.shape[1])
        _, _, total = _forward(series, times, covariances)
        measured = int((covariances.gain[:, 0, 0] > 0).sum())
        if measured == 0:
            return np.full(series.shape[1], np.nan)
        return total / measured


def _forward(
    series: np.ndarray, times: np.ndarray, covariances: _Covariances
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filtered positions and velocities (F, C), and each channel's log-likelihood sum (C,).

    Overwrites ``series`` (a private copy) with the positions, frame by frame: frame i is
    read before it is written.
    """
    frames = series.shape[0]
    position = series
    velocity = np.zeros_like(series)
    log_likelihood = np.zeros(series.shape[1])
    for i in range(1, frames):
        dt = float(times[i] - times[i - 1])
        if dt == 0.0:
            position[i] = position[i - 1]
            velocity[i] = velocity[i - 1]
            continue
        k0, k1 = covariances.channel(covariances.gain[i])
        s = covariances.channel(covariances.innovation_var[i])
        predicted = position[i - 1] + dt * velocity[i - 1]
        innovation = series[i] - predicted
        log_likelihood -= 0.5 * (innovation * innovation / s + np.log(2.0 * math.pi * s))
        position[i] = predicted + k0 * innovation
        velocity[i] = velocity[i - 1] + k1 * innovation
    return position, velocity, log_likelihood


def _backward(
    position: np.ndarray, velocity: np.ndarray, times: np.ndarray, covariances: _Covariances
) -> None:
    """Smooth the filtered positions and velocities in place, last frame to first."""
    for i in range(position.shape[0] - 2, -1, -1):
        dt = float(times[i + 1] - times[i])
        # x_s[i+1] - A x[i], both components
        d_position = position[i + 1] - (position[i] + dt * velocity[i])
        d_velocity = velocity[i + 1] - velocity[i]
        (g00, g01), (g10, g11) = covariances.channel(covariances.smoother_gain[i])
        position[i] += g00 * d_position + g01 * d_velocity
        velocity[i] += g10 * d_position + g11 * d_velocity


def estimate_acceleration(x: npt.ArrayLike, t: npt.ArrayLike, noise: float) -> np.ndarray:
    """(C,) each channel's process noise (acceleration std, units/s^2) of greatest likelihood.

    Maximises ``RTSSmoother(noise, a).log_likelihood(x, t)`` per channel over a: a grid of
    factor 4 from 16 to 4^10 noise/s^2, then factors sqrt 2 and 2^(1/4) around each
    channel's best; all channels in each forward pass (13 passes). The measurement noise
    is known (the rig's); only how hard each channel accelerates is read off the series,
    which a live filter cannot do before it has seen it.

    Parameters
    ----------
    x : (F, C) float
        F >= 3 frames at three or more distinct times.
    t : (F,) float
    noise : float
        Measurement noise std, > 0.
    """
    sigma = check_positive("noise", noise)
    series, times = _sanitize_series(x, t)
    if np.unique(times).size < 3:
        raise InputError(
            f"estimating the acceleration needs 3 or more frames at distinct times, got "
            f"{np.unique(times).size}",
            code="bad_input",
        )
    channels = series.shape[1]

    def likelihood(units: np.ndarray) -> np.ndarray:
        return RTSSmoother(sigma, units * sigma).log_likelihood(series, times)

    grid = _SEARCH_LOW * _SEARCH_FACTOR ** np.arange(_SEARCH_STEPS)
    scores = np.array([likelihood(np.full(channels, a)) for a in grid])  # (G, C)
    best = grid[scores.argmax(axis=0)]
    best_score = scores.max(axis=0)
    for factor in (math.sqrt(2.0), 2.0**0.25):
        centre = best.copy()
        for candidate in (centre / factor, centre * factor):
            score = likelihood(candidate)
            better = score > best_score
            best = np.where(better, candidate, best)
            best_score = np.where(better, score, best_score)
    estimate: np.ndarray = best * sigma
    return estimate

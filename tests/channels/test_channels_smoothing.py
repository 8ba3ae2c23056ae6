"""A publisher's smoothing (PROTOCOL.md §5.1.1) through a real channel: Kalman, auto, refusal,
and auto taking a calibrate's noise (§5.2.5)."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import Calibrate, Calibrated, ChannelLive, ErrorCode, Hello, Smoothing
from facecast.rig.filters import KALMAN_ACCELERATION, KalmanFilter, OneEuroFilter
from facecast.rig.rebase import rebase
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, refused, tiny_rig, write_rigs

pytestmark = pytest.mark.anyio


async def test_a_publishers_kalman_smoothing_reaches_the_watchers(settings, rigs, ws_impl):
    rig = rigs["alpha"]
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(4)]
    reference = KalmanFilter(noise=0.05, acceleration=300.0 * 0.05)
    expected = [
        rig.weights(reference(p.astype(np.float64).reshape(-1), ts).reshape(p.shape))
        for p, ts in frames
    ]
    smoothing = Smoothing(filter="kalman", acceleration=300.0, noise=0.05)
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "alpha")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha", smoothing=smoothing)
        await watcher.next(ChannelLive)
        for seq, (p, ts) in enumerate(frames):
            await publisher.send(seq, p, ts=ts)
        result = await watcher.result_with_seq(3)
        await publisher.close()
        await watcher.close()

    np.testing.assert_allclose(result.weights, expected[3].astype(np.float32), atol=1e-6)
    assert not np.allclose(result.weights, rig.weights(frames[3][0]), atol=1e-4)


async def test_a_kalman_publisher_on_a_rig_fitted_without_noise_is_refused(settings, ws_impl):
    hello = Hello(rig="alpha", smoothing=Smoothing(filter="kalman"))  # alpha: fitted exactly
    async with run_server(settings, ws=ws_impl) as server:
        error, _ = await refused(channel_url(server.ws_url, "stage", "publish"), hello=hello)
        # The refusal claimed nothing: another publisher takes the channel at once.
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.close()

    assert error.code == ErrorCode.INVALID_FIELD and "smoothing.noise" in error.message


async def _published(settings, ws_impl: str, rig_id: str, frames, smoothing: Smoothing):
    """The publisher's ready and a watcher's result for the last of ``frames``."""
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", rig_id)
        publisher = await Publisher.open(server.ws_url, "stage", rig_id, smoothing=smoothing)
        await watcher.next(ChannelLive)
        for seq, (p, ts) in enumerate(frames):
            await publisher.send(seq, p, ts=ts)
        result = await watcher.result_with_seq(len(frames) - 1)
        await publisher.close()
        await watcher.close()
    return publisher.ready, result


def _filtered_weights(rig, frames, point_filter) -> np.ndarray:
    """The weights of the last of ``frames`` after ``point_filter`` ran over them all."""
    smoothed = [point_filter(p.astype(np.float64).reshape(-1), ts) for p, ts in frames]
    return rig.weights(smoothed[-1].reshape(frames[-1][0].shape))


async def test_a_publishers_auto_smoothing_on_a_noise_rig_runs_the_kalman_filter(settings, ws_impl):
    rig = tiny_rig(7, noise=0.05)
    write_rigs(settings.rigs_dir, {"noisy": rig})
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(4)]
    kalman = KalmanFilter(noise=0.05, acceleration=KALMAN_ACCELERATION * 0.05)
    expected = _filtered_weights(rig, frames, kalman)

    ready, result = await _published(settings, ws_impl, "noisy", frames, Smoothing())

    assert ready.smoothing == "kalman"
    np.testing.assert_allclose(result.weights, expected.astype(np.float32), atol=1e-6)


async def test_a_publishers_auto_smoothing_on_an_exact_rig_runs_the_one_euro_filter(
    settings, rigs, ws_impl
):
    rig = rigs["alpha"]  # fitted exactly
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(4)]
    expected = _filtered_weights(rig, frames, OneEuroFilter(min_cutoff=2.0, beta=0.5))

    ready, result = await _published(settings, ws_impl, "alpha", frames, Smoothing(beta=0.5))

    assert ready.smoothing == "one-euro"
    np.testing.assert_allclose(result.weights, expected.astype(np.float32), atol=1e-6)


async def test_a_publishers_point_filter_starts_afresh_when_ts_goes_back(settings, ws_impl):
    # A performer's clock that jumps back (the tracker restarted): the frame after the
    # jump is the filter's first, passed through as it is, as on /v1/stream.
    rig = tiny_rig(7, noise=0.05)
    write_rigs(settings.rigs_dir, {"noisy": rig})
    frames = [(points(rig, seed), 10.0 + 0.1 * seed) for seed in range(4)]
    frames.append((points(rig, 9), 0.5))  # back in time

    _, result = await _published(settings, ws_impl, "noisy", frames, Smoothing(filter="kalman"))

    np.testing.assert_allclose(result.weights, rig.weights(frames[-1][0]).astype(np.float32),
                               atol=1e-6)  # fmt: skip


async def _calibrated_then_published(settings, ws_impl, rig_id, neutral, noise, frames):
    """A publisher with an auto smoothing (the page's ``hello``) on ``rig_id`` that
    calibrates on ``neutral`` with ``noise``, then publishes ``frames``: its ``ready``, its
    ``calibrated`` and a watcher's result for the last frame."""
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", rig_id)
        publisher = await Publisher.open(server.ws_url, "stage", rig_id, smoothing=Smoothing())
        await watcher.next(ChannelLive)
        calibrate = Calibrate(points=neutral, noise=noise)
        await publisher.ws.send(publisher.protocol.send(calibrate))
        while not isinstance(calibrated := await publisher.queue.get(), Calibrated):
            pass
        for seq, (p, ts) in enumerate(frames):
            await publisher.send(seq, p, ts=ts)
        result = await watcher.result_with_seq(len(frames) - 1)
        await publisher.close()
        await watcher.close()
    return publisher.ready, calibrated, result


async def test_an_auto_smoothing_on_an_exact_rig_takes_the_calibrates_noise(
    settings, rigs, ws_impl
):
    # The page's and `facecast perform`'s case: a generic character is fitted exactly, so
    # at the hello no noise is known and auto starts as the one-euro filter; a calibrate
    # with a noise re-bases it noise-aware, and that σ is the Kalman's (PROTOCOL.md
    # §5.2.5): the watchers get the points filtered by it, on their rig re-based as the
    # calibrate says.
    rig = rigs["alpha"]  # fitted exactly
    neutral = points(rig, 99)
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(5)]
    rebased = rebase(rig, neutral, noise=0.02)
    sigma = rebased.fit_report["rebase"]["noise"]  # the re-base's σ: the Kalman's
    kalman = KalmanFilter(noise=sigma, acceleration=KALMAN_ACCELERATION * sigma)
    expected = _filtered_weights(rebased, frames, kalman)

    ready, calibrated, result = await _calibrated_then_published(
        settings, ws_impl, "alpha", neutral, 0.02, frames
    )

    assert ready.smoothing == "one-euro"
    assert calibrated.active and calibrated.smoothing == "kalman"
    np.testing.assert_allclose(result.weights, expected.astype(np.float32), atol=1e-6)
    one_euro = _filtered_weights(rebased, frames, OneEuroFilter())
    assert not np.allclose(result.weights, one_euro, atol=1e-4)


async def test_a_calibrate_without_noise_leaves_the_one_euro_filter(settings, rigs, ws_impl):
    rig = rigs["alpha"]
    neutral = points(rig, 99)
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(5)]
    expected = _filtered_weights(rig.calibrated(neutral), frames, OneEuroFilter())

    _, calibrated, result = await _calibrated_then_published(
        settings, ws_impl, "alpha", neutral, None, frames
    )

    assert calibrated.smoothing == "one-euro"
    np.testing.assert_allclose(result.weights, expected.astype(np.float32), atol=1e-6)


async def test_a_noise_rigs_kalman_keeps_its_own_noise_at_a_calibrate(settings, ws_impl):
    # A rig fitted with noise (the performer's own) runs the Kalman on its fitted noise from
    # the hello on; a calibrate's noise does not change that filter.
    rig = tiny_rig(7, noise=0.05)
    write_rigs(settings.rigs_dir, {"noisy": rig})
    neutral = points(rig, 99)
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(5)]
    kalman = KalmanFilter(noise=0.05, acceleration=KALMAN_ACCELERATION * 0.05)
    expected = _filtered_weights(rebase(rig, neutral, noise=0.02), frames, kalman)

    ready, calibrated, result = await _calibrated_then_published(
        settings, ws_impl, "noisy", neutral, 0.02, frames
    )

    assert ready.smoothing == "kalman" and calibrated.smoothing == "kalman"
    np.testing.assert_allclose(result.weights, expected.astype(np.float32), atol=1e-6)

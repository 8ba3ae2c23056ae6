"""A publisher's Kalman smoothing (PROTOCOL.md §5.1.1) through a real channel, and its refusal."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import ChannelLive, ErrorCode, Hello, Smoothing
from facecast.rig.filters import KalmanFilter
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, refused

pytestmark = pytest.mark.anyio


async def test_a_publishers_kalman_smoothing_reaches_the_watchers(settings, rigs):
    rig = rigs["alpha"]
    frames = [(points(rig, seed), 0.1 * seed) for seed in range(4)]
    reference = KalmanFilter(noise=0.05, acceleration=300.0 * 0.05)
    expected = [
        rig.weights(reference(p.astype(np.float64).reshape(-1), ts).reshape(p.shape))
        for p, ts in frames
    ]
    smoothing = Smoothing(filter="kalman", acceleration=300.0, noise=0.05)
    async with run_server(settings) as server:
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


async def test_a_kalman_publisher_on_a_rig_fitted_without_noise_is_refused(settings):
    hello = Hello(rig="alpha", smoothing=Smoothing(filter="kalman"))  # alpha: fitted exactly
    async with run_server(settings) as server:
        error, _ = await refused(channel_url(server.ws_url, "stage", "publish"), hello=hello)
        # The refusal claimed nothing: another publisher takes the channel at once.
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.close()

    assert error.code == ErrorCode.INVALID_FIELD and "smoothing.noise" in error.message

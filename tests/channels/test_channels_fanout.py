"""One process: fan-out per key, exact results, late joiners, publisher leave/return, busy."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import ChannelIdle, ChannelLive, ErrorCode, Hello, Ready, Result
from facecast.server.channels.fanout import ChannelFrame, key_state
from facecast.server.testing import run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points, refused, wait_for

pytestmark = pytest.mark.anyio


async def test_three_rigs_cost_three_clones_per_frame_whatever_the_viewer_count(
    settings, rigs, ws_impl
):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = {
            rig_id: [await Watcher.open(server.ws_url, "stage", rig_id) for _ in range(4)]
            for rig_id in RIG_IDS
        }
        publisher = await Publisher.open(server.ws_url, "stage", RIG_IDS[0])
        frames = [points(rigs[RIG_IDS[0]], seed) for seed in range(10)]
        for seq, pts in enumerate(frames):
            await publisher.send(seq, pts)
            for group in watchers.values():
                for watcher in group:
                    await watcher.result_with_seq(seq)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            info = (await http.get("/v1/channels/stage")).json()

    assert info["clones"] == 3 * info["frames"]
    assert info["clones_per_frame"] == 3.0
    assert info["viewers_per_rig"] == {rig_id: 4 for rig_id in RIG_IDS}


async def test_watchers_get_single_frame_clones_exactly_in_f32(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = {
            rig_id: await Watcher.open(server.ws_url, "stage", rig_id) for rig_id in RIG_IDS
        }
        publisher = await Publisher.open(server.ws_url, "stage", RIG_IDS[0])
        pts = points(rigs[RIG_IDS[0]], 3)
        await publisher.send(7, pts)
        received = {rig_id: await w.result_with_seq(7) for rig_id, w in watchers.items()}

    for rig_id, result in received.items():
        expected = rigs[rig_id].weights(pts).astype(np.float32)
        assert result.weights.dtype == np.float32
        np.testing.assert_array_equal(result.weights, expected)


async def test_vertices_watchers_get_the_blend_of_the_weights(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta", output="vertices")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        pts = points(rigs["alpha"], 1)
        await publisher.send(0, pts)
        result = await watcher.result_with_seq(0)

    rig = rigs["beta"]
    np.testing.assert_array_equal(result.vertices, rig.blend(rig.weights(pts)))


async def test_results_to_watchers_carry_server_ts(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "alpha")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        before = time.time()
        await publisher.send(0, points(rigs["alpha"], 0))
        result = await watcher.result_with_seq(0)
        after = time.time()
        raw = await _raw_result(server, rigs)

    assert isinstance(raw["server_ts"], float)
    # The protocol package decodes it too (PROTOCOL.md §5.2.2), for Python watchers.
    assert before <= result.server_ts <= after


async def _raw_result(server, rigs) -> dict:
    import msgpack
    import websockets

    url = channel_url(server.ws_url, "stage", "watch", {"rig": "alpha"})
    async with websockets.connect(url, subprotocols=["facecast.v1"]) as ws:
        while True:
            message = msgpack.unpackb(await ws.recv())
            if message["type"] == "result":
                return message


async def test_late_joiner_gets_the_newest_frame_at_once(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        early = await Watcher.open(server.ws_url, "stage", "alpha")
        for seq in range(5):
            await publisher.send(seq, points(rigs["alpha"], seq))
        await early.result_with_seq(4)
        same_key = await Watcher.open(server.ws_url, "stage", "alpha")
        new_key = await Watcher.open(server.ws_url, "stage", "gamma")
        first_same = await same_key.next(Result)
        first_new = await new_key.next(Result)

    assert first_same.seq == 4
    assert first_new.seq == 4
    np.testing.assert_array_equal(
        first_new.weights, rigs["gamma"].weights(points(rigs["alpha"], 4)).astype(np.float32)
    )


async def test_watchers_see_the_publisher_leave_and_return(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        first = await watcher.next(ChannelIdle, ChannelLive)
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        live = await watcher.next(ChannelIdle, ChannelLive)
        await publisher.close()
        idle = await watcher.next(ChannelIdle, ChannelLive)
        again = await Publisher.open(server.ws_url, "stage", "alpha")
        live_again = await watcher.next(ChannelIdle, ChannelLive)
        await again.send(11, points(rigs["alpha"], 11))
        resumed = await watcher.result_with_seq(11)
        open_throughout = not watcher.closed.is_set()
    await asyncio.wait_for(watcher.closed.wait(), 5.0)

    assert [type(m) for m in (first, live, idle, live_again)] == [
        ChannelIdle, ChannelLive, ChannelIdle, ChannelLive,
    ]  # fmt: skip
    assert resumed.seq == 11
    assert open_throughout
    assert watcher.close_code == 1001  # the server going away, not the publisher


def _publisher_gone(server, name: str) -> bool:
    channel = server.app.state.channels.channels.get(name)
    return channel is None or (channel.publisher is None and channel.claimed_by is None)


async def test_second_publisher_is_refused_with_channel_busy(settings, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        first = await Publisher.open(server.ws_url, "stage", "alpha")
        error, code = await refused(
            channel_url(server.ws_url, "stage", "publish"), hello=Hello(rig="alpha")
        )
        await first.close()
        # The client's close returns before the server has let the publisher go (the
        # legacy websockets stack takes longer): wait for it, not for a fixed time.
        await wait_for(lambda: _publisher_gone(server, "stage"), what="first publisher gone")
        second = await Publisher.open(server.ws_url, "stage", "alpha")

    assert error.code == ErrorCode.CHANNEL_BUSY and error.fatal
    assert code == 1008
    assert isinstance(second.ready, Ready)


async def test_publisher_receives_its_own_results(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        pts = points(rigs["alpha"], 2)
        await publisher.send(0, pts)
        while not isinstance(message := await publisher.queue.get(), Result):
            pass

    np.testing.assert_array_equal(message.weights, rigs["alpha"].weights(pts).astype(np.float32))


async def test_watching_an_unknown_rig_is_refused(settings, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        error, _ = await refused(channel_url(server.ws_url, "stage", "watch", {"rig": "nobody"}))

    assert error.code == ErrorCode.UNKNOWN_RIG


def test_weights_clones_run_inline_until_a_new_calibration_needs_a_refit(rigs):
    rig = rigs["alpha"]
    pts = points(rig, 3)
    weights = key_state(("alpha", "weights", "f32"), rig)
    vertices = key_state(("alpha", "vertices", "f32"), rig)
    calibrated = ChannelFrame(seq=2, ts=0.1, points=pts, neutral=pts, neutral_id="n1")

    plain = ChannelFrame(seq=1, ts=0.0, points=pts)
    before = (weights.inline(plain), vertices.inline(plain), weights.inline(calibrated))
    weights.clone(calibrated, 0.0)  # the refit happens once, in whichever thread clones

    assert before == (True, False, False)
    assert weights.inline(calibrated) is True

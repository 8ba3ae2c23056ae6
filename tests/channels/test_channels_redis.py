"""Channels across processes on a real redis-server: fan-out, presence, and Redis dying.

Each "process" is a separate app with its own event loop, hub and Redis connections
(``run_server``); they share only Redis and the rig directory, as replicas do.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools

import httpx
import numpy as np
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import ChannelIdle, ChannelLive, Error, ErrorCode, Hello, Result
from facecast.server.channels.hub import RECLAIM_WAIT
from facecast.server.channels.members import STALE_AFTER
from facecast.server.testing import run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points, refused, wait_for
from .conftest import TOKENS

pytestmark = pytest.mark.anyio


@pytest.fixture
def redis_settings(settings, redis_server):
    return dataclasses.replace(settings, redis_url=redis_server.url)


async def _live(watcher: Watcher) -> None:
    while not isinstance(await watcher.next(ChannelIdle, ChannelLive, timeout=10), ChannelLive):
        pass


async def test_a_publisher_on_one_process_reaches_viewers_on_another(redis_settings, rigs, ws_impl):
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
    ):
        watchers = {rig_id: await Watcher.open(b.ws_url, "stage", rig_id) for rig_id in RIG_IDS}
        publisher = await Publisher.open(a.ws_url, "stage", "alpha")
        for watcher in watchers.values():
            await _live(watcher)
        sent = [points(rigs["alpha"], seed) for seed in range(5)]
        for seq, pts in enumerate(sent):
            await publisher.send(seq, pts)
            for watcher in watchers.values():
                await watcher.result_with_seq(seq)
        async with httpx.AsyncClient(base_url=b.base_url) as http:
            info = {}

            async def both_processes_reported() -> bool:
                # Each process reports itself to Redis about once a second.
                info.update((await http.get("/v1/channels/stage")).json())
                return len(info["processes"]) == 2

            await wait_for(both_processes_reported, what="both processes' reports")

    for rig_id, watcher in watchers.items():
        by_seq = {r.seq: r for r in watcher.results}
        for seq, pts in enumerate(sent):
            expected = rigs[rig_id].weights(pts).astype(np.float32)
            np.testing.assert_array_equal(by_seq[seq].weights, expected)
    assert info["publisher"] is True
    assert info["clones_per_frame"] == 3.0  # process B clones for its own three keys
    assert info["viewers_per_rig"] == {rig_id: 1 for rig_id in RIG_IDS}
    assert len(info["processes"]) == 2


async def test_a_second_publisher_on_another_process_is_refused(redis_settings, ws_impl):
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
    ):
        first = await Publisher.open(a.ws_url, "stage", "alpha")
        error, _ = await refused(
            channel_url(b.ws_url, "stage", "publish"), hello=Hello(rig="alpha")
        )
        await first.close()
        # The client's close returns before process a has released the channel's lock in
        # Redis; a drops the channel after that release.
        await wait_for(lambda: "stage" not in a.app.state.channels.channels, what="lock released")
        second = await Publisher.open(b.ws_url, "stage", "alpha")

    assert error.code == ErrorCode.CHANNEL_BUSY
    assert second.ready.rig == "alpha"


async def test_remote_viewers_see_the_publisher_leave_and_return(redis_settings, rigs, ws_impl):
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
    ):
        watcher = await Watcher.open(b.ws_url, "stage", "beta")
        publisher = await Publisher.open(a.ws_url, "stage", "alpha")
        await _live(watcher)
        await publisher.close()
        idle = await watcher.next(ChannelIdle, ChannelLive, timeout=10)
        again = await Publisher.open(a.ws_url, "stage", "alpha")
        live = await watcher.next(ChannelIdle, ChannelLive, timeout=10)
        await again.send(3, points(rigs["alpha"], 3))
        resumed = await watcher.result_with_seq(3)

    assert isinstance(idle, ChannelIdle) and isinstance(live, ChannelLive)
    assert resumed.seq == 3


async def test_a_publisher_closing_and_coming_back_at_once_gets_its_channel(
    redis_settings, ws_impl
):
    # Issue #25 item 8: the client's close returns before the server has released the
    # channel's lock in Redis; a publisher coming straight back got CHANNEL_BUSY.
    async with run_server(redis_settings, ws=ws_impl) as a:
        readies = []
        for _ in range(20):
            publisher = await Publisher.open(a.ws_url, "stage", "alpha")
            readies.append(publisher.ready.rig)
            await publisher.close()

    assert readies == ["alpha"] * 20


#: With auth on, a second publisher token: another performer.
AUTH_TOKENS = {**TOKENS, "other-publisher-token": frozenset({"publisher"})}


@pytest.fixture
async def auth_servers(redis_settings, ws_impl):
    """Two processes on one Redis, auth on."""
    settings = dataclasses.replace(redis_settings, auth=True, tokens=AUTH_TOKENS)
    async with run_server(settings, ws=ws_impl) as a, run_server(settings, ws=ws_impl) as b:
        yield a, b


def _hubs(servers):
    return [server.app.state.channels for server in servers]


#: Where the publisher's second connection goes: the process of its first, or another.
RETURNS_TO = pytest.mark.parametrize("returns_to", [0, 1], ids=["same-process", "other-process"])


@RETURNS_TO
async def test_a_returning_publisher_takes_its_channel_back_from_its_stale_connection(
    auth_servers, rigs, returns_to
):
    # A blip: the publisher reconnects while its old connection is still open on the
    # server (not yet noticed gone); the same token gets the channel, the old one ends.
    # The old one is taken for stale once silent for the hubs' stale_after: shortened
    # from STALE_AFTER (1 s) here; the test that a sender keeps its channel keeps it.
    a, b = auth_servers
    for hub in _hubs(auth_servers):
        assert hub.stale_after == STALE_AFTER  # the production default, unless set
        hub.stale_after = STALE_AFTER / 4
    watcher = await Watcher.open(b.ws_url, "stage", "beta", token="viewer-token")
    stale = await Publisher.open(a.ws_url, "stage", "alpha", token="publisher-token")
    await _live(watcher)
    server = auth_servers[returns_to]
    again = await Publisher.open(server.ws_url, "stage", "alpha", token="publisher-token")
    ended = await asyncio.wait_for(stale.queue.get(), 10)
    pts = points(rigs["alpha"], 3)
    await again.send(3, pts)
    resumed = await watcher.result_with_seq(3, timeout=10)
    await again.close()
    await watcher.close()

    assert again.ready.rig == "alpha"
    assert isinstance(ended, Error) and ended.code == ErrorCode.CHANNEL_BUSY
    assert "same token" in ended.message
    expected = rigs["beta"].weights(pts).astype(np.float32)
    np.testing.assert_array_equal(resumed.weights, expected)


@RETURNS_TO
async def test_a_publisher_that_keeps_sending_keeps_its_channel_from_its_own_token(
    auth_servers, rigs, returns_to
):
    # Two pages of one performer: the one that sends keeps the channel (the other is
    # refused after the hubs' reclaim_wait), so they do not take it from each other in
    # turn. reclaim_wait is shortened from RECLAIM_WAIT (6.5 s, the lock TTL of a dead
    # process, which no process here is) to a few times STALE_AFTER: long enough that a
    # sender silent that long would have lost the channel.
    for hub in _hubs(auth_servers):
        assert hub.reclaim_wait == RECLAIM_WAIT  # the production default, unless set
        hub.reclaim_wait = 2 * STALE_AFTER
    live = await Publisher.open(auth_servers[0].ws_url, "stage", "alpha", token="publisher-token")

    async def keep_sending() -> None:
        for seq in itertools.count():
            await live.send(seq, points(rigs["alpha"], seq % 5))
            await asyncio.sleep(1 / 30)  # a camera's pace, not a wait for an event

    sending = asyncio.create_task(keep_sending())
    url = channel_url(auth_servers[returns_to].ws_url, "stage", "publish")
    try:
        error, _ = await refused(
            url, token="publisher-token", hello=Hello(rig="alpha"), timeout=2 * STALE_AFTER + 5
        )
    finally:
        sending.cancel()
    await live.send(10_000, points(rigs["alpha"], 1))
    while (result := await asyncio.wait_for(live.queue.get(), 5)).seq != 10_000:
        pass
    await live.close()

    assert error.code == ErrorCode.CHANNEL_BUSY
    assert isinstance(result, Result)


async def test_another_token_cannot_take_a_live_publishers_channel(auth_servers, rigs):
    first = await Publisher.open(auth_servers[0].ws_url, "stage", "alpha", token="publisher-token")
    here, there = (channel_url(s.ws_url, "stage", "publish") for s in auth_servers)
    hello = Hello(rig="alpha")
    refused_here, _ = await refused(here, token="other-publisher-token", hello=hello)
    # On another process the holder might have been leaving: refused after RELEASE_WAIT,
    # within the helper's 5 s.
    refused_there, _ = await refused(there, token="other-publisher-token", hello=hello)
    await first.send(1, points(rigs["alpha"], 1))
    result = await asyncio.wait_for(first.queue.get(), 5)
    await first.close()

    assert refused_here.code == refused_there.code == ErrorCode.CHANNEL_BUSY
    assert isinstance(result, Result) and result.seq == 1


async def test_channels_recover_when_redis_is_killed_and_restarted(
    redis_settings, redis_server, rigs, ws_impl
):
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
        httpx.AsyncClient() as http,
    ):

        async def ready(server) -> int:
            return (await http.get(f"{server.base_url}/readyz")).status_code

        await wait_for(lambda: _both(ready, a, b, 200), what="both ready")
        watcher = await Watcher.open(b.ws_url, "stage", "beta")
        publisher = await Publisher.open(a.ws_url, "stage", "alpha")
        await _live(watcher)
        await publisher.send(0, points(rigs["alpha"], 0))
        await watcher.result_with_seq(0)

        redis_server.kill()
        await wait_for(lambda: _both(ready, a, b, 503), what="readyz 503 while redis is down")
        down = (await http.get(f"{a.base_url}/readyz")).json()
        redis_server.start()
        await wait_for(lambda: _both(ready, a, b, 200), what="readyz 200 after restart")

        seq = 1
        got: list[Result] = []

        async def delivered() -> bool:
            nonlocal seq
            await publisher.send(seq, points(rigs["alpha"], seq))
            seq += 1
            got.extend(r for r in watcher.results if r.seq >= 1)
            return bool(got)

        await wait_for(delivered, timeout=15, what="frames through the restarted redis")

    assert down["code"] == "not_ready" and "redis" in down["detail"]
    assert got[0].seq >= 1


async def _both(ready, a, b, status: int) -> bool:
    return await ready(a) == status and await ready(b) == status


async def test_a_watcher_joining_on_another_process_sees_the_channel_live_at_once(
    redis_settings, ws_impl
):
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
    ):
        publisher = await Publisher.open(a.ws_url, "stage", "alpha")
        watcher = await Watcher.open(b.ws_url, "stage", "beta")
        first = await watcher.next(ChannelIdle, ChannelLive)
        await publisher.close()

    assert isinstance(first, ChannelLive)

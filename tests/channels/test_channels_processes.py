"""Channels across real ``facecast serve --redis`` processes: exact fan-out, Redis dying, a stall.

Unlike test_channels_redis.py (servers as threads of this process), each facecast here is
its own interpreter started from the CLI; they share only redis-server and the rig folder.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time

import httpx
import numpy as np
import pytest

from facecast.cli.bench.harness import ServerProcess, facecast_serve
from facecast.client.channel import channel_url
from facecast.protocol import ChannelIdle, ChannelLive, Error, ErrorCode, Hello, Result
from facecast.server.channels.hub import RECLAIM_WAIT

from ._helpers import Publisher, Watcher, points, refused, wait_for

pytestmark = pytest.mark.anyio

#: Generous: a loaded 2-core CI machine starts two interpreters at once.
STARTUP_TIMEOUT = 45.0
#: The publisher's frame rate in the restart test (a performer's pace, far below max_fps).
FRAME_INTERVAL = 0.02
#: How long the stall test stops the publisher's process: past ``members.STALE_AFTER`` and
#: the bus's bound on one Redis call (1 s each), like the stall of a loaded CI run that
#: ended a live channel.
STALL = 1.5
#: The stall test's frame rate: a camera's 30 fps, so that the frames a stall holds back
#: (45) reach the server in one burst within ``rate_burst`` (60), not rate-limited.
CAMERA_INTERVAL = 1 / 30
#: A performer stalled with A sends again this long after A runs again: A then reads B's
#: evicts first, and finds the publisher silent for the stall and this (well below
#: STALE_AFTER) had the stall counted.
CAMERA_LAG = 0.3


def _serve_pair(rigs_dir, redis_server, tmp_path, *extra: str, env: dict[str, str]):
    """Processes A and B on the same redis-server, started together, waited for until ready
    (a generator: stops them when closed)."""
    started: list[ServerProcess] = []
    try:
        for name in ("A", "B"):
            process = facecast_serve(
                rigs_dir, "--redis", redis_server.url, *extra, env=env,
                log_path=tmp_path / f"facecast-{name}.log", name=f"facecast {name}",
            )  # fmt: skip
            started.append(process.start())
        deadline = time.monotonic() + STARTUP_TIMEOUT
        for process in started:
            process.wait_ready(timeout=max(0.0, deadline - time.monotonic()))
        yield tuple(started)
    finally:
        for process in started:
            process.stop()


#: face_lost_after as in conftest's settings: no eased (synthetic) results while frames
#: stop crossing Redis, so every result is the clone of a published frame.
ENV = {"FACECAST_LOG_LEVEL": "warning", "FACECAST_FACE_LOST_AFTER": "30"}


@pytest.fixture
def processes(rigs_dir, redis_server, tmp_path):
    """Processes A and B, both ready, on the same redis-server; stopped at the end."""
    yield from _serve_pair(rigs_dir, redis_server, tmp_path, env=ENV)


@pytest.fixture
def auth_processes(rigs_dir, redis_server, tmp_path):
    """``processes`` with auth on: a publisher's token, a viewer's."""
    tokens = "publisher-token:publisher,viewer-token:viewer"
    yield from _serve_pair(rigs_dir, redis_server, tmp_path, "--auth",
                           env={**ENV, "FACECAST_TOKENS": tokens})  # fmt: skip


async def _live(watcher: Watcher) -> None:
    """Wait for ChannelLive; it crossed Redis, so this process is subscribed to the channel."""
    while not isinstance(await watcher.next(ChannelIdle, ChannelLive, timeout=15), ChannelLive):
        pass


def _offline_weights(rig, pts: np.ndarray) -> np.ndarray:
    """What cloning ``pts`` onto ``rig`` in this process gives, as the wire carries it."""
    return rig.weights(pts).astype(np.float32)


async def test_results_on_process_b_equal_offline_cloning_of_frames_published_on_process_a(
    processes, rigs
):
    a, b = processes
    watchers = {
        "weights": await Watcher.open(b.ws_url, "stage", "beta"),
        "vertices": await Watcher.open(b.ws_url, "stage", "gamma", output="vertices"),
    }
    publisher = await Publisher.open(a.ws_url, "stage", "alpha")
    try:
        for watcher in watchers.values():
            await _live(watcher)
        sent = range(8)
        for seq in sent:
            await publisher.send(seq, points(rigs["alpha"], seq))
            for watcher in watchers.values():
                await watcher.result_with_seq(seq, timeout=15)
    finally:
        await publisher.close()
        for watcher in watchers.values():
            await watcher.close()

    alpha, beta, gamma = rigs["alpha"], rigs["beta"], rigs["gamma"]
    assert [r.seq for r in watchers["weights"].results] == list(sent)
    assert [r.seq for r in watchers["vertices"].results] == list(sent)
    for result in watchers["weights"].results:
        assert result.weights.dtype == np.float32
        expected = _offline_weights(beta, points(alpha, result.seq))
        np.testing.assert_array_equal(result.weights, expected)
    for result in watchers["vertices"].results:
        assert result.vertices.dtype == np.float32
        expected = gamma.blend(gamma.weights(points(alpha, result.seq)))  # float32 already
        np.testing.assert_array_equal(result.vertices, expected)


async def test_channels_between_processes_recover_when_redis_is_killed_and_restarted(
    processes, redis_server, rigs
):
    a, b = processes
    watcher = await Watcher.open(b.ws_url, "stage", "beta")
    publisher = await Publisher.open(a.ws_url, "stage", "alpha")
    next_seq = 0

    async def publish_continuously() -> None:
        nonlocal next_seq
        while True:
            await publisher.send(next_seq, points(rigs["alpha"], next_seq))
            next_seq += 1
            await asyncio.sleep(FRAME_INTERVAL)  # the performer's frame rate, not a wait

    async with httpx.AsyncClient(timeout=5.0) as http:

        async def readyz_on_both(status: int) -> bool:
            codes = [(await http.get(f"{p.base_url}/readyz")).status_code for p in (a, b)]
            return codes == [status, status]

        def results_from(seq: int):
            return lambda: any(r.seq >= seq for r in watcher.results)

        await _live(watcher)
        stream = asyncio.create_task(publish_continuously())
        try:
            await wait_for(results_from(0), timeout=15, what="frames across redis")

            # In a thread, so the stream goes on while redis-server dies and comes back.
            await asyncio.to_thread(redis_server.kill)
            await wait_for(lambda: readyz_on_both(503), timeout=15, what="503 while redis is down")
            down = (await http.get(f"{b.base_url}/readyz")).json()
            sent_while_down = next_seq + 10
            await wait_for(lambda: next_seq >= sent_while_down, timeout=15, what="frames sent")
            alive_while_down = (a.alive, b.alive)

            await asyncio.to_thread(redis_server.start)  # the same port: see RedisServer
            restarted_at = next_seq
            await wait_for(lambda: readyz_on_both(200), timeout=20, what="200 after restart")
            await wait_for(results_from(restarted_at), timeout=20, what="frames after restart")
            sockets_survived = (not watcher.closed.is_set(), publisher.ws.close_code is None)
        finally:
            stream.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await stream
            await publisher.close()
            await watcher.close()

    assert alive_while_down == (True, True)
    assert (a.alive, b.alive) == (True, True)
    assert down["code"] == "not_ready" and "redis" in down["detail"]
    # As in-process: the same two sockets carried frames before the kill and after the restart.
    assert sockets_survived == (True, True)
    seqs = [r.seq for r in watcher.results]
    assert seqs == sorted(set(seqs))
    assert seqs[0] < restarted_at <= seqs[-1]
    for result in watcher.results:
        expected = _offline_weights(rigs["beta"], points(rigs["alpha"], result.seq))
        np.testing.assert_array_equal(result.weights, expected)


@pytest.mark.parametrize("performer", ["sending", "stalled-too"])
async def test_a_stall_of_the_publishers_process_does_not_end_its_live_channel(
    auth_processes, rigs, performer
):
    # A second connection of the publisher's token claims the channel on B, so B asks A
    # (bus event evict, every 0.5 s) to end the older connection if it is silent. A's
    # whole process is stopped meanwhile: B's evicts wait in A's Redis connection, and
    # A's timers run late. The performer either sends on (its frames wait in A's socket,
    # and race the evicts once A runs) or stalls too (a whole machine stalled, as CI's
    # servers and clients in one process did) and sends again CAMERA_LAG after A runs.
    # The time A itself did not run is not the publisher's silence: it keeps its channel
    # and its results, and B's claimant is refused after RECLAIM_WAIT.
    a, b = auth_processes
    live = await Publisher.open(a.ws_url, "stage", "alpha", token="publisher-token")
    next_seq = 0
    camera_on = asyncio.Event()
    camera_on.set()

    async def keep_sending() -> None:
        nonlocal next_seq
        while await camera_on.wait():
            await live.send(next_seq, points(rigs["alpha"], next_seq % 5))
            next_seq += 1
            await asyncio.sleep(CAMERA_INTERVAL)  # the camera's pace, not a wait

    sending = asyncio.create_task(keep_sending())
    claim = asyncio.create_task(
        refused(channel_url(b.ws_url, "stage", "publish"), token="publisher-token",
                hello=Hello(rig="alpha"), timeout=RECLAIM_WAIT + 10)
    )  # fmt: skip
    viewer = {"Authorization": "Bearer viewer-token"}
    try:
        async with httpx.AsyncClient(timeout=5.0, headers=viewer) as http:

            async def b_is_claiming() -> bool:
                # B's claim makes the channel B's too: B reports itself in its figures.
                response = await http.get(f"{b.base_url}/v1/channels/stage")
                if response.status_code == 404:  # neither B's nor A's report yet
                    return False
                info = response.raise_for_status().json()
                return any(p["process"] == info["process"] for p in info["processes"])

            await wait_for(b_is_claiming, timeout=15, what="B claiming the channel")
        if performer == "stalled-too":
            camera_on.clear()
        os.kill(a.pid, signal.SIGSTOP)
        try:
            await asyncio.sleep(STALL)  # the stall itself
        finally:
            os.kill(a.pid, signal.SIGCONT)
        if performer == "stalled-too":
            await asyncio.sleep(CAMERA_LAG)  # the scenario's timing, not a wait
        camera_on.set()
        after_stall = next_seq
        received: list[Result | Error] = []
        async with asyncio.timeout(15):
            while True:  # until a result of a frame sent after the stall, or anything else
                received.append(message := await live.queue.get())
                if not isinstance(message, Result) or message.seq >= after_stall:
                    break
        # Once the publisher is ended, B's claimant has the channel: nothing to wait for.
        error = (await claim)[0] if isinstance(message, Result) else None
    finally:
        sending.cancel()
        claim.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await sending
        await live.close()

    assert [m for m in received if not isinstance(m, Result)] == []
    assert received[-1].seq >= after_stall
    assert error is not None and error.code == ErrorCode.CHANNEL_BUSY
    assert "already has a publisher" in error.message

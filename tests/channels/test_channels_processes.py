"""Channels across real ``facecast serve --redis`` processes: exact fan-out, and Redis dying.

Unlike test_channels_redis.py (servers as threads of this process), each facecast here is
its own interpreter started from the CLI; they share only redis-server and the rig folder.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import httpx
import numpy as np
import pytest

from facecast.cli.bench.harness import ServerProcess, facecast_serve
from facecast.protocol import ChannelIdle, ChannelLive

from ._helpers import Publisher, Watcher, points, wait_for

pytestmark = pytest.mark.anyio

#: Generous: a loaded 2-core CI machine starts two interpreters at once.
STARTUP_TIMEOUT = 45.0
#: The publisher's frame rate in the restart test (a performer's pace, far below max_fps).
FRAME_INTERVAL = 0.02


@pytest.fixture
def processes(rigs_dir, redis_server, tmp_path):
    """Processes A and B, both ready, on the same redis-server; stopped at the end."""
    # face_lost_after as in conftest's settings: no eased (synthetic) results while
    # frames stop crossing Redis, so every result is the clone of a published frame.
    env = {"FACECAST_LOG_LEVEL": "warning", "FACECAST_FACE_LOST_AFTER": "30"}
    started: list[ServerProcess] = []
    try:
        for name in ("A", "B"):
            process = facecast_serve(
                rigs_dir, "--redis", redis_server.url, env=env,
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

"""The Redis bus on a real redis-server: when a frame handed to it reaches Redis.

A raw (synchronous) subscriber stands in for the other processes; blocking on it blocks
the event loop, as this process's own fan-out of the frame does.
"""

from __future__ import annotations

import asyncio

import msgpack
import pytest
import redis

from facecast.server.channels.bus import RedisBus, frames_channel, stop_tasks

from ._helpers import wait_for

pytestmark = pytest.mark.anyio


async def test_a_frame_reaches_redis_before_the_local_fan_out_holds_the_loop(redis_server):
    subscriber = redis.Redis.from_url(redis_server.url).pubsub()
    subscriber.subscribe(frames_channel("stage"))
    assert subscriber.get_message(timeout=5.0)["type"] == "subscribe"  # before anything is sent
    bus = RedisBus(redis_server.url)
    await bus.start(lambda *_: None)
    try:
        # The promise holds on a connection that is up: the first event also connects.
        bus.send("stage", "live")
        await wait_for(lambda: subscriber.get_message(timeout=0) is not None, what="first event")

        bus.send("stage", "frame", b"points")
        # Channel.submit wakes the send loop, then the pump: one turn of the loop runs the
        # send loop's first step, and the next thing to run is the pump's fan-out.
        await asyncio.sleep(0)
        message = subscriber.get_message(timeout=2.0)  # the loop is held, as by a fan-out
    finally:
        await bus.close()
        subscriber.close()

    assert message is not None, "the frame was still in this process when the fan-out began"
    assert msgpack.unpackb(message["data"])["p"] == b"points"


async def _swallows_cancels(times: int, hold: list[bool] | None = None) -> None:
    """Sleeps on, ``times`` cancellations over (as the probe's loop did after a ping), or
    every one while ``hold[0]``."""
    swallowed = 0
    while True:
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            swallowed += 1
            if swallowed > times and not (hold and hold[0]):
                raise


async def test_stopping_the_bus_tasks_cancels_again_one_that_swallowed_its_cancel():
    stubborn = asyncio.create_task(_swallows_cancels(1))
    plain = asyncio.create_task(_swallows_cancels(0))
    await asyncio.sleep(0)

    async with asyncio.timeout(5):  # one cancel and a gather waited here for good
        await stop_tasks([stubborn, plain], timeout=4)

    assert stubborn.cancelled() and plain.cancelled()


async def test_a_task_that_never_stops_is_logged_and_left_after_the_timeout(caplog):
    hold = [True]
    stuck = asyncio.create_task(_swallows_cancels(0, hold))
    await asyncio.sleep(0)

    try:
        async with asyncio.timeout(5):
            await stop_tasks([stuck], timeout=0.2)
        done = stuck.done()
    finally:
        hold[0] = False  # the test's own clean-up
        stuck.cancel()

    assert not done
    stuck_logs = [r for r in caplog.records if getattr(r, "event", "") == "tasks.stuck"]
    assert [r.tasks for r in stuck_logs] == [[stuck.get_name()]]

"""The Redis bus on a real redis-server: when a frame handed to it reaches Redis, when
Redis is taken for down.

A raw (synchronous) subscriber stands in for the other processes; blocking on it blocks
the event loop, as this process's own fan-out of the frame does, or a stall of it.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time

import msgpack
import pytest
import redis

from facecast.server.channels.bus import DOWN_WITHIN, RedisBus, frames_channel, stop_tasks

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


#: A stall of the loop past the bus's 1 s bound on one call, as a loaded CI run's was.
STALL = 1.5


def _events(caplog, name: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if getattr(r, "event", "") == name]


async def _received(subscriber) -> dict:
    """The subscriber's next message, polled without holding the loop."""
    got: list[dict] = []

    def poll() -> bool:
        message = subscriber.get_message(timeout=0)
        if message is not None:
            got.append(message)
        return bool(got)

    await wait_for(poll, what="a message at the subscriber")
    return got[0]


async def test_a_stall_of_the_loop_fails_the_publish_in_flight_but_redis_stays_up(
    redis_server, caplog
):
    caplog.set_level(logging.INFO, logger="facecast.server.bus")
    subscriber = redis.Redis.from_url(redis_server.url).pubsub()
    subscriber.subscribe(frames_channel("stage"))
    assert subscriber.get_message(timeout=5.0)["type"] == "subscribe"
    bus = RedisBus(redis_server.url)
    await bus.start(lambda *_: None)
    try:
        await wait_for(lambda: bus.not_ready_reason() is None, what="redis up")
        bus.send("stage", "live")  # connects the frames' client
        await _received(subscriber)

        bus.send("stage", "frame", b"points")
        await asyncio.sleep(0)  # the send loop's first step writes the PUBLISH (see above)
        time.sleep(STALL)  # the loop stalls; Redis answers meanwhile, unread
        reached_redis = subscriber.get_message(timeout=5.0)
        await wait_for(lambda: bus.dropped == 1, what="the publish caught by the stall failed")
        reason_after_the_failure = bus.not_ready_reason()

        bus.send("stage", "frame", b"after")
        after = await _received(subscriber)  # on a new connection: the stall's was cut
        reason_after_the_next = bus.not_ready_reason()
    finally:
        await bus.close()
        subscriber.close()

    assert msgpack.unpackb(reached_redis["data"])["p"] == b"points"  # in time: the stall's
    # Readiness may come back before it is read (the probe runs first): the log tells.
    assert _events(caplog, "bus.down") == [], "one publish timed out by a stall made redis down"
    assert len(_events(caplog, "bus.doubt")) == 1
    assert reason_after_the_failure is None and reason_after_the_next is None
    assert msgpack.unpackb(after["data"])["p"] == b"after"


async def test_a_redis_that_stops_answering_is_down_within_the_documented_time(redis_server):
    bus = RedisBus(redis_server.url)
    await bus.start(lambda *_: None)
    try:
        await wait_for(lambda: bus.not_ready_reason() is None, what="redis up")
        os.kill(redis_server.pid, signal.SIGSTOP)  # hung: connections open, no answers
        stopped = time.monotonic()
        try:
            await wait_for(lambda: bus.not_ready_reason() is not None, timeout=DOWN_WITHIN + 10,
                           what="redis down")  # fmt: skip
            took = time.monotonic() - stopped
            reason = bus.not_ready_reason()
        finally:
            os.kill(redis_server.pid, signal.SIGCONT)
        await wait_for(lambda: bus.not_ready_reason() is None, what="redis up again")
    finally:
        await bus.close()

    assert reason is not None and "unreachable: TimeoutError" in reason
    # Confirmed by a second ping: not before one ping's 1 s bound ran out twice.
    assert took >= 2.0, took

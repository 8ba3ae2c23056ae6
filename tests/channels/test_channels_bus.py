"""The Redis bus on a real redis-server: when a frame handed to it reaches Redis.

A raw (synchronous) subscriber stands in for the other processes; blocking on it blocks
the event loop, as this process's own fan-out of the frame does.
"""

from __future__ import annotations

import asyncio

import msgpack
import pytest
import redis

from facecast.server.channels.bus import RedisBus, frames_channel

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

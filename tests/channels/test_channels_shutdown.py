"""The hub's maintenance (at shutdown) and a channel's tasks (when it is dropped) stop,
bounded, even when one swallows its cancel, as the bus probe's was seen swallowed in Redis.

One cancel and a wait held the server's shutdown for good there: the task was back in its
loop. Here the hub's and the channel's loops swallow their first cancel on a real server
with a real redis-server; they must be cancelled again and end in bounded time.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable, Coroutine
from typing import Any

import pytest

from facecast.server.channels.bus import SHUTDOWN_STOP_SECONDS
from facecast.server.channels.channel import Channel
from facecast.server.channels.hub import ChannelHub
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, wait_for

pytestmark = pytest.mark.anyio

Loop = Callable[[Any], Coroutine[Any, Any, None]]


def swallowing_its_first_cancel(loop: Loop, swallowed: list[str], ended: list[str]) -> Loop:
    """``loop`` whose task, cancelled once, carries on as if the cancel had been lost."""

    async def stubborn(self: Any) -> None:
        name = asyncio.current_task().get_name()  # type: ignore[union-attr]
        try:
            await loop(self)
        except asyncio.CancelledError:
            swallowed.append(name)
        try:
            await loop(self)  # back in its loop
        finally:
            ended.append(name)

    return stubborn


async def test_the_hub_and_an_emptied_channel_stop_tasks_that_swallowed_a_cancel(
    settings, rigs, redis_server, monkeypatch
):
    swallowed: list[str] = []
    ended: list[str] = []
    for cls, name in ((ChannelHub, "_maintain"), (Channel, "_pump_loop")):
        original = getattr(cls, name)
        monkeypatch.setattr(cls, name, swallowing_its_first_cancel(original, swallowed, ended))
    redis_settings = dataclasses.replace(settings, redis_url=redis_server.url)
    pump = "channel-stage-pump"

    async with run_server(redis_settings) as server:
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        watcher = await Watcher.open(server.ws_url, "stage", "alpha")
        await publisher.send(0, points(rigs["alpha"], 0))
        await watcher.result_with_seq(0)  # the channel's pump runs
        await watcher.close()
        await publisher.close()
        # The emptied channel is dropped and stopped (Channel.stop) while the server runs.
        await wait_for(lambda: pump in ended, SHUTDOWN_STOP_SECONDS + 2.0, "the pump to end")
        start = time.monotonic()
    took = time.monotonic() - start

    assert swallowed == [pump, "facecast-channels"] and ended == swallowed
    # Shutdown's part: the hub's maintenance (ChannelHub.close), within stop_tasks' bound;
    # one cancel and a wait held it until ThreadedServer.stop gave up after 30 s.
    assert took < SHUTDOWN_STOP_SECONDS + 3.0, took

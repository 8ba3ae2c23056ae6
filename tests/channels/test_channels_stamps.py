"""Stage stamps through a channel (PROTOCOL.md §5.4): the plausible ones relayed with the
server's arrival, the implausible dropped, a publisher without stamps served as before.

A real server; the clients speak the protocol over plain websockets.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from facecast.protocol import Frame, Result, Stamps
from facecast.server.channels.fanout import ChannelFrame
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points


async def _send(publisher: Publisher, seq: int, pts: np.ndarray, stamps: Stamps | None) -> None:
    frame = Frame(seq=seq, ts=float(seq), points=pts, stamps=stamps)
    await publisher.ws.send(publisher.protocol.send(frame))


@pytest.mark.anyio
async def test_every_watcher_gets_the_stamps_and_the_servers_arrival(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = [
            await Watcher.open(server.ws_url, "stage", "beta"),
            await Watcher.open(server.ws_url, "stage", "gamma", output="points", dtype="f64"),
        ]
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        now = time.time()
        sent = Stamps(captured=now - 0.030, tracked=now - 0.002, sent=now - 0.001)
        await _send(publisher, 0, points(rigs["alpha"], 0), sent)
        received = [await watcher.result_with_seq(0) for watcher in watchers]
        after = time.time()
    for result in received:
        assert result.stamps is not None
        assert (result.stamps.captured, result.stamps.tracked, result.stamps.sent) == (
            sent.captured,
            sent.tracked,
            sent.sent,
        )
        assert result.stamps.server_in is not None and result.server_ts is not None
        assert now <= result.stamps.server_in <= result.server_ts <= after


@pytest.mark.anyio
async def test_a_stamp_from_the_future_or_the_far_past_is_not_relayed(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        now = time.time()
        await _send(publisher, 0, points(rigs["alpha"], 0), Stamps(captured=now + 3600, sent=now))
        future = await watcher.result_with_seq(0)
        await _send(publisher, 1, points(rigs["alpha"], 1), Stamps(captured=1.0))
        past = await watcher.result_with_seq(1)
    assert future.stamps is not None and future.stamps.captured is None
    assert future.stamps.sent == now
    assert past.stamps is None  # nothing plausible: no stamps at all, the result as before


@pytest.mark.anyio
async def test_a_publisher_without_stamps_is_served_as_before(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await _send(publisher, 0, points(rigs["alpha"], 0), None)
        result = await watcher.result_with_seq(0)
    assert isinstance(result, Result) and result.stamps is None
    assert result.weights is not None and result.server_ts is not None


def test_stamps_cross_processes_with_the_frame() -> None:
    # What another process (through Redis) clones from: the same stamps, bit for bit.
    stamps = Stamps(captured=1.25, tracked=1.5, sent=1.75, server_in=2.0)
    frame = ChannelFrame(seq=3, ts=1.0, points=np.zeros((2, 3), np.float32), stamps=stamps)
    assert ChannelFrame.from_bytes(frame.to_bytes(), max_points=16).stamps == stamps
    plain = dataclasses.replace(frame, stamps=None)
    assert ChannelFrame.from_bytes(plain.to_bytes(), max_points=16).stamps is None

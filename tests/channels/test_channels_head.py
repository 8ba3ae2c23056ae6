"""Head pose through a channel (PROTOCOL.md §5.3): relayed unchanged, refused when bad.

A real server (and a real redis-server for two processes); the clients speak the protocol
over plain websockets, as a third-party publisher or watcher would.
"""

from __future__ import annotations

import asyncio
import dataclasses

import msgpack
import numpy as np
import pytest
import websockets

from facecast.client.urls import stream_url
from facecast.protocol import (
    SUBPROTOCOL,
    ChannelLive,
    ClientProtocol,
    Error,
    ErrorCode,
    FaceLost,
    Frame,
    Head,
    Hello,
    Ready,
    Result,
    array_to_wire,
    encode,
)
from facecast.server.testing import run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points

pytestmark = pytest.mark.anyio

#: Not a float32-exact quaternion: an f64 relay that rounded anywhere would show.
_ROTATION = np.array([0.1, -0.2, 0.05, 0.0], dtype=np.float64)
_ROTATION[3] = np.sqrt(1.0 - np.sum(_ROTATION[:3] ** 2))
HEAD = Head(rotation=_ROTATION, position=np.array([0.0, 0.06, -0.01], dtype=np.float32))


async def _send(publisher: Publisher, seq: int, pts: np.ndarray, head: Head | None) -> None:
    frame = Frame(seq=seq, ts=float(seq), points=pts, head=head)
    await publisher.ws.send(publisher.protocol.send(frame))


async def _next_result(publisher: Publisher) -> Result:
    async with asyncio.timeout(5):
        while not isinstance(message := await publisher.queue.get(), Result):
            pass
    return message


def _assert_same_head(result: Result, head: Head) -> None:
    assert result.head is not None
    assert result.head.rotation.dtype == head.rotation.dtype
    assert result.head.rotation.tobytes() == head.rotation.tobytes()
    assert result.head.position is not None and head.position is not None
    assert result.head.position.tobytes() == head.position.tobytes()


async def test_every_watcher_gets_the_published_head_bit_for_bit(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = [
            await Watcher.open(server.ws_url, "stage", "alpha"),
            await Watcher.open(server.ws_url, "stage", "beta", output="vertices", dtype="f16"),
            await Watcher.open(server.ws_url, "stage", "gamma", output="points", dtype="f64"),
        ]
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await _send(publisher, 0, points(rigs["alpha"], 0), HEAD)
        received = [await watcher.result_with_seq(0) for watcher in watchers]
        own = await _next_result(publisher)
    for result in [*received, own]:
        _assert_same_head(result, HEAD)


async def test_a_frame_without_a_head_gives_results_without_one(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await _send(publisher, 0, points(rigs["alpha"], 0), HEAD)
        with_head = await watcher.result_with_seq(0)
        # The next frame has none: its result must not repeat the previous head.
        await _send(publisher, 1, points(rigs["alpha"], 1), None)
        without = await watcher.result_with_seq(1)
    assert with_head.head is not None and without.head is None


async def test_a_late_joiner_gets_the_newest_result_with_its_head(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        first = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await _send(publisher, 4, points(rigs["alpha"], 4), HEAD)
        await first.result_with_seq(4)
        late = await Watcher.open(server.ws_url, "stage", "beta")
        result = await late.next(Result)
    assert result.seq == 4
    _assert_same_head(result, HEAD)


def _bad_frame(seq: int, pts: np.ndarray) -> bytes:
    wire = Frame(seq=seq, ts=1.0, points=pts).serialize()
    wire["head"] = {"rotation": array_to_wire(np.array([0.0, 0.0, 0.0, 0.5]))}
    return msgpack.packb(wire, use_bin_type=True)


async def test_a_bad_head_is_refused_and_the_channel_goes_on(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.ws.send(_bad_frame(0, points(rigs["alpha"], 0)))
        async with asyncio.timeout(5):
            while not isinstance(error := await publisher.queue.get(), Error):
                pass
        await _send(publisher, 1, points(rigs["alpha"], 1), HEAD)
        result = await watcher.next(Result)
    assert isinstance(error, Error) and not error.fatal
    assert (error.code, error.seq) == (ErrorCode.INVALID_FIELD, 0)
    assert "frame.head.rotation must be a unit quaternion" in error.message
    assert result.seq == 1  # frame 0 never reached the watchers


async def test_a_head_crosses_processes_through_redis(settings, redis_server, rigs, ws_impl):
    redis_settings = dataclasses.replace(settings, redis_url=redis_server.url)
    async with (
        run_server(redis_settings, ws=ws_impl) as a,
        run_server(redis_settings, ws=ws_impl) as b,
    ):
        watcher = await Watcher.open(b.ws_url, "stage", "beta")
        publisher = await Publisher.open(a.ws_url, "stage", "alpha")
        while not isinstance(await watcher.next(ChannelLive, timeout=10), ChannelLive):
            pass
        await _send(publisher, 0, points(rigs["alpha"], 0), HEAD)
        result = await watcher.result_with_seq(0, timeout=10)
    _assert_same_head(result, HEAD)


async def test_eased_results_after_a_lost_face_carry_no_head(settings, rigs, ws_impl):
    face_settings = dataclasses.replace(settings, face_lost_after=0.2, face_lost_ease=0.2)
    async with run_server(face_settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await _send(publisher, 0, points(rigs["alpha"], 0), HEAD)
        live = await watcher.result_with_seq(0)
        await watcher.next(FaceLost)
        eased = await watcher.next(Result)
    _assert_same_head(live, HEAD)
    assert eased.seq == 0 and eased.head is None


async def _stream(server, frame_bytes: bytes) -> object:
    """Open /v1/stream on rig alpha, send one frame's bytes, return the answer to it."""
    protocol = ClientProtocol()
    async with websockets.connect(
        stream_url(server.base_url), subprotocols=[SUBPROTOCOL], open_timeout=5
    ) as ws:
        await ws.send(protocol.send(Hello(rig=RIG_IDS[0])))
        assert isinstance(protocol.receive(await ws.recv()), Ready)
        await ws.send(frame_bytes)
        return protocol.receive(await ws.recv())


async def test_stream_checks_a_head_but_does_not_echo_it(settings, rigs, ws_impl):
    pts = points(rigs["alpha"], 2)
    async with run_server(settings, ws=ws_impl) as server:
        result = await _stream(server, encode(Frame(seq=0, ts=0.0, points=pts, head=HEAD)))
        refusal = await _stream(server, _bad_frame(0, pts))
    assert isinstance(result, Result) and result.seq == 0 and result.head is None
    assert isinstance(refusal, Error) and refusal.code == ErrorCode.INVALID_FIELD

"""The client library against a real server: clone, pipelining, latency, reconnection, errors."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from facecast.client.connection import ConnectionFailed, Reconnect, connect
from facecast.client.latency import LatencyTracker
from facecast.client.streaming import stream_frames
from facecast.client.urls import resolve_token, rest_url, stream_url
from facecast.protocol import ErrorCode, ProtocolError, Result, Smoothing
from facecast.rig.demo import demo_animation
from facecast.rig.filters import KalmanFilter

from ._stream_fixtures import RIG_ID, LiveServer, demo_rig, live_server, rigs_dir, server_settings

__all__ = ["demo_rig", "live_server", "rigs_dir"]  # fixtures used by name

FAST_RECONNECT = Reconnect(attempts=40, initial_delay=0.02, max_delay=0.2)


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return demo_animation(seconds=1.0, fps=60.0).points


def test_clone_returns_the_offline_weights_exactly_in_f32(live_server, demo_rig, frames):
    async def run() -> list[Result]:
        async with connect(live_server.base_url, RIG_ID) as session:
            return [await session.clone(p) for p in frames[:20]]

    results = asyncio.run(run())

    for points, result in zip(frames[:20], results, strict=True):
        np.testing.assert_array_equal(result.weights, demo_rig.weights(points).astype(np.float32))


def test_kalman_smoothing_asked_for_in_connect_filters_the_points(live_server, demo_rig, frames):
    smoothing = Smoothing(filter="kalman", acceleration=480.0, noise=0.01)
    times = np.arange(10) / 60.0

    async def run() -> list[Result]:
        results = []
        async with connect(live_server.base_url, RIG_ID, smoothing=smoothing) as session:
            for points, t in zip(frames[:10], times, strict=True):
                await session.send(points, t=float(t))
                results.append(await session.receive())
        return results

    results = asyncio.run(run())

    reference = KalmanFilter(noise=0.01, acceleration=480.0 * 0.01)
    for points, t, result in zip(frames[:10], times, results, strict=True):
        smoothed = reference(points.reshape(-1), float(t)).reshape(points.shape)  # f64 frames
        np.testing.assert_allclose(result.weights, demo_rig.weights(smoothed), atol=1e-6)
    assert not np.allclose(results[-1].weights, demo_rig.weights(frames[9]), atol=1e-4)


def test_pipelined_frames_come_back_in_order_with_their_seq(live_server, frames):
    async def run() -> list[int]:
        seqs: list[int] = []
        async with connect(live_server.base_url, RIG_ID) as session:
            for i in range(0, 30, 2):
                # Two in flight, then both answers: the server never has to supersede one.
                await session.send(frames[i], seq=1000 + i)
                await session.send(frames[i + 1])
                seqs += [(await session.receive()).seq, (await session.receive()).seq]
        return seqs

    assert asyncio.run(run()) == list(range(1000, 1030))


def test_async_for_yields_every_result_of_a_windowed_stream(live_server, frames):
    async def run() -> list[int]:
        seqs: list[int] = []
        async with connect(live_server.base_url, RIG_ID) as session:
            await session.send(frames[0])
            async for result in session:
                seqs.append(result.seq)
                if len(seqs) == 10:
                    break
                await session.send(frames[len(seqs)])
        return seqs

    assert asyncio.run(run()) == list(range(10))


def test_closing_with_results_unread_completes_the_closing_handshake(live_server, frames):
    # A hundred results the application never reads, one of them held by the session:
    # the rest fill websockets' own queue, which stops reading the socket. Closing must
    # still read through to the server's close frame (1000), not wait out websockets'
    # close_timeout and drop the connection (1006).
    async def run() -> int | None:
        session = await connect(live_server.base_url, RIG_ID, max_queue=1)
        for points in np.resize(frames, (100, *frames.shape[1:])):
            await session.send(points)
        await session.close()
        return session.close_code

    assert asyncio.run(run()) == 1000


def test_streamed_vertices_in_f16_match_offline_clone_within_f16_tolerance(
    live_server, demo_rig, frames
):
    async def run():
        async with connect(live_server.base_url, RIG_ID, output="vertices", dtype="f16") as s:
            return await stream_frames(s, frames, fps=60.0)

    outcome = asyncio.run(run())

    expected = demo_rig.clone(frames)
    assert outcome.values.shape == expected.shape
    scale = np.abs(expected).max()
    np.testing.assert_allclose(outcome.values, expected, atol=2e-3 * scale, rtol=0)


def test_latency_stats_count_every_answered_frame(live_server, frames):
    async def run():
        async with connect(live_server.base_url, RIG_ID) as session:
            for points in frames[:25]:
                await session.clone(points)
            return session.latency.stats()

    stats = asyncio.run(run())

    assert stats.count == 25
    assert 0 < stats.p50_ms <= stats.p95_ms <= stats.p99_ms <= stats.max_ms


def test_session_reconnects_after_a_server_restart_and_keeps_numbering(rigs_dir, demo_rig, frames):
    server = LiveServer(server_settings(rigs_dir)).start()

    async def run():
        async with connect(server.base_url, RIG_ID, reconnect=FAST_RECONNECT) as session:
            before = await session.clone(frames[0])
            await asyncio.to_thread(server.stop)
            await asyncio.to_thread(server.start)
            after = await session.clone(frames[1])
            return before, after, session.reconnects

    try:
        before, after, reconnects = asyncio.run(run())
    finally:
        server.stop()

    assert reconnects == 1
    assert after.seq > before.seq
    np.testing.assert_array_equal(after.weights, demo_rig.weights(frames[1]).astype(np.float32))


def test_session_gives_up_with_connection_failed_when_the_server_stays_down(rigs_dir, frames):
    server = LiveServer(server_settings(rigs_dir)).start()

    async def run():
        policy = Reconnect(attempts=2, initial_delay=0.01, max_delay=0.05)
        async with connect(server.base_url, RIG_ID, reconnect=policy) as session:
            await session.clone(frames[0])
            await asyncio.to_thread(server.stop)
            await session.receive(timeout=10.0)

    with pytest.raises(ConnectionFailed, match="gave up after 2 reconnection"):
        asyncio.run(run())


def test_unknown_rig_is_a_protocol_error_with_its_code(live_server):
    async def run():
        async with connect(live_server.base_url, "no-such-rig"):
            pass

    with pytest.raises(ProtocolError) as caught:
        asyncio.run(run())

    assert caught.value.code is ErrorCode.UNKNOWN_RIG


def test_wrong_point_count_is_refused_before_sending(live_server):
    async def run():
        async with connect(live_server.base_url, RIG_ID) as session:
            await session.send(np.zeros((3, 3)))

    with pytest.raises(ProtocolError) as caught:
        asyncio.run(run())

    assert caught.value.code is ErrorCode.WRONG_POINT_COUNT


def test_token_from_the_environment_is_sent_as_a_bearer_header(rigs_dir, frames, monkeypatch):
    server = LiveServer(server_settings(rigs_dir, auth=True, tokens={"s3cret": {"stream"}}))
    server.start()
    monkeypatch.setenv("FACECAST_TOKEN", "s3cret")

    async def run():
        async with connect(server.base_url, RIG_ID) as session:
            return await session.clone(frames[0])

    try:
        result = asyncio.run(run())
    finally:
        server.stop()

    assert result.seq == 0


def test_missing_token_is_refused_as_unauthorized(rigs_dir, monkeypatch):
    server = LiveServer(server_settings(rigs_dir, auth=True, tokens={"s3cret": {"stream"}}))
    server.start()
    monkeypatch.delenv("FACECAST_TOKEN", raising=False)

    async def run():
        async with connect(server.base_url, RIG_ID):
            pass

    try:
        with pytest.raises(ProtocolError) as caught:
            asyncio.run(run())
    finally:
        server.stop()

    assert caught.value.code is ErrorCode.UNAUTHORIZED


def test_unreachable_server_raises_connection_failed():
    from facecast.server.testing import free_port

    async def run():
        async with connect(f"http://127.0.0.1:{free_port()}", RIG_ID, open_timeout=2.0):
            pass

    with pytest.raises(ConnectionFailed, match="cannot open a session"):
        asyncio.run(run())


@pytest.mark.parametrize(
    ("base", "expected"),
    [
        ("http://127.0.0.1:8000", "ws://127.0.0.1:8000/v1/stream"),
        ("https://face.example/", "wss://face.example/v1/stream"),
        ("http://h/prefix", "ws://h/prefix/v1/stream"),
        ("ws://h:1/v1/stream", "ws://h:1/v1/stream"),
    ],
)
def test_stream_url_is_derived_from_the_base_url(base, expected):
    assert stream_url(base) == expected


def test_rest_url_quotes_segments():
    assert rest_url("https://h:9", "rigs", "a b") == "https://h:9/v1/rigs/a%20b"


@pytest.mark.parametrize("bad", ["127.0.0.1:8000", "ftp://h", "http://h/?x=1"])
def test_malformed_base_url_is_a_value_error(bad):
    with pytest.raises(ValueError, match="server URL"):
        stream_url(bad)


def test_explicit_token_wins_over_the_environment():
    assert resolve_token("a", {"FACECAST_TOKEN": "b"}) == "a"
    assert resolve_token(None, {"FACECAST_TOKEN": "b"}) == "b"


@given(st.lists(st.floats(min_value=0.0, max_value=10.0), min_size=1, max_size=200))
def test_latency_percentiles_are_ordered_and_bounded_by_the_max(rtts):
    tracker = LatencyTracker(max_samples=50)
    for seq, rtt in enumerate(rtts):
        tracker.sent(seq, when=0.0)
        tracker.received(seq, when=rtt)

    stats = tracker.stats()

    assert stats.count == len(rtts)
    assert stats.p50_ms <= stats.p95_ms <= stats.p99_ms <= stats.max_ms
    assert stats.max_ms == pytest.approx(max(rtts) * 1e3)


def test_latency_tracker_forgets_frames_overtaken_by_a_later_result():
    tracker = LatencyTracker()
    for seq in range(5):
        tracker.sent(seq, when=0.0)

    tracker.received(3, when=1.0)

    assert tracker.in_flight == 1  # only seq 4; 0..2 were dropped by the server

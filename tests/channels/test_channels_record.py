"""``output=points`` watchers and ``facecast record``; ``facecast publish --realtime`` replays a take.

A real server on a free port, real sockets, the real CLI; timing is measured on a
weights watcher's arrival clock, so a replay that loses its pauses fails.
"""

from __future__ import annotations

import asyncio
import dataclasses

import httpx
import numpy as np
import pytest
import websockets
from hypothesis import given
from hypothesis import strategies as st

from facecast.cli.commands.record import Take
from facecast.cli.main import main
from facecast.client.channel import channel_url
from facecast.protocol import (
    SUBPROTOCOL,
    ChannelLive,
    ErrorCode,
    ProtocolError,
    Ready,
    Result,
    decode_server,
    encode,
)
from facecast.rig.sources.loading import load_source_animation
from facecast.server.channels.fanout import ChannelFrame
from facecast.server.testing import run_server

from ._helpers import K, Publisher, Watcher, points, refused, wait_for
from .conftest import TOKENS

pytestmark = pytest.mark.anyio


def performance(rig, stamps: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """(F, K, 3) points exact in f32 and their (F,) timestamps."""
    frames = np.stack([points(rig, seed) for seed in range(len(stamps))]).astype(np.float64)
    return frames, np.asarray(stamps, dtype=np.float64)


async def _viewers(http: httpx.AsyncClient, name: str, count: int) -> None:
    async def joined() -> bool:
        response = await http.get(f"/v1/channels/{name}")
        return response.status_code == 200 and response.json()["viewers"] == count

    await wait_for(joined, what=f"{count} viewer(s) on {name}")


async def _record(base: str, http, out, *extra: str, viewers: int = 1) -> asyncio.Task[int]:
    """Start ``facecast record`` on channel "stage" and wait until it has joined."""
    task = asyncio.create_task(asyncio.to_thread(
        main, ["record", base, "stage", "-o", str(out), "--rig", "alpha", "-q", *extra]))  # fmt: skip
    await _viewers(http, "stage", viewers)
    return task


async def _publish(base: str, source, *flags: str) -> int:
    return await asyncio.to_thread(
        main, ["publish", base, "stage", str(source), "--rig", "alpha", "-q", *flags]
    )


class _PointsWatcher:
    """A raw ``output=points`` watcher (ClientProtocol does not know points results yet)."""

    def __init__(self, ws) -> None:
        self.ws = ws

    @classmethod
    async def open(cls, base: str, query: dict[str, str]) -> _PointsWatcher:
        url = channel_url(base, "stage", "watch", query)
        return cls(await websockets.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=5))

    async def next(self, kind: type, timeout: float = 5.0):
        async with asyncio.timeout(timeout):
            while True:
                message = decode_server(await self.ws.recv())
                if isinstance(message, kind):
                    return message


# --- the protocol: points results and the points watch query ------------------------------


@given(
    st.lists(st.floats(-1e6, 1e6, width=32), min_size=3, max_size=30).filter(
        lambda v: len(v) % 3 == 0
    ),
    st.sampled_from([np.float32, np.float64]),
)
def test_points_result_round_trips_exactly(values, dtype):
    pts = np.asarray(values, dtype=dtype).reshape(-1, 3)
    result = Result(seq=3, ts=1.25, points=pts)

    decoded = decode_server(encode(result))

    assert decoded == result and decoded.output == "points" and decoded.dtype == result.dtype


def test_result_with_points_and_weights_is_invalid():
    with pytest.raises(ProtocolError) as caught:
        Result(seq=0, ts=0.0, weights=np.ones(2, np.float32), points=np.ones((2, 3), np.float32))

    assert caught.value.code == ErrorCode.INVALID_FIELD


def test_ready_for_points_allows_f64_but_weights_do_not():
    common = {"session": "s", "rig": "r", "names": ("n",), "num_points": 2, "num_vertices": 4}
    ready = Ready(output="points", dtype="f64", **common)

    assert decode_server(encode(ready)) == ready
    with pytest.raises(ProtocolError):
        Ready(output="weights", dtype="f64", **common)


def test_channel_frame_carries_raw_points_across_processes():
    raw = np.arange(6, dtype=np.float64).reshape(2, 3)
    frame = ChannelFrame(seq=1, ts=2.0, points=raw * 0.5, raw_points=raw)

    back = ChannelFrame.from_bytes(frame.to_bytes(), max_points=16)

    np.testing.assert_array_equal(back.raw_points, raw)
    np.testing.assert_array_equal(back.points, raw * 0.5)


def test_take_counts_seq_gaps_as_missed_frames():
    take = Take()
    for seq, ts in ((4, 0.0), (5, 0.1), (9, 0.5), (10, 0.6)):
        take.add(seq, ts, np.zeros((1, 3)))

    assert take.missed == 3


def test_take_ends_when_the_clock_goes_back():
    take = Take()
    take.add(7, 5.0, np.zeros((1, 3)))

    assert take.add(0, 0.0, np.zeros((1, 3))) is not None
    assert take.seq == [7]


# --- the server: output=points watchers ---------------------------------------------------


@pytest.mark.parametrize(("dtype", "wire"), [("f32", np.float32), ("f64", np.float64)])
async def test_points_watcher_receives_the_published_points_exactly(
    settings, rigs, dtype, wire, ws_impl
):
    sent = points(rigs["alpha"], 1).astype(np.float64) + 1e-9  # f64-only digits
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await _PointsWatcher.open(server.ws_url,
                                            {"rig": "beta", "output": "points", "dtype": dtype})  # fmt: skip
        ready = await watcher.next(Ready)
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await watcher.next(ChannelLive)
        await publisher.send(41, sent, ts=123.25)
        result = await watcher.next(Result)
        await publisher.close()
        await watcher.ws.close()

    assert (ready.output, ready.dtype, ready.num_points) == ("points", dtype, K)
    assert (result.seq, result.ts, result.output, result.dtype) == (41, 123.25, "points", dtype)
    np.testing.assert_array_equal(result.points, sent.astype(wire))


async def test_points_watcher_gets_raw_points_not_the_publishers_smoothing(settings, rigs, ws_impl):
    from facecast.protocol import Smoothing

    frames = [points(rigs["alpha"], seed) for seed in range(3)]
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await _PointsWatcher.open(server.ws_url, {"rig": "alpha", "output": "points"})
        publisher = await Publisher.open(server.ws_url, "stage", "alpha",
                                         smoothing=Smoothing(min_cutoff=0.01))  # fmt: skip
        await watcher.next(ChannelLive)
        for seq, frame in enumerate(frames):
            await publisher.send(seq, frame, ts=seq * 0.1)
        async with asyncio.timeout(5):
            result = await watcher.next(Result)
            while result.seq < 2:
                result = await watcher.next(Result)
        await publisher.close()
        await watcher.ws.close()

    np.testing.assert_array_equal(result.points, frames[2])


async def test_points_watchers_are_not_counted_as_clones(settings, rigs, ws_impl):
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        watcher = await _PointsWatcher.open(server.ws_url, {"rig": "alpha", "output": "points"})
        publisher = await Publisher.open(server.ws_url, "stage", "alpha", output="vertices")
        await watcher.next(ChannelLive)
        for seq in range(5):
            await publisher.send(seq, points(rigs["alpha"], seq))
            await watcher.next(Result)
        info = (await http.get("/v1/channels/stage")).json()
        await publisher.close()
        await watcher.ws.close()

    assert info["clones"] == info["frames"]  # the publisher's own key only
    assert {"rig": "alpha", "output": "points", "dtype": "f32", "viewers": 1} in info["keys"]


@pytest.mark.parametrize(
    ("query", "word"),
    [({"rig": "alpha", "output": "bogus"}, "points"),
     ({"rig": "alpha", "output": "points", "dtype": "f16"}, "f64"),
     ({"output": "points"}, "rig")],
)  # fmt: skip
async def test_bad_watch_query_is_refused_with_invalid_field(settings, query, word, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        error, close = await refused(channel_url(server.ws_url, "stage", "watch", query))

    assert (error.code, close) == (ErrorCode.INVALID_FIELD, 1008)
    assert word in error.message


@pytest.mark.parametrize(
    ("token", "code"),
    [(None, ErrorCode.UNAUTHORIZED), ("publisher-token", ErrorCode.FORBIDDEN),
     ("stream-token", ErrorCode.FORBIDDEN)],
)  # fmt: skip
async def test_points_watch_needs_the_viewer_role(settings, token, code, ws_impl):
    auth = dataclasses.replace(settings, auth=True, tokens=TOKENS)
    async with run_server(auth, ws=ws_impl) as server:
        url = channel_url(server.ws_url, "stage", "watch", {"rig": "alpha", "output": "points"})
        error, close = await refused(url, token=token)

    assert (error.code, close) == (code, 1008)


async def test_record_with_a_viewer_token_records(settings, rigs, tmp_path, ws_impl):
    auth = dataclasses.replace(settings, auth=True, tokens=TOKENS)
    async with (
        run_server(auth, ws=ws_impl) as server,
        httpx.AsyncClient(
            base_url=server.base_url, headers={"Authorization": "Bearer viewer-token"}
        ) as http,
    ):
        out = tmp_path / "take.npz"
        record = await _record(server.base_url, http, out, "--token", "viewer-token",
                               "--frames", "1")  # fmt: skip
        publisher = await Publisher.open(server.ws_url, "stage", "alpha",
                                         token="publisher-token")  # fmt: skip
        await publisher.send(0, points(rigs["alpha"], 0))
        status = await record
        await publisher.close()

    assert status == 0 and np.load(out)["points"].shape == (1, K, 3)


# --- the CLI: record, then replay with the original timing --------------------------------


async def test_record_saves_published_points_and_their_timestamps(
    settings, rigs, tmp_path, ws_impl
):
    stamps = [100.0, 100.03, 100.05, 100.12, 100.13, 100.2, 100.31, 100.33, 100.4, 100.47]
    frames, times = performance(rigs["alpha"], stamps)
    np.savez(tmp_path / "source.npz", points=frames, timestamps=times, fps=30.0)
    out = tmp_path / "take.npz"
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        record = await _record(server.base_url, http, out)
        published = await _publish(server.base_url, tmp_path / "source.npz", "--realtime")
        recorded = await record

    take = np.load(out)
    seq = take["seq"]
    assert (published, recorded) == (0, 0)
    assert len(seq) >= 2 and (np.diff(seq) > 0).all()
    np.testing.assert_array_equal(take["points"], frames[seq].astype(np.float32))
    np.testing.assert_array_equal(take["timestamps"], times[seq] - times[seq[0]])
    assert take["points"].dtype == np.float32 and str(take["rig"]) == "alpha"
    animation = load_source_animation(out)
    np.testing.assert_array_equal(animation.timestamps, take["timestamps"])


async def test_replaying_a_take_realtime_keeps_its_pause(settings, rigs, tmp_path, ws_impl):
    # 8 frames 20 ms apart, a 0.3 s pause, 8 more: the replay must show the pause.
    stamps = [0.02 * i for i in range(8)] + [0.44 + 0.02 * i for i in range(8)]
    frames, times = performance(rigs["alpha"], stamps)
    np.savez(tmp_path / "take.npz", points=frames, timestamps=times, fps=50.0)
    out = tmp_path / "replayed.npz"
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        clock = await Watcher.open(server.ws_url, "stage", "beta")
        record = await _record(server.base_url, http, out, viewers=2)
        published = await _publish(server.base_url, tmp_path / "take.npz", "--realtime")
        recorded = await record
        await clock.close()

    take = np.load(out)
    arrived = {r.seq: t for r, t in zip(clock.results, clock.arrivals, strict=True)}
    assert (published, recorded) == (0, 0)
    np.testing.assert_array_equal(take["timestamps"], times[take["seq"]] - times[take["seq"][0]])
    np.testing.assert_array_equal(take["points"], frames[take["seq"]].astype(np.float32))
    before = max(s for s in arrived if s <= 7)
    after = min(s for s in arrived if s >= 8)
    expected = times[after] - times[before]
    assert abs((arrived[after] - arrived[before]) - expected) < 0.1, (arrived, expected)


async def test_publish_without_realtime_does_not_keep_the_pause(settings, rigs, tmp_path, ws_impl):
    stamps = [0.0, 0.02, 0.32, 0.34]
    frames, times = performance(rigs["alpha"], stamps)
    np.savez(tmp_path / "take.npz", points=frames, timestamps=times, fps=50.0)
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        clock = await Watcher.open(server.ws_url, "stage", "beta")
        await _viewers(http, "stage", 1)
        published = await _publish(server.base_url, tmp_path / "take.npz")
        await clock.result_with_seq(3)
        await clock.close()

    assert published == 0
    assert clock.arrivals[-1] - clock.arrivals[0] < 0.2
    assert [r.ts for r in clock.results if r.seq == 3] == [0.34]  # the take's own clock


async def test_record_without_a_publisher_times_out_with_a_clear_message(
    settings, tmp_path, capsys, ws_impl
):
    out = tmp_path / "take.npz"
    async with run_server(settings, ws=ws_impl) as server:
        status = await asyncio.to_thread(
            main, ["record", server.base_url, "stage", "-o", str(out), "--rig", "alpha",
                   "--idle-timeout", "0.5"],
        )  # fmt: skip

    assert status == 2 and not out.exists()
    assert "no frames from channel 'stage' (no frame for 0.5 s)" in capsys.readouterr().err


async def test_record_with_an_unknown_rig_fails_clearly(settings, tmp_path, capsys, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        status = await asyncio.to_thread(
            main, ["record", server.base_url, "stage", "-o", str(tmp_path / "t.npz"),
                   "--rig", "nope"],
        )  # fmt: skip

    assert status == 2 and "UNKNOWN_RIG" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "word"),
    [(["-o", "take.glb"], ".npz"), (["-o", "take.npz", "--frames", "216001"], "--frames"),
     (["-o", "take.npz", "--seconds", "0"], "--seconds")],
)  # fmt: skip
def test_record_refuses_bad_arguments(tmp_path, capsys, monkeypatch, flags, word):
    monkeypatch.chdir(tmp_path)

    status = main(["record", "http://127.0.0.1:9", "stage", *flags])

    assert status == 2 and word in capsys.readouterr().err

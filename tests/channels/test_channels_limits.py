"""Bounds of the channel endpoints: name length, watcher query, connection count, frame rate."""

from __future__ import annotations

import asyncio
import dataclasses
from urllib.parse import quote

import httpx
import numpy as np
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import Error, ErrorCode, Ready, Result
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, refused, tiny_rig, write_rigs

pytestmark = pytest.mark.anyio


async def test_a_name_of_256_characters_is_accepted_and_257_refused(settings, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        ok = await Watcher.open(server.ws_url, "n" * 256, "alpha")
        ready = await ok.next()
        url = channel_url(server.ws_url, "n" * 256, "watch", {"rig": "alpha"})
        error, code = await refused(url.replace("n" * 256, "n" * 257))

    assert isinstance(ready, Ready)
    assert (error.code, code) == (ErrorCode.INVALID_FIELD, 1008)


@pytest.mark.parametrize(("output", "dtype"), [("weights", "f16"), ("points", "f64")])
async def test_a_watchers_ready_says_what_it_receives_and_its_one_limit(
    settings, rigs, output, dtype
):
    async with run_server(settings) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta", output=output, dtype=dtype)
        ready = await watcher.next(Ready)

    rig = rigs["beta"]
    assert (ready.rig, ready.output, ready.dtype) == ("beta", output, dtype)
    assert (list(ready.names), ready.num_points, ready.num_vertices) == (
        list(rig.names), rig.num_points, rig.num_vertices,
    )  # fmt: skip
    assert ready.limits == {"max_message_bytes": settings.max_message_bytes}
    assert ready.moving is None and ready.smoothing is None


async def test_names_with_slashes_and_spaces_are_channels_too(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "studio/a b", "beta")
        publisher = await Publisher.open(server.ws_url, "studio/a b", "alpha")
        await publisher.send(0, points(rigs["alpha"], 0))
        result = await watcher.result_with_seq(0)

    assert result.seq == 0


@pytest.mark.parametrize("name", ["a\r\nb", "line\nbreak", "\n", "tab\tand\x7f"])
async def test_names_with_line_breaks_and_controls_are_channels_too(settings, rigs, name, ws_impl):
    # Issue 13, item 9: CR/LF got a bare HTTP 403 where §2.1 promises any character.
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, name, "beta")
        ready = await watcher.next(Ready)
        publisher = await Publisher.open(server.ws_url, name, "alpha")
        await publisher.send(0, points(rigs["alpha"], 0))
        result = await watcher.result_with_seq(0)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            info = await http.get(f"/v1/channels/{quote(name, safe='')}")
            listed = await http.get("/v1/channels")

    assert ready.rig == "beta" and result.seq == 0
    assert info.status_code == 200
    assert [c["name"] for c in listed.json()["channels"]] == [name]


@pytest.mark.parametrize(
    "query",
    [{}, {"rig": "alpha", "output": "mesh"}, {"rig": "alpha", "dtype": "f64"}, {"rig": "../x"}],
)
async def test_a_bad_watch_query_is_refused_with_a_code(settings, query, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        error, code = await refused(channel_url(server.ws_url, "stage", "watch", query))

    assert error.code in (ErrorCode.INVALID_FIELD, ErrorCode.UNKNOWN_RIG)
    assert error.fatal and code == 1008


async def test_watchers_beyond_max_connections_are_refused_overloaded(settings, ws_impl):
    limited = dataclasses.replace(settings, max_connections=3)
    async with run_server(limited, ws=ws_impl) as server:
        admitted = [await Watcher.open(server.ws_url, "stage", "alpha") for _ in range(3)]
        for watcher in admitted:
            await watcher.next(Ready)
        error, code = await refused(channel_url(server.ws_url, "stage", "watch", {"rig": "alpha"}))

    assert (error.code, code) == (ErrorCode.OVERLOADED, 1013)


async def test_a_publisher_over_max_fps_gets_rate_limited_not_closed(settings, rigs, ws_impl):
    limited = dataclasses.replace(settings, max_fps=5.0, rate_burst=2)
    async with run_server(limited, ws=ws_impl) as server:
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        for seq in range(10):
            await publisher.send(seq, points(rigs["alpha"], seq))
        async with asyncio.timeout(5):
            while not isinstance(message := await publisher.queue.get(), Error):
                pass
        # Still open: the pong comes back (a closed connection raises ConnectionClosed).
        await asyncio.wait_for(await publisher.ws.ping(), 5)
        close_code = publisher.ws.close_code

    assert message.code == ErrorCode.RATE_LIMITED and not message.fatal
    assert close_code is None


async def test_watchers_of_a_rig_that_does_not_fit_are_told_and_others_unaffected(
    settings, rigs, ws_impl
):
    write_rigs(settings.rigs_dir, {"wide": tiny_rig(3, k=6)})
    async with run_server(settings, ws=ws_impl) as server:
        misfit = await Watcher.open(server.ws_url, "stage", "wide")
        fine = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.send(0, points(rigs["alpha"], 0))
        told = await misfit.next(Error)
        result = await fine.result_with_seq(0)
        await publisher.send(1, points(rigs["alpha"], 1))
        await fine.result_with_seq(1)

    assert told.code == ErrorCode.WRONG_POINT_COUNT and not told.fatal
    assert result.seq == 0
    assert not [m for m in publisher.queue._queue if isinstance(m, Error)]


# -- results that would not be finite (issue 13, item 3) -----------------------------------


async def test_a_published_frame_in_other_units_is_refused_before_any_watcher(
    settings, rigs, ws_impl
):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = [
            await Watcher.open(server.ws_url, "stage", "beta", output=output, dtype="f16")
            for output in ("weights", "vertices")
        ]
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.send(0, points(rigs["alpha"], 0) * np.float32(1e5))
        error = await asyncio.wait_for(publisher.queue.get(), 5)
        await publisher.send(1, points(rigs["alpha"], 1))
        first = [await w.next(Result) for w in watchers]

    assert isinstance(error, Error)
    assert (error.code, error.seq, error.fatal) == (ErrorCode.POINTS_OUT_OF_RANGE, 0, False)
    assert [r.seq for r in first] == [1, 1]  # frame 0 reached nobody


async def test_a_watched_rig_overflowing_f16_tells_its_watchers_and_spares_the_others(
    settings, rigs, ws_impl
):
    write_rigs(settings.rigs_dir, {"huge": tiny_rig(1, target_scale=1e5)})
    async with run_server(settings, ws=ws_impl) as server:
        f16 = await Watcher.open(server.ws_url, "stage", "huge", output="vertices", dtype="f16")
        f32 = await Watcher.open(server.ws_url, "stage", "huge", output="vertices", dtype="f32")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        for seq in range(2):
            await publisher.send(seq, points(rigs["alpha"], seq))
            await f32.result_with_seq(seq)
        error = await f16.next(Error)
        await publisher.send(2, points(rigs["alpha"], 2))
        await f32.result_with_seq(2)

    assert (error.code, error.fatal) == (ErrorCode.RESULT_NOT_FINITE, False)
    assert f16.results == []  # nothing non-finite, and nothing else, was sent to it
    assert f16.queue.empty()  # one error per streak, not one per frame
    assert np.isfinite(f32.results[-1].vertices).all()


async def test_an_idle_publisher_gets_idle_timeout_and_its_watchers_stay(settings):
    quiet = dataclasses.replace(settings, idle_timeout=0.3)
    async with run_server(quiet) as server:
        watcher = await Watcher.open(server.ws_url, "quiet", "alpha")
        publisher = await Publisher.open(server.ws_url, "quiet", "alpha")
        async with asyncio.timeout(5):
            error = await publisher.queue.get()
            while not isinstance(error, Error):  # events of the channel may come first
                error = await publisher.queue.get()
            await publisher.ws.wait_closed()
        watcher_open = not watcher.closed.is_set()
        await watcher.close()

    assert isinstance(error, Error)
    assert (error.code, error.fatal) == (ErrorCode.IDLE_TIMEOUT, True)
    assert publisher.ws.close_code == 1008
    assert watcher_open  # a watcher only listens: no idle rule for it

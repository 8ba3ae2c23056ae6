"""Hostile input against a real server, bounded in count and time (issue 13, items 3, 5, 6).

Floods of frames in the wrong units, uploads sent all at once, and a server killed -9 in
the middle of unpacking one: each must end in a documented answer, never a non-finite
result, an unbounded number of buffered uploads, or files left behind for ever.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import io
import os
import threading
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from facecast.cli.bench.harness import facecast_serve
from facecast.client.channel import channel_url
from facecast.protocol import (
    SUBPROTOCOL,
    ClientProtocol,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Ready,
    Result,
)
from facecast.rig import ExampleSet, fit
from facecast.server.settings import Settings
from facecast.server.storage.rig_store import SCRATCH_DIR
from facecast.server.testing import free_port, run_server
from tests.server._server_helpers import folder_members, tiny_example_set, write_example_folder

pytestmark = pytest.mark.anyio

#: Frames per flood; each waits for its answer, so the run is bounded by count, not time.
FLOOD = 300


def example_archive(folder: Path, es: ExampleSet) -> bytes:
    """A stored (uncompressed) zip of a ``facecast.toml`` example folder."""
    write_example_folder(folder, es)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name, data in folder_members(folder).items():
            archive.writestr(name, data)
    return buffer.getvalue()


def hostile_points(rig, rng: np.random.Generator) -> np.ndarray:
    """Points near the neutral, scaled about it by 1 .. 1e7 and moved by up to 1e6 radii."""
    neutral = rig.source_neutral
    centre = neutral.mean(axis=0)
    scale = 10.0 ** rng.uniform(0, 7)
    offset = rng.normal(size=3) * 10.0 ** rng.uniform(-2, 6)
    moved = centre + (neutral - centre + rng.normal(scale=0.05, size=neutral.shape)) * scale
    return (moved + offset).astype(np.float32)


async def connect(url: str):
    return await websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=2**26)


# -- item 3: frames in the wrong units never give a non-finite result ----------------------


@pytest.mark.parametrize("output", ["weights", "vertices"])
async def test_a_flood_of_frames_in_absurd_units_gets_an_answer_each_and_none_non_finite(
    tmp_path, output, ws_impl
):
    # A target beyond f16 for a few frames' worth of displacement, and ordinary frames.
    rig = fit(tiny_example_set(num_vertices=64))
    rng = np.random.default_rng(13)
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=FLOOD)
    answers: collections.Counter[str] = collections.Counter()
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        ws = await connect(f"{server.ws_url}/v1/stream")
        protocol = ClientProtocol()  # refuses any non-finite array it is sent (§4)
        await ws.send(protocol.send(Hello(rig="face", output=output, dtype="f16")))
        assert isinstance(protocol.receive(await ws.recv()), Ready)
        for seq in range(FLOOD):
            points = hostile_points(rig, rng) if seq % 2 else rig.source_neutral
            await ws.send(protocol.send(Frame(seq=seq, ts=seq / 60, points=points)))
            message = protocol.receive(await asyncio.wait_for(ws.recv(), 10))
            assert getattr(message, "seq", None) == seq, message
            if isinstance(message, Result):
                answers["result"] += 1
            else:
                assert isinstance(message, Error) and not message.fatal, message
                answers[message.code.name] += 1
        await ws.close()

    assert sum(answers.values()) == FLOOD
    assert answers["result"] >= FLOOD // 2  # every neutral frame at least
    assert answers["POINTS_OUT_OF_RANGE"] > 0
    assert set(answers) <= {"result", "POINTS_OUT_OF_RANGE", "RESULT_NOT_FINITE"}


async def test_a_publisher_flooding_absurd_frames_never_breaks_an_f16_watcher(tmp_path, ws_impl):
    rig = fit(tiny_example_set(num_vertices=64))
    rng = np.random.default_rng(14)
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=FLOOD)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        watch = channel_url(server.ws_url, "stage", "watch",
                            {"rig": "face", "output": "vertices", "dtype": "f16"})  # fmt: skip
        watcher = await connect(watch)
        watching = ClientProtocol(watching=True)
        publisher = await connect(channel_url(server.ws_url, "stage", "publish"))
        publishing = ClientProtocol()
        await publisher.send(publishing.send(Hello(rig="face")))
        assert isinstance(publishing.receive(await publisher.recv()), Ready)
        refused = 0
        for seq in range(FLOOD):
            absurd = seq % 2 == 1
            points = hostile_points(rig, rng) if absurd else rig.source_neutral
            await publisher.send(publishing.send(Frame(seq=seq, ts=seq / 60, points=points)))
            message = publishing.receive(await asyncio.wait_for(publisher.recv(), 10))
            if isinstance(message, Error):
                assert message.code in (ErrorCode.POINTS_OUT_OF_RANGE,
                                        ErrorCode.RESULT_NOT_FINITE), message  # fmt: skip
                refused += 1
        last = FLOOD - 2  # the last neutral frame
        seen = []
        async with asyncio.timeout(10):
            while not seen or seen[-1] < last:
                message = watching.receive(await watcher.recv())  # raises on non-finite
                if isinstance(message, Result):
                    seen.append(message.seq)
        await publisher.close()
        await watcher.close()

    assert refused > 0 and seen[-1] == last


# -- item 5: uploads sent all at once hold at most max_pending_fits slots -------------------


async def test_ten_uploads_at_once_hold_at_most_max_pending_fits(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_pending_fits=2)
    body = example_archive(tmp_path / "set", tiny_example_set())
    release = asyncio.Event()

    async def held_body():
        yield body[:64]
        await release.wait()
        yield body[64:]

    def refused_so_far(metrics_text: str) -> float:
        for line in metrics_text.splitlines():
            if 'route="/v1/rigs/{rig_id}/examples"' in line and 'status="503"' in line:
                return float(line.rsplit(" ", 1)[1])
        return 0.0

    limits = httpx.Limits(max_connections=20)
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=30, limits=limits) as http,
    ):
        puts = [
            asyncio.create_task(http.put(f"/v1/rigs/r{i}/examples", content=held_body()))
            for i in range(10)
        ]
        deadline = time.monotonic() + 20
        while refused_so_far((await http.get("/metrics")).text) < 8:
            assert time.monotonic() < deadline, "the server did not refuse 8 uploads"
            await asyncio.sleep(0.02)
        holding = server.app.state.pending_fits
        release.set()
        outcomes = await asyncio.gather(*puts, return_exceptions=True)

    statuses = collections.Counter(
        o.status_code if isinstance(o, httpx.Response) else type(o).__name__ for o in outcomes
    )
    assert holding == 2
    # A refused upload may see its connection closed before its body is all sent.
    assert statuses[201] == 2 and statuses[503] + statuses["WriteError"] == 8, statuses


# -- item 6: kill -9 in the middle of an upload leaves nothing behind -----------------------


def _uploads_in_scratch(rigs: Path) -> list[Path]:
    return sorted(rigs.glob(f"{SCRATCH_DIR}/*/upload-*"))


@pytest.mark.slow
def test_uploads_killed_mid_fit_leave_no_files_after_the_next_start(tmp_path):
    # A target large enough that unpacking and loading it takes a while (~1 s here).
    body = example_archive(tmp_path / "set", tiny_example_set(num_vertices=60_000))
    rigs, port = tmp_path / "rigs", free_port()
    server = facecast_serve(rigs, "--log-level", "warning", port=port).start()
    try:
        server.wait_ready("/healthz")
        uploads = [
            threading.Thread(
                target=lambda i=i: _put_ignoring_errors(port, f"big{i}", body), daemon=True
            )
            for i in range(3)
        ]
        for thread in uploads:
            thread.start()
        deadline = time.monotonic() + 60
        while not _uploads_in_scratch(rigs):
            assert time.monotonic() < deadline, "no upload was ever unpacked"
            time.sleep(0.005)  # polling the file system of another process
        server.kill()
        for thread in uploads:
            thread.join(30)
        left = _uploads_in_scratch(rigs)
    finally:
        server.kill()

    with facecast_serve(rigs, "--log-level", "warning", port=port) as restarted:
        restarted.wait_ready("/healthz")
        after = _uploads_in_scratch(rigs)
        folders = [os.listdir(f) for f in (rigs / SCRATCH_DIR).iterdir()]
        listed = httpx.get(f"http://127.0.0.1:{port}/v1/rigs").json()["rigs"]

    assert left  # the kill did leave an unpacked upload behind
    assert after == []
    # Only the new process's own scratch folder, holding nothing but its lock.
    assert folders == [[".lock"]]
    assert listed == []


def _put_ignoring_errors(port: int, rig_id: str, body: bytes) -> None:
    with contextlib.suppress(httpx.TransportError):  # the server was killed under it
        httpx.put(f"http://127.0.0.1:{port}/v1/rigs/{rig_id}/examples", content=body, timeout=60)

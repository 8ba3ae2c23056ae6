"""``/metrics`` attributes stream frames' server time to stages and counts blend batch sizes."""

from __future__ import annotations

import httpx
import pytest
import websockets
from _server_helpers import frame_points, open_session, recv_message, tiny_rig
from prometheus_client.parser import text_string_to_metric_families

from facecast.protocol import Frame, Result, encode
from facecast.server.compute.stages import STAGES
from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

FRAMES = 6


async def stream_vertices(server, rig) -> list[Result]:
    async with websockets.connect(
        f"{server.ws_url}/v1/stream", subprotocols=["facecast.v1"], max_size=None
    ) as ws:
        await open_session(ws, "face", output="vertices", dtype="f16")
        results = []
        for seq in range(FRAMES):
            await ws.send(encode(Frame(seq=seq, ts=seq / 60, points=frame_points(rig, seq))))
            message = await recv_message(ws)
            assert isinstance(message, Result), message
            results.append(message)
    return results


async def scrape(server) -> dict[tuple[str, str], float]:
    async with httpx.AsyncClient(base_url=server.base_url) as http:
        text = (await http.get("/metrics")).text
    samples = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            label = sample.labels.get("stage") or sample.labels.get("frames") or ""
            samples[(sample.name, label)] = sample.value
    return samples


@pytest.mark.parametrize("where", ["inline", "pool"])
async def test_every_stage_of_every_vertices_frame_is_timed(tmp_path, ws_impl, monkeypatch, where):
    from facecast.server.stream import session as session_module

    monkeypatch.setattr(session_module, "INLINE_MAX_SECONDS", 1e9 if where == "inline" else 0.0)
    rig = tiny_rig(num_vertices=2000)
    async with run_server(
        Settings(rigs_dir=tmp_path / "rigs", stage_timing=True), ws=ws_impl
    ) as server:
        server.app.state.store.put_rig("face", rig)
        await stream_vertices(server, rig)
        samples = await scrape(server)

    for stage in STAGES:
        assert samples[("facecast_stage_items_total", stage)] == FRAMES, stage
        assert samples[("facecast_stage_seconds_total", stage)] > 0, stage


async def test_pooled_blends_count_their_batch_sizes(tmp_path, ws_impl, monkeypatch):
    from facecast.server.stream import session as session_module

    monkeypatch.setattr(session_module, "INLINE_MAX_SECONDS", 0.0)
    rig = tiny_rig(num_vertices=2000)
    async with run_server(
        Settings(rigs_dir=tmp_path / "rigs", stage_timing=True), ws=ws_impl
    ) as server:
        server.app.state.store.put_rig("face", rig)
        await stream_vertices(server, rig)
        samples = await scrape(server)

    sizes = {
        int(label): count
        for (name, label), count in samples.items()
        if name == "facecast_blend_batches_total"
    }
    # One session, one frame in flight at a time: every batch is of one frame.
    assert sizes == {1: FRAMES}


async def test_stage_clocks_stay_off_unless_asked_for(tmp_path, ws_impl):
    rig = tiny_rig(num_vertices=2000)
    async with run_server(Settings(rigs_dir=tmp_path / "rigs"), ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        await stream_vertices(server, rig)
        samples = await scrape(server)

    for stage in STAGES:
        assert samples[("facecast_stage_items_total", stage)] == 0, stage

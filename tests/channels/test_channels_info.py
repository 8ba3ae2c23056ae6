"""GET /v1/channels and /v1/channels/{name}: presence, viewers per rig, rates, drops, clones."""

from __future__ import annotations

import httpx
import pytest

from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points

pytestmark = pytest.mark.anyio


async def test_channel_info_reports_presence_viewers_and_rates(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = [
            await Watcher.open(server.ws_url, "stage", rig) for rig in ("alpha", "beta", "beta")
        ]
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        for seq in range(5):
            await publisher.send(seq, points(rigs["alpha"], seq))
            for w in watchers:
                await w.result_with_seq(seq)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            one = (await http.get("/v1/channels/stage")).json()
            listing = (await http.get("/v1/channels")).json()
            missing = await http.get("/v1/channels/nowhere")

    assert one["publisher"] is True
    assert one["viewers"] == 3
    assert one["viewers_per_rig"] == {"alpha": 1, "beta": 2}
    assert one["frames"] == 5 and one["clones_per_frame"] == 2.0
    assert one["fps_in"] > 0 and one["fps_out"] > 0
    assert one["dropped"] == 0
    assert listing == {"channels": [{"name": "stage", "publisher": True, "viewers": 3,
                                     "viewers_per_rig": {"alpha": 1, "beta": 2}}]}  # fmt: skip
    assert missing.status_code == 404 and missing.json()["code"] == "channel_not_found"


async def test_a_channel_disappears_when_its_last_member_leaves(settings, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "alpha")
        await watcher.next()
        await watcher.close()
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            for _ in range(100):
                listing = (await http.get("/v1/channels")).json()
                if not listing["channels"]:
                    break

    assert listing == {"channels": []}


async def test_metrics_count_channel_clones_and_members(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watchers = [await Watcher.open(server.ws_url, "stage", rig) for rig in ("alpha", "beta")]
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        for seq in range(4):
            await publisher.send(seq, points(rigs["alpha"], seq))
            for w in watchers:
                await w.result_with_seq(seq)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            text = (await http.get("/metrics")).text

    assert "facecast_channel_clones_total 8.0" in text
    assert 'facecast_channel_members{role="viewer"} 2.0' in text
    assert 'facecast_channel_members{role="publisher"} 1.0' in text

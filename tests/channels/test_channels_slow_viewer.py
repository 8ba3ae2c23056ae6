"""A viewer that never reads skips to the newest frame and slows nobody else."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest
import websockets

from facecast.client.bridges.channel import channel_url
from facecast.server.outbox import MAX_OUTBOX
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, tiny_rig, write_rigs

pytestmark = pytest.mark.anyio

FRAMES = 90  # 1.5 s at 60 fps


async def test_a_viewer_that_never_reads_does_not_slow_the_others(settings, rigs):
    # A large target: each vertices result is ~240 KB, so the stuck viewer's socket
    # buffers fill after a few frames and the server must skip, not queue.
    write_rigs(settings.rigs_dir, {"big": tiny_rig(7, num_vertices=20_000)})
    async with run_server(settings) as server:
        stuck_url = channel_url(
            server.ws_url, "stage", "watch", {"rig": "big", "output": "vertices"}
        )
        # max_queue=1: the client library stops reading the socket after one message.
        stuck = await websockets.connect(stuck_url, subprotocols=["facecast.v1"], max_queue=1,
                                         max_size=2**26, compression=None)  # fmt: skip
        fast = await Watcher.open(server.ws_url, "stage", "alpha")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        sent_at = {}
        start = time.perf_counter()
        for seq in range(FRAMES):
            await asyncio.sleep(max(0.0, start + seq / 60 - time.perf_counter()))  # 60 fps pacing
            sent_at[seq] = time.time()
            await publisher.send(seq, points(rigs["alpha"], seq), ts=sent_at[seq])
        await fast.result_with_seq(FRAMES - 1)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            info = (await http.get("/v1/channels/stage")).json()
        await stuck.close()

    latencies = np.array([t - r.ts for r, t in zip(fast.results, fast.arrivals, strict=True)])
    assert len(fast.results) >= 0.9 * FRAMES
    assert np.percentile(latencies, 99) < 0.1
    assert info["skipped"] > FRAMES // 2  # the stuck viewer skipped most frames
    assert info["outbox_max"] <= MAX_OUTBOX

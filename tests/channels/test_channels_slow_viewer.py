"""A viewer that never reads skips to the newest frame and slows nobody else."""

from __future__ import annotations

import asyncio

import httpx
import pytest
import websockets

from facecast.client.channel import channel_url
from facecast.server.channels.outbox import MAX_OUTBOX
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, points, tiny_rig, write_rigs

pytestmark = pytest.mark.anyio

FRAMES = 90


async def test_a_viewer_that_never_reads_does_not_slow_the_others(settings, rigs, ws_impl):
    # A large target: each vertices result is ~240 KB, so the stuck viewer's socket
    # buffers fill after a few frames and the server must skip, not queue.
    write_rigs(settings.rigs_dir, {"big": tiny_rig(7, num_vertices=20_000)})
    async with run_server(settings, ws=ws_impl) as server:
        stuck_url = channel_url(
            server.ws_url, "stage", "watch", {"rig": "big", "output": "vertices"}
        )
        # max_queue=1: the client library stops reading the socket after one message.
        stuck = await websockets.connect(stuck_url, subprotocols=["facecast.v1"], max_queue=1,
                                         max_size=2**26, compression=None)  # fmt: skip
        fast = await Watcher.open(server.ws_url, "stage", "alpha")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        # Lockstep with the fast viewer: each frame goes out once the fast viewer has the
        # one before, so its outbox is empty at every frame and it may skip none. Were the
        # fan-out waiting on the stuck viewer's full socket, a frame would not reach it.
        for seq in range(FRAMES):
            await publisher.send(seq, points(rigs["alpha"], seq))
            await fast.result_with_seq(seq, timeout=10)
            # At most 60 fps: unpaced, lockstep on a quiet machine outruns max_fps (240)
            # once the bucket's rate_burst is spent, and a frame is RATE_LIMITED.
            await asyncio.sleep(1 / 60)  # pacing the performer, not synchronisation
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            info = (await http.get("/v1/channels/stage")).json()
        # Gone as a frozen tab goes, without a closing handshake: a close would wait
        # websockets' close_timeout (10 s) for the server's close frame it never reads.
        stuck.transport.abort()
        await stuck.wait_closed()

    assert [r.seq for r in fast.results] == list(range(FRAMES))
    assert info["skipped"] > FRAMES // 2  # the stuck viewer skipped most frames
    assert info["outbox_max"] <= MAX_OUTBOX

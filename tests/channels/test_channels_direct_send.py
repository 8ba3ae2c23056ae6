"""Results written straight to the socket: exact frames, both uvicorn WebSocket stacks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from websockets.frames import Frame, Opcode

from facecast.server.serving.seam import binary_frame
from facecast.server.testing import WS_IMPLEMENTATIONS, run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points, wait_for

pytestmark = [
    pytest.mark.anyio,
    # uvicorn deprecates its legacy ``websockets`` stack, which the server still supports.
    pytest.mark.filterwarnings("ignore::uvicorn.config.UvicornDeprecationWarning"),
]

#: Payload lengths at and around RFC 6455's length encodings (7-bit, 16-bit, 64-bit).
_EDGES = (0, 1, 125, 126, 127, 65535, 65536, 70000)


@given(
    length=st.one_of(st.sampled_from(_EDGES), st.integers(0, 70_000)),
    fill=st.binary(min_size=1, max_size=8),
)
def test_binary_frame_is_the_frame_websockets_would_send(length, fill):
    data = (fill * (length // len(fill) + 1))[:length]

    frame = binary_frame(data)

    expected = Frame(Opcode.BINARY, data).serialize(mask=False, extensions=[])
    assert frame == expected


def test_binary_frame_is_built_once_for_the_same_result():
    data = bytes(300)

    first, second = binary_frame(data), binary_frame(data)

    assert first is second


def _channel_members(server, name: str) -> list:
    channel = server.app.state.channels.channels[name]
    return [m for group in channel.members.values() for m in group if m.watcher]


@pytest.mark.parametrize("ws", WS_IMPLEMENTATIONS)
async def test_watchers_get_every_result_intact_on_both_websocket_stacks(settings, rigs, ws):
    async with run_server(settings, ws=ws) as server:
        watchers = [await Watcher.open(server.ws_url, "stage", rig_id) for rig_id in RIG_IDS]
        publisher = await Publisher.open(server.ws_url, "stage", RIG_IDS[0])
        members = _channel_members(server, "stage")
        for seq in range(20):
            await publisher.send(seq, points(rigs[RIG_IDS[0]], seq))
            for watcher in watchers:
                await watcher.result_with_seq(seq)

    # Direct writes only where uvicorn's protocol allows them (sansio, no extension).
    assert [m.direct for m in members] == [ws == "websockets-sansio"] * len(RIG_IDS)
    for watcher, rig_id in zip(watchers, RIG_IDS, strict=True):
        seqs = [r.seq for r in watcher.results]
        assert seqs == list(range(20))
        assert watcher.results[-1].weights.shape == (len(rigs[rig_id].names),)
        assert np.all(np.isfinite(watcher.results[-1].weights))


@pytest.mark.parametrize("ws", WS_IMPLEMENTATIONS)
async def test_a_watcher_that_leaves_mid_stream_costs_the_others_nothing(settings, rigs, ws):
    async with run_server(settings, ws=ws) as server:
        leaving = await Watcher.open(server.ws_url, "stage", RIG_IDS[0])
        staying = await Watcher.open(server.ws_url, "stage", RIG_IDS[0])
        publisher = await Publisher.open(server.ws_url, "stage", RIG_IDS[0])
        for seq in range(15):
            if seq == 5:
                await leaving.close()
            await publisher.send(seq, points(rigs[RIG_IDS[0]], seq))
            await staying.result_with_seq(seq)
        await wait_for(lambda: len(_channel_members(server, "stage")) == 1, what="leaver removed")

    assert [r.seq for r in staying.results] == list(range(15))
    assert leaving.close_code == 1000

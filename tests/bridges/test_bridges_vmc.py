"""VMC out: OSC bundles with OK, T, Blend/Val per expression then Apply, over real UDP."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pythonosc.osc_packet import OscPacket
from websockets.exceptions import InvalidStatus

from facecast.client.bridges.channel import channel_url, watch_channel
from facecast.client.bridges.vmc import (
    VmcSender,
    run_vmc_bridge,
    vmc_frame_bundle,
    vmc_names,
    vmc_status_bundle,
)
from facecast.client.connection import ConnectionFailed, Reconnect, connect
from facecast.protocol import FaceLost, Ready, Result
from facecast.server.settings import Settings
from facecast.server.testing import run_server

RIG_ID = "arkit"


@pytest.fixture
def osc_receiver():
    """A real UDP socket on 127.0.0.1 standing in for the avatar app."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(10)
    yield sock
    sock.close()


def _messages(datagram: bytes) -> list[tuple[str, list]]:
    return [(m.message.address, list(m.message.params)) for m in OscPacket(datagram).messages]


def test_demo_and_vrm1_names_map_to_vrm_presets_and_others_pass_through():
    names = ("aa", "ee", "oo", "happy", "anger", "sad", "surprise", "blink", "fear", "jawOpen")
    assert vmc_names(names) == (
        "A", "E", "U", "Joy", "Angry", "Sorrow", "Surprised", "Blink", "fear", "jawOpen",
    )  # fmt: skip
    assert vmc_names(("Happy", "oo"), {"oo": "O"}) == ("Joy", "O")


def test_frame_bundle_sends_ok_time_values_in_order_then_apply(osc_receiver):
    names = ("A", "Joy", "Blink")
    with VmcSender(*osc_receiver.getsockname()) as sender:
        sender.send(vmc_frame_bundle(names, np.array([0.25, 1.5, -0.5]), 12.5))
        messages = _messages(osc_receiver.recv(65536))
    assert messages[0] == ("/VMC/Ext/OK", [1, 3, 0, 1])
    assert messages[1] == ("/VMC/Ext/T", [12.5])
    assert messages[2:5] == [
        ("/VMC/Ext/Blend/Val", ["A", 0.25]),
        ("/VMC/Ext/Blend/Val", ["Joy", 1.0]),  # clamped to [0, 1]
        ("/VMC/Ext/Blend/Val", ["Blink", 0.0]),
    ]
    assert messages[5:] == [("/VMC/Ext/Blend/Apply", [])]


def test_unclamped_bundle_keeps_values_outside_the_unit_range():
    messages = _messages(vmc_frame_bundle(("A",), np.array([1.5]), 0.0, clamp=False))
    assert messages[2] == ("/VMC/Ext/Blend/Val", ["A", 1.5])


def test_status_bundle_reports_tracking_lost():
    assert _messages(vmc_status_bundle(False, 1.0)) == [
        ("/VMC/Ext/OK", [1, 3, 0, 0]),
        ("/VMC/Ext/T", [1.0]),
    ]


def test_sending_to_an_absent_receiver_does_not_raise():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    with VmcSender("127.0.0.1", port) as sender:
        for _ in range(3):
            sender.send(vmc_status_bundle(True, 0.0))
        assert sender.sent + sender.failed == 3


@pytest.fixture
def server_settings(tmp_path, cloning_rig):
    cloning_rig.save(tmp_path / f"{RIG_ID}.rig")
    return Settings(rigs_dir=tmp_path)


@pytest.mark.anyio
async def test_server_weights_reach_the_avatar_app_as_vmc(
    server_settings, osc_receiver, source_rig, cloning_rig
):
    rng = np.random.default_rng(5)
    frames = source_rig.points(rng.uniform(0, 1, size=(3, 52)))
    received: list[Result] = []

    async with (
        run_server(server_settings) as server,
        connect(server.base_url, RIG_ID) as session,
    ):

        async def messages():
            # What a watcher yields: ready, then results (and channel events).
            yield session.ready
            for points in frames:
                received.append(await session.clone(points))
                yield received[-1]
            yield FaceLost(since=1.0)

        with VmcSender(*osc_receiver.getsockname()) as sender:
            stats = await run_vmc_bridge(messages(), sender, clock=lambda: 2.0)

    assert (stats.frames, stats.status) == (3, 1)
    names = vmc_names(cloning_rig.names[1:])
    for result in received:
        datagram = _messages(osc_receiver.recv(65536))
        values = [p[1] for a, p in datagram if a == "/VMC/Ext/Blend/Val"]
        sent_names = [p[0] for a, p in datagram if a == "/VMC/Ext/Blend/Val"]
        assert sent_names == list(names)
        expected = np.clip(np.asarray(result.weights[1:], dtype=np.float64), 0, 1)
        assert np.allclose(values, expected, atol=1e-6)
    assert _messages(osc_receiver.recv(65536))[0] == ("/VMC/Ext/OK", [1, 3, 0, 0])


@pytest.mark.anyio
async def test_channel_weights_reach_the_avatar_app_as_vmc(
    server_settings, osc_receiver, source_rig
):
    import asyncio

    from facecast.client.bridges.channel import FramePublisher
    from facecast.protocol import Hello

    async with run_server(server_settings) as server:
        url = channel_url(server.base_url, "stage", "watch", {"rig": RIG_ID})
        messages = watch_channel(url, reconnect=Reconnect(attempts=0))
        try:
            first = await anext(messages)
        except ConnectionFailed as exc:
            if isinstance(exc.__cause__, InvalidStatus):
                pytest.skip("channels not available")
            raise
        assert isinstance(first, Ready)

        async def replay():
            yield first
            async for message in messages:
                yield message

        answered = asyncio.Event()
        publisher = FramePublisher(
            channel_url(server.base_url, "stage", "publish"),
            Hello(rig=RIG_ID),
            on_result=lambda _: answered.set(),
        )
        with VmcSender(*osc_receiver.getsockname()) as sender:
            bridge = asyncio.create_task(run_vmc_bridge(replay(), sender, max_frames=2))
            async with asyncio.timeout(20), publisher:
                for seed in range(2):
                    answered.clear()
                    await publisher.send(source_rig.points(np.full(52, 0.1 * seed)), ts=seed)
                    await answered.wait()
                stats = await bridge
        await messages.aclose()
    assert stats.frames == 2
    datagrams = [_messages(osc_receiver.recv(65536)) for _ in range(stats.frames + stats.status)]
    frames = [d for d in datagrams if d[-1][0] == "/VMC/Ext/Blend/Apply"]
    assert len(frames) == 2

"""VMC out: names per receiver convention, bundles split to fit UDP, tracking, head, failures.

The receiver in these tests is python-osc's own UDP server on 127.0.0.1 (`OscReceiver`),
standing in for the avatar app.
"""

from __future__ import annotations

import asyncio
import logging
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.osc_packet import OscPacket

from facecast.cli.bridges.vmc import (
    SAFE_DATAGRAM,
    VmcFrameEncoder,
    VmcSender,
    head_bone_message,
    run_vmc_bridge,
    vmc_frame_datagrams,
    vmc_head_bundle,
    vmc_status_bundle,
)
from facecast.cli.bridges.vmc_names import vmc_names
from facecast.cli.errors import CommandError
from facecast.client.channel import FramePublisher, channel_url, watch_channel
from facecast.client.connection import Reconnect, connect
from facecast.protocol import ChannelLive, FaceLost, Hello, Ready, Result
from facecast.rig.sources.source_rig import ARKIT_NAMES
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import OscReceiver, run_command

RIG_ID = "arkit"


@pytest.fixture
def osc_receiver():
    receiver = OscReceiver()
    yield receiver
    receiver.close()


def _messages(datagram: bytes) -> list[tuple[str, list]]:
    return [(m.message.address, list(m.message.params)) for m in OscPacket(datagram).messages]


def _values(messages) -> list[tuple[str, float]]:
    return [tuple(p) for a, p in messages if a == "/VMC/Ext/Blend/Val"]


# -- names ----------------------------------------------------------------------------

_RIG_NAMES = ("aa", "happy", "surprised", "blinkLeft", "eyeBlinkLeft", "jawOpen", "fear")


@pytest.mark.parametrize(
    ("convention", "expected"),
    [
        ("vrm0", ("A", "Joy", "Surprised", "Blink_L", "Blink_L", "JawOpen", "fear")),
        ("vrm1", ("aa", "happy", "surprised", "blinkLeft", "blinkLeft", "jawOpen", "fear")),
        ("perfectsync", ("A", "Joy", "Surprised", "Blink_L", "EyeBlinkLeft", "JawOpen", "fear")),
    ],
)
def test_names_follow_the_receivers_convention(convention, expected):
    assert vmc_names(_RIG_NAMES, convention) == expected


def test_vrm0_is_the_default_and_vrm0_spellings_map_to_vrm1_ones():
    assert vmc_names(("Joy", "Sorrow", "Blink_R", "oo")) == ("Joy", "Sorrow", "Blink_R", "U")
    assert vmc_names(("Joy", "Sorrow", "Blink_R", "oo"), "vrm1") == (
        "happy", "sad", "blinkRight", "ou",
    )  # fmt: skip


def test_perfect_sync_sends_every_arkit_name_in_pascal_case_whatever_the_rig_case():
    names = vmc_names([n.lower() for n in ARKIT_NAMES], "perfectsync")
    assert names == tuple(n[0].upper() + n[1:] for n in ARKIT_NAMES)
    assert "MouthSmileLeft" in names and "TongueOut" in names


def test_overrides_win_over_the_convention():
    assert vmc_names(("happy", "oo"), "vrm1", {"oo": "O"}) == ("happy", "O")


def test_an_unknown_convention_is_a_value_error_naming_the_choices():
    with pytest.raises(ValueError, match="vrm0, vrm1, perfectsync"):
        vmc_names(("aa",), "vrm2")


# -- bundles --------------------------------------------------------------------------


def test_frame_sends_ok_time_values_in_order_then_apply(osc_receiver):
    names = ("A", "Joy", "Blink")
    with VmcSender(*osc_receiver.address) as sender:
        sender.send_all(vmc_frame_datagrams(names, np.array([0.25, 1.5, -0.5]), 12.5))
        messages = osc_receiver.until_apply()
    assert messages[0] == ("/VMC/Ext/OK", [1, 3, 0, 1])
    assert messages[1] == ("/VMC/Ext/T", [12.5])
    assert messages[2:5] == [
        ("/VMC/Ext/Blend/Val", ["A", 0.25]),
        ("/VMC/Ext/Blend/Val", ["Joy", 1.0]),  # clamped to [0, 1]
        ("/VMC/Ext/Blend/Val", ["Blink", 0.0]),
    ]
    assert messages[5:] == [("/VMC/Ext/Blend/Apply", [])]


def test_unclamped_frame_keeps_values_outside_the_unit_range():
    (datagram,) = vmc_frame_datagrams(("A",), np.array([1.5]), 0.0, clamp=False)
    assert _messages(datagram)[2] == ("/VMC/Ext/Blend/Val", ["A", 1.5])


def test_a_name_with_a_nul_is_refused_since_osc_strings_end_at_nul():
    with pytest.raises(ValueError, match="NUL"):
        VmcFrameEncoder(("Jaw\x00Open",))


def test_a_name_that_is_no_utf8_is_refused():
    with pytest.raises(ValueError, match="UTF-8"):
        VmcFrameEncoder(("\ud800",))


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e39])
def test_weights_that_are_no_finite_float32_are_refused(value):
    with pytest.raises(ValueError, match="NaN"):
        vmc_frame_datagrams(("A",), np.array([value]), 0.0, clamp=False)


def test_a_perfect_sync_frame_is_split_into_datagrams_under_the_safe_size(osc_receiver):
    names = vmc_names(ARKIT_NAMES, "perfectsync")
    weights = np.linspace(0, 1, len(names))
    datagrams = vmc_frame_datagrams(names, weights, 1.0)
    assert len(datagrams) > 1
    assert all(len(d) <= SAFE_DATAGRAM for d in datagrams)
    # Apply only at the very end, so a receiver applies the whole frame at once.
    applies = [sum(a == "/VMC/Ext/Blend/Apply" for a, _ in _messages(d)) for d in datagrams]
    assert applies == [0] * (len(datagrams) - 1) + [1]
    with VmcSender(*osc_receiver.address) as sender:
        assert sender.send_all(datagrams)
        messages = osc_receiver.until_apply()
    received = _values(messages)
    assert [n for n, _ in received] == list(names)
    assert np.allclose([v for _, v in received], weights, atol=1e-6)


def _python_osc_message(address: str, *args):
    builder = OscMessageBuilder(address)
    for arg in args:
        kind = {str: "s", int: "i", float: "f"}[type(arg)]
        builder.add_arg(arg, kind)
    return builder.build()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.text(st.characters(codec="utf-8", exclude_characters="\x00"), min_size=1, max_size=40),
        min_size=1,
        max_size=80,
    ),
    st.data(),
    st.booleans(),
    st.floats(0, 1e6, width=32),
    st.booleans(),
    st.integers(576, 4000),
)
def test_encoder_bytes_are_python_oscs_own_messages_and_bundles(
    names, data, tracking, t, with_head, max_datagram
):
    weights = data.draw(st.lists(st.floats(-2, 2, width=32), min_size=len(names),
                                 max_size=len(names)))  # fmt: skip
    head = head_bone_message((0.1, 0.2, 0.3)) if with_head else None
    datagrams = VmcFrameEncoder(names, max_datagram=max_datagram).datagrams(
        np.array(weights), t, tracking=tracking, head=head
    )
    expected = [
        _python_osc_message("/VMC/Ext/OK", 1, 3, 0, int(tracking)),
        _python_osc_message("/VMC/Ext/T", float(t)),
        *([head] if head is not None else []),
        *[
            _python_osc_message("/VMC/Ext/Blend/Val", n, float(np.clip(w, 0, 1)))
            for n, w in zip(names, weights, strict=True)
        ],
        _python_osc_message("/VMC/Ext/Blend/Apply"),
    ]
    got = []
    for datagram in datagrams:
        messages = [m.message for m in OscPacket(datagram).messages]
        rebuilt = OscBundleBuilder(IMMEDIATELY)
        for message in messages:
            rebuilt.add_content(message)
        assert rebuilt.build().dgram == datagram  # python-osc's own bundle bytes
        assert len(datagram) <= max_datagram or len(messages) == 1
        got += messages
    assert [m.dgram for m in got] == [m.dgram for m in expected]  # python-osc's messages


@pytest.mark.parametrize("size", [575, 65508])
def test_a_datagram_bound_outside_udp_limits_is_refused(size):
    with pytest.raises(ValueError, match="max_datagram"):
        vmc_frame_datagrams(("A",), np.zeros(1), 0.0, max_datagram=size)


def test_status_bundle_reports_tracking_lost():
    assert _messages(vmc_status_bundle(False, 1.0)) == [
        ("/VMC/Ext/OK", [1, 3, 0, 0]),
        ("/VMC/Ext/T", [1.0]),
    ]


# -- head -----------------------------------------------------------------------------


def _quaternion(message) -> np.ndarray:
    assert message.address == "/VMC/Ext/Bone/Pos"
    params = list(message.params)
    assert params[0] == "Head" and params[1:4] == [0.0, 0.0, 0.0]
    return np.array(params[4:], dtype=np.float64)


@pytest.mark.parametrize(
    ("angles", "expected"),
    [
        # Unity is left-handed with the avatar's left at -x: about y and z the turn
        # reverses, about x (ear to ear) it does not.
        ((0.3, 0.0, 0.0), (0.0, -math.sin(0.15), 0.0, math.cos(0.15))),
        ((0.0, 0.2, 0.0), (math.sin(0.1), 0.0, 0.0, math.cos(0.1))),
        ((0.0, 0.0, 0.1), (0.0, 0.0, -math.sin(0.05), math.cos(0.05))),
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ],
)
def test_head_angles_become_a_unity_quaternion_on_the_head_bone(angles, expected):
    q = _quaternion(head_bone_message(angles))
    assert np.allclose(q, expected, atol=1e-6) or np.allclose(q, -np.array(expected), atol=1e-6)


def test_head_bundle_reaches_the_receiver_as_one_bone_message(osc_receiver):
    with VmcSender(*osc_receiver.address) as sender:
        assert sender.send(vmc_head_bundle((0.3, -0.2, 0.1), position=(0.0, 0.06, 0.0)))
        address, params = osc_receiver.get()
    assert address == "/VMC/Ext/Bone/Pos" and params[0] == "Head"
    assert np.allclose(params[1:4], [0.0, 0.06, 0.0], atol=1e-7)
    assert math.isclose(float(np.linalg.norm(params[4:])), 1.0, rel_tol=1e-6)


# -- sending --------------------------------------------------------------------------


def test_send_failures_are_counted_and_logged_once_not_raised(caplog):
    # Linux refuses a broadcast address without SO_BROADCAST: a failure on every send.
    with VmcSender("255.255.255.255", 9) as sender, caplog.at_level(logging.WARNING):
        results = [sender.send(vmc_status_bundle(True, 0.0)) for _ in range(5)]
    assert results == [False] * 5
    assert (sender.sent, sender.failed) == (0, 5)
    assert isinstance(sender.last_error, OSError)
    warnings = [r for r in caplog.records if "VMC send" in r.getMessage()]
    assert len(warnings) == 1 and "255.255.255.255" in warnings[0].getMessage()


# -- the bridge loop --------------------------------------------------------------------


def _ready() -> Ready:
    return Ready(
        session="s", rig="r", names=("neutral", "aa"), num_points=1, num_vertices=3,
        output="weights", dtype="f32",
    )  # fmt: skip


def _result(seq: int, weights) -> Result:
    return Result(seq=seq, ts=float(seq), weights=np.asarray(weights, dtype=np.float32))


@pytest.mark.anyio
async def test_tracking_stays_off_from_face_lost_until_the_channel_is_live_again(osc_receiver):
    ready = _ready()

    async def messages():
        yield ready
        yield _result(0, [0.0, 0.8])
        yield FaceLost(since=0.0)
        yield _result(0, [0.5, 0.4])  # the server's eased results: same seq
        yield _result(0, [1.0, 0.0])
        yield ChannelLive(channel="stage")
        yield _result(1, [0.0, 0.6])

    with VmcSender(*osc_receiver.address) as sender:
        stats = await run_vmc_bridge(messages(), sender, clock=lambda: 1.0)
    flags = []
    for _ in range(stats.frames + stats.status):
        address, params = osc_receiver.get()
        while address != "/VMC/Ext/OK":
            address, params = osc_receiver.get()
        flags.append(params[3])
    assert (stats.frames, stats.status) == (4, 2)
    assert flags == [1, 0, 0, 0, 1, 1]


@pytest.mark.anyio
async def test_the_bridge_counts_frames_it_could_not_send():
    ready = _ready()

    async def messages():
        yield ready
        for seq in range(3):
            yield _result(seq, [0.0, 0.5])

    with VmcSender("255.255.255.255", 9) as sender:
        stats = await run_vmc_bridge(messages(), sender)
    assert (stats.frames, stats.failed_frames, sender.failed) == (3, 3, 3)


@pytest.fixture
def server_settings(tmp_path, cloning_rig):
    cloning_rig.save(tmp_path / f"{RIG_ID}.rig")
    return Settings(rigs_dir=tmp_path)


@pytest.mark.anyio
async def test_server_weights_reach_the_avatar_app_as_vmc(
    server_settings, osc_receiver, source_rig, cloning_rig, ws_impl
):
    rng = np.random.default_rng(5)
    frames = source_rig.points(rng.uniform(0, 1, size=(3, 52)))
    received: list[Result] = []

    async with (
        run_server(server_settings, ws=ws_impl) as server,
        connect(server.base_url, RIG_ID) as session,
    ):

        async def messages():
            # What a watcher yields: ready, then results (and channel events).
            yield session.ready
            for points in frames:
                received.append(await session.clone(points))
                yield received[-1]
            yield FaceLost(since=1.0)

        with VmcSender(*osc_receiver.address) as sender:
            stats = await run_vmc_bridge(messages(), sender, clock=lambda: 2.0)

    assert (stats.frames, stats.status) == (3, 1)
    names = vmc_names(cloning_rig.names[1:])
    for result in received:
        messages = osc_receiver.until_apply()
        assert [n for n, _ in _values(messages)] == list(names)
        expected = np.clip(np.asarray(result.weights[1:], dtype=np.float64), 0, 1)
        assert np.allclose([v for _, v in _values(messages)], expected, atol=1e-6)
    assert osc_receiver.get() == ("/VMC/Ext/OK", [1, 3, 0, 0])


@pytest.mark.anyio
async def test_channel_weights_reach_the_avatar_app_as_vmc(
    server_settings, osc_receiver, source_rig, cloning_rig, ws_impl
):
    async with run_server(server_settings, ws=ws_impl) as server:
        url = channel_url(server.base_url, "stage", "watch", {"rig": RIG_ID})
        messages = watch_channel(url, reconnect=Reconnect(attempts=0))
        first = await anext(messages)
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
        with VmcSender(*osc_receiver.address) as sender:
            bridge = asyncio.create_task(run_vmc_bridge(replay(), sender, max_frames=2))
            async with asyncio.timeout(20), publisher:
                for seed in range(2):
                    answered.clear()
                    await publisher.send(source_rig.points(np.full(52, 0.1 * seed)), ts=seed)
                    await answered.wait()
                stats = await bridge
        await messages.aclose()
    assert stats.frames == 2
    for _ in range(2):
        assert len(_values(osc_receiver.until_apply())) == len(cloning_rig.names) - 1


# -- the command --------------------------------------------------------------------------


@pytest.mark.parametrize("size", ["100", "70000"])
def test_bridge_vmc_refuses_a_datagram_bound_outside_udp_limits(size):
    with pytest.raises(CommandError, match="--max-datagram"):
        run_command(
            "bridge",
            ["bridge", "vmc", "http://127.0.0.1:9", "--channel", "c", "--rig", "r",
             "--max-datagram", size],
        )  # fmt: skip


async def _run_vmc_command(server, source_rig, *options: str) -> int:
    """``bridge vmc ... --frames 2`` against a publisher that keeps the channel busy."""
    argv = ["bridge", "vmc", server.base_url, "--channel", "stage", "--rig", RIG_ID,
            "--frames", "2", *options]  # fmt: skip
    command = asyncio.create_task(asyncio.to_thread(run_command, "bridge", argv))
    # Frames published before the command watches are simply not seen by it: keep
    # publishing, one per answer, until it has sent its two frames and returned.
    answered = asyncio.Event()
    publisher = FramePublisher(
        channel_url(server.base_url, "stage", "publish"),
        Hello(rig=RIG_ID),
        on_result=lambda _: answered.set(),
    )
    async with asyncio.timeout(30), publisher:
        seed = 0
        while not command.done():
            answered.clear()
            await publisher.send(source_rig.points(np.full(52, 0.1 * (seed % 5))), ts=seed)
            seed += 1
            waiter = asyncio.ensure_future(answered.wait())
            await asyncio.wait([command, waiter], return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
    return await command


@pytest.mark.anyio
async def test_bridge_vmc_command_sends_perfect_sync_names_and_reports_datagrams(
    server_settings, osc_receiver, source_rig, cloning_rig, capsys, ws_impl
):
    host, port = osc_receiver.address
    async with run_server(server_settings, ws=ws_impl) as server:
        code = await _run_vmc_command(
            server, source_rig, "--send", f"{host}:{port}", "--names", "perfectsync"
        )
    assert code == 0
    expected = vmc_names(cloning_rig.names[1:], "perfectsync")
    for _ in range(2):
        assert tuple(n for n, _ in _values(osc_receiver.until_apply())) == expected
    err = capsys.readouterr().err
    assert "2 frames sent as VMC (perfectsync names)" in err and ", 0 failed" in err


@pytest.mark.anyio
async def test_bridge_vmc_command_reports_its_send_failures(
    server_settings, source_rig, capsys, ws_impl
):
    async with run_server(server_settings, ws=ws_impl) as server:
        code = await _run_vmc_command(server, source_rig, "--send", "255.255.255.255:9")
    assert code == 0
    err = capsys.readouterr().err
    assert "2 frames sent as VMC (vrm0 names), 0 datagrams sent, " in err
    assert "failed (last: [Errno 13] Permission denied)" in err

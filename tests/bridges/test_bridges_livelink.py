"""Live Link Face: packet bytes -> frames, UDP on 127.0.0.1 -> points, and points -> a server."""

from __future__ import annotations

import asyncio
import contextlib
import queue
import socket
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from facecast.cli.bridges.livelink import (
    MAX_PACKET_BYTES,
    LiveLinkPacketError,
    open_livelink_receiver,
    parse_livelink_packet,
    run_livelink_bridge,
)
from facecast.cli.bridges.vmc import head_bone_message
from facecast.client.channel import FramePublisher, channel_url, watch_channel
from facecast.client.connection import Reconnect
from facecast.client.urls import stream_url
from facecast.protocol import ChannelLive, Hello, Ready, Result
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import OscReceiver, livelink_packet, pylivelinkface_packet, run_command

RIG_ID = "arkit"


def _values(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = np.concatenate([rng.uniform(0, 1, 52), rng.uniform(-0.4, 0.4, 9)])
    return values.astype(np.float32)


# -- the parser -------------------------------------------------------------------------


def test_golden_packet_bytes_decode_field_by_field():
    data = bytes.fromhex(
        "06"  # version
        "00000001" "44"  # device id "D"
        "00000002" "5331"  # subject "S1"
        "0000003c" "3f000000"  # frame 60, sub-frame 0.5
        "0000001e" "00000001"  # 30 / 1 fps
        "3d"  # 61 values
        "3f800000" + "00000000" * 51 + "3e800000" + "00000000" * 8  # 1.0, ..., head yaw 0.25
    )  # fmt: skip
    frame = parse_livelink_packet(data)
    assert (frame.version, frame.device_id, frame.subject) == (6, "D", "S1")
    assert (frame.frame_number, frame.sub_frame, frame.rate_numerator) == (60, 0.5, 30)
    assert frame.time == pytest.approx(60.5 / 30)
    assert frame.weights[0] == 1.0 and not frame.weights[1:].any()
    assert frame.head[0] == 0.25 and not frame.head[1:].any()


@settings(max_examples=50, deadline=None)
@given(arrays(np.float32, 61, elements=st.floats(-2, 2, width=32)), st.text(max_size=40))
def test_packets_round_trip_the_values_and_names(values, subject):
    data = livelink_packet(values, subject=subject.encode())
    frame = parse_livelink_packet(data)
    assert np.array_equal(frame.weights, values[:52].astype(np.float64))
    assert np.array_equal(frame.head, values[52:].astype(np.float64))
    assert frame.subject == subject


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_parser_raises_only_its_own_error_on_arbitrary_bytes(data):
    try:
        parse_livelink_packet(bytes([6]) + data)
    except LiveLinkPacketError as exc:
        assert exc.code


def test_packet_ending_after_the_subject_has_no_face():
    data = livelink_packet([])[: 1 + 4 + 36 + 4 + 6]
    frame = parse_livelink_packet(data)
    assert frame.subject == "iPhone" and not frame.has_face and frame.weights is None


_GOOD = livelink_packet(_values(0))


@pytest.mark.parametrize(
    ("data", "code"),
    [
        (b"", "truncated"),
        (bytes([5]) + _GOOD[1:], "unsupported_version"),
        (_GOOD[:3], "truncated"),
        (_GOOD[:-1], "truncated"),
        (_GOOD + b"\0", "trailing_bytes"),
        (livelink_packet(_values(0), count=52), "bad_value_count"),
        (livelink_packet([float("nan"), *_values(0)[1:]]), "non_finite"),
        (bytes([6]) + struct.pack(">i", -1), "bad_string"),
        (bytes([6]) + struct.pack(">i", 1 << 30) + b"x", "bad_string"),
        (livelink_packet(_values(0), subject=b"\xff\xfe"), "bad_string"),
        (_GOOD + b"\0" * MAX_PACKET_BYTES, "too_large"),
    ],
)
def test_bad_packets_raise_a_coded_value_error(data, code):
    with pytest.raises(ValueError) as info:
        parse_livelink_packet(data)
    assert isinstance(info.value, LiveLinkPacketError) and info.value.code == code


# -- PyLiveLinkFace's layout --------------------------------------------------------------


def test_golden_pylivelinkface_packet_with_a_short_id_and_no_face():
    data = bytes.fromhex(
        "06000000"  # version 6, little-endian uint32
        "2449"  # "$I": device id, no length
        "00000002" "5331"  # subject "S1"
    )  # fmt: skip
    frame = parse_livelink_packet(data)
    assert (frame.layout, frame.device_id, frame.subject) == ("pylivelinkface", "$I", "S1")
    assert not frame.has_face


def test_golden_pylivelinkface_packet_with_a_face():
    data = bytes.fromhex(
        "06000000" "246964"  # version, "$id"
        "00000002" "5331"  # subject "S1"
        "0000003c" "3f000000" "0000001e" "00000001"  # frame 60 + 0.5 at 30/1 fps
        "3d" "3f800000" + "00000000" * 51 + "3e800000" + "00000000" * 8
    )  # fmt: skip
    frame = parse_livelink_packet(data)
    assert (frame.layout, frame.device_id, frame.subject) == ("pylivelinkface", "$id", "S1")
    assert frame.time == pytest.approx(60.5 / 30)
    assert frame.weights[0] == 1.0 and not frame.weights[1:].any()
    assert frame.head[0] == 0.25


def test_a_pylivelinkface_uuid_packet_is_byte_for_byte_an_app_packet():
    uuid = b"0c0d3c5e-6f8a-11ee-9d2e-3f4a5b6c7d8e"
    values = _values(2)
    data = pylivelinkface_packet(values, device=b"$" + uuid, subject="iPhone")
    assert data == livelink_packet(values, device=uuid, frame=7, sub_frame=0.5)
    frame = parse_livelink_packet(data)
    assert (frame.layout, frame.device_id) == ("livelinkface", uuid.decode())


def test_a_subject_name_counted_in_characters_is_read_whole():
    values = _values(3)
    frame = parse_livelink_packet(pylivelinkface_packet(values, subject="Jürgen's 顔"))
    assert (frame.layout, frame.subject, frame.device_id) == (
        "pylivelinkface", "Jürgen's 顔", "$my-phone",
    )  # fmt: skip
    assert np.array_equal(frame.weights, values[:52].astype(np.float64))
    assert np.array_equal(frame.head, values[52:].astype(np.float64))


def test_the_app_layout_counts_a_non_ascii_subject_in_bytes():
    frame = parse_livelink_packet(livelink_packet(_values(4), subject="Jürgen".encode()))
    assert (frame.layout, frame.subject) == ("livelinkface", "Jürgen")


@settings(max_examples=50, deadline=None)
@given(
    st.text(st.characters(codec="utf-8"), max_size=60),
    st.text(st.characters(codec="utf-8"), max_size=60),
    st.booleans(),
)
def test_pylivelinkface_packets_round_trip_any_id_and_name(device, subject, with_face):
    values = _values(5) if with_face else []
    data = pylivelinkface_packet(values, device=("$" + device).encode(), subject=subject)
    frame = parse_livelink_packet(data)
    assert frame.subject == subject and frame.has_face == with_face
    if frame.layout == "pylivelinkface":
        assert frame.device_id == "$" + device
    else:  # the bytes happen to be an app packet too (a 36-byte id): then exactly one
        app = livelink_packet(
            values, device=frame.device_id.encode(), subject=frame.subject.encode(),
            frame=7, sub_frame=0.5,
        )  # fmt: skip
        assert data == (app if with_face else app[: len(data)])
    if with_face:
        assert np.array_equal(frame.weights, np.asarray(values[:52], dtype=np.float64))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_parser_raises_only_its_own_error_on_pylivelinkface_starts(data):
    try:
        parse_livelink_packet(b"\x06\x00\x00\x00$" + data)
    except LiveLinkPacketError as exc:
        assert exc.code


def test_a_packet_neither_layout_fits_names_both_reasons():
    data = pylivelinkface_packet(_values(0))[:-3]  # three bytes short of the last value
    with pytest.raises(LiveLinkPacketError) as info:
        parse_livelink_packet(data)
    message = str(info.value)
    assert "Live Link Face app's layout" in message and "PyLiveLinkFace" in message


def test_a_pylivelinkface_packet_with_nan_is_refused_for_the_nan():
    values = _values(0)
    values[60] = np.nan
    with pytest.raises(LiveLinkPacketError) as info:
        parse_livelink_packet(pylivelinkface_packet(values))
    assert info.value.code == "non_finite"


def test_a_device_id_that_is_not_utf8_says_where():
    with pytest.raises(LiveLinkPacketError, match="byte 1 of 2") as info:
        parse_livelink_packet(livelink_packet(_values(0), device=b"a\xff"))
    assert info.value.code == "bad_string"


# -- the UDP receiver -----------------------------------------------------------------


@pytest.fixture
def udp_sender():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield sock
    sock.close()


@pytest.mark.anyio
async def test_udp_frames_equal_the_weights_sent_and_give_the_source_rig_points(
    udp_sender, source_rig
):
    receiver = await open_livelink_receiver("127.0.0.1", 0)
    try:
        for seed in range(3):
            values = _values(seed)
            udp_sender.sendto(livelink_packet(values, frame=seed), receiver.address)
            frame = await receiver.get(timeout=5)
            assert frame.frame_number == seed
            assert np.array_equal(frame.weights, values[:52].astype(np.float64))
            assert np.array_equal(
                source_rig.points(frame.weights), source_rig.points(values[:52].astype(np.float64))
            )
    finally:
        receiver.close()


@pytest.mark.anyio
async def test_receiver_counts_bad_packets_and_keeps_receiving(udp_sender):
    receiver = await open_livelink_receiver("127.0.0.1", 0)
    try:
        udp_sender.sendto(b"\x06\x00", receiver.address)
        udp_sender.sendto(livelink_packet(_values(1), frame=7), receiver.address)
        frame = await receiver.get(timeout=5)
        assert frame.frame_number == 7
        assert receiver.malformed == 1 and receiver.last_error.code == "truncated"
    finally:
        receiver.close()


@pytest.mark.anyio
async def test_receiver_keeps_only_the_newest_frames_when_the_consumer_lags(udp_sender):
    receiver = await open_livelink_receiver("127.0.0.1", 0, max_queue=2)
    try:
        for i in range(5):
            udp_sender.sendto(livelink_packet(_values(i), frame=i), receiver.address)
        # Wait until all five arrived (the counter moves when each is queued).
        async with asyncio.timeout(5):
            while receiver.received < 5:
                await asyncio.sleep(0)
        frames = [await receiver.get(timeout=5) for _ in range(2)]
        assert [f.frame_number for f in frames] == [3, 4]
        assert receiver.dropped == 3
    finally:
        receiver.close()


# -- bridged to a real server -----------------------------------------------------------


@pytest.fixture
def server_settings(tmp_path, cloning_rig):
    cloning_rig.save(tmp_path / f"{RIG_ID}.rig")
    return Settings(rigs_dir=tmp_path)


async def _bridge_and_compare(receiver, publisher, results, arrived, udp_sender, source_rig, rig):
    bridge = asyncio.create_task(run_livelink_bridge(receiver, source_rig, publisher))
    try:
        for seed in range(4):
            values = _values(seed)
            udp_sender.sendto(livelink_packet(values, frame=seed), receiver.address)
            async with asyncio.timeout(10):
                while len(results) <= seed:
                    arrived.clear()
                    await arrived.wait()
            points = source_rig.points(values[:52].astype(np.float64)).astype(np.float32)
            expected = rig.weights(points.astype(np.float64))
            assert np.allclose(results[seed], expected, atol=1e-5)
    finally:
        bridge.cancel()


@pytest.mark.anyio
async def test_bridged_stream_output_equals_offline_cloning(
    server_settings, udp_sender, source_rig, cloning_rig, ws_impl
):
    results: list[np.ndarray] = []
    arrived = asyncio.Event()

    def on_result(result: Result) -> None:
        results.append(np.asarray(result.weights, dtype=np.float64))
        arrived.set()

    async with run_server(server_settings, ws=ws_impl) as server:
        receiver = await open_livelink_receiver("127.0.0.1", 0)
        # The publish endpoint speaks /v1/stream's protocol, so the stream stands in for it.
        publisher = FramePublisher(
            stream_url(server.base_url), Hello(rig=RIG_ID), on_result=on_result
        )
        try:
            async with publisher:
                await _bridge_and_compare(
                    receiver, publisher, results, arrived, udp_sender, source_rig, cloning_rig
                )
                assert publisher.stats.sent == 4 and publisher.stats.dropped == 0
        finally:
            receiver.close()


@pytest.mark.anyio
async def test_publisher_reports_an_unknown_rig(server_settings, ws_impl):
    from facecast.protocol import ErrorCode, ProtocolError

    async with run_server(server_settings, ws=ws_impl) as server:
        publisher = FramePublisher(stream_url(server.base_url), Hello(rig="nope"))
        with pytest.raises(ProtocolError) as info:
            await publisher.start()
    assert info.value.code == ErrorCode.UNKNOWN_RIG


@pytest.mark.anyio
async def test_bridged_channel_output_equals_offline_cloning(
    server_settings, udp_sender, source_rig, cloning_rig, ws_impl
):
    results: list[np.ndarray] = []
    arrived = asyncio.Event()
    async with run_server(server_settings, ws=ws_impl) as server:
        watch_url = channel_url(server.base_url, "stage", "watch", {"rig": RIG_ID})
        messages = watch_channel(watch_url, reconnect=Reconnect(attempts=0))
        first = await anext(messages)
        assert isinstance(first, Ready)
        publisher = FramePublisher(
            channel_url(server.base_url, "stage", "publish"), Hello(rig=RIG_ID)
        )

        async def collect() -> None:
            async for message in messages:
                if isinstance(message, Result):
                    results.append(np.asarray(message.weights, dtype=np.float64))
                    arrived.set()
                elif isinstance(message, ChannelLive):
                    arrived.set()

        collector = asyncio.create_task(collect())
        receiver = await open_livelink_receiver("127.0.0.1", 0)
        try:
            async with publisher:
                await _bridge_and_compare(
                    receiver, publisher, results, arrived, udp_sender, source_rig, cloning_rig
                )
        finally:
            receiver.close()
            collector.cancel()
            # The generator is closed only once the task iterating it has finished.
            with contextlib.suppress(asyncio.CancelledError):
                await collector
            await messages.aclose()


@pytest.mark.anyio
async def test_bridge_livelink_command_sends_the_head_pose_as_vmc(
    server_settings, udp_sender, example_set, tmp_path, capsys, ws_impl
):
    example_set.save_npz(tmp_path / "source.npz")
    avatar = OscReceiver()
    try:
        async with run_server(server_settings, ws=ws_impl) as server:
            # The bridge binds the port the test then sends to, so it has to be chosen
            # first: a free port from the OS, released just before the bridge binds it.
            probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
            probe.close()
            argv = [
                "bridge", "livelink", server.base_url, "--channel", "stage", "--rig", RIG_ID,
                "--source-rig", str(tmp_path / "source.npz"), "--listen", f"127.0.0.1:{port}",
                "--vmc-head", f"127.0.0.1:{avatar.address[1]}", "--frames", "2",
                "--vmc-head-position", "0,0.06,0.01",
            ]  # fmt: skip
            command = asyncio.create_task(asyncio.to_thread(run_command, "bridge", argv))
            values = _values(9)
            values[52:55] = (0.3, -0.2, 0.1)
            heads = []
            async with asyncio.timeout(30):
                while not command.done():
                    # Until the bridge listens, packets go nowhere; each one it gets
                    # comes back as a head message, which is what this waits on.
                    udp_sender.sendto(livelink_packet(values), ("127.0.0.1", port))
                    try:
                        heads.append(await asyncio.to_thread(avatar.get, 0.2))
                    except queue.Empty:
                        continue
            assert await command == 0
    finally:
        avatar.close()
    angles = values[52:55].astype(np.float64)
    expected = list(head_bone_message(angles, (0.0, 0.06, 0.01)).params)
    assert len(heads) >= 2
    for address, params in heads[:2]:
        assert address == "/VMC/Ext/Bone/Pos" and params[0] == "Head"
        assert np.allclose(params[1:], expected[1:], atol=1e-6)
    assert "VMC head 2 sent, 0 failed" in capsys.readouterr().err

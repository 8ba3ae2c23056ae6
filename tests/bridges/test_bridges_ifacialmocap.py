"""iFacialMocap / Facemotion3D: UDP text -> frames, a stand-in phone on 127.0.0.1 -> a server."""

from __future__ import annotations

import asyncio
import socket
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.cli.bridges.ifacialmocap import (
    APPS,
    MAX_PACKET_BYTES,
    FacialMocapPacketError,
    open_ifacialmocap_receiver,
    parse_ifacialmocap_packet,
    request_stream,
)
from facecast.cli.bridges.tracker import run_tracker_bridge
from facecast.cli.bridges.vmc import head_bone_message
from facecast.client.channel import FramePublisher
from facecast.client.urls import stream_url
from facecast.protocol import Hello, Result
from facecast.rig.sources.source_rig import ARKIT_NAMES
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import OscReceiver, run_command

RIG_ID = "arkit"


def _ifm_name(arkit: str) -> str:
    """iFacialMocap's spelling, from its page: ARKit names with _L / _R for Left / Right."""
    for side, suffix in (("Left", "_L"), ("Right", "_R")):
        if arkit.endswith(side):
            return arkit[: -len(side)] + suffix
    return arkit


def ifacialmocap_text(values, head=(0.0, 0.0, 0.0), separator: str = "-") -> bytes:
    """A frame as the apps' pages describe it: name-value fields, then head and eyes."""
    names = ARKIT_NAMES if separator == "&" else [_ifm_name(n) for n in ARKIT_NAMES]
    fields = [f"{name}{separator}{int(v)}" for name, v in zip(names, values, strict=True)]
    x, y, z = head
    fields.append(f"=head#{x},{y},{z},-0.03,-0.1,-0.66")
    fields += ["rightEye#6.0,2.4,0.25", "leftEye#6.0,-1.7,-0.2", ""]
    return "|".join(fields).encode()


def _percent(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 101, size=52)


# -- the parser -------------------------------------------------------------------------


def test_golden_ifacialmocap_text_decodes_field_by_field():
    data = (
        b"mouthSmile_R-40|eyeBlink_L-7|jawOpen-100|browInnerUp-0|"
        b"=head#-21.5,10.0,-6.5,-0.03,-0.1,-0.66|rightEye#6.0,2.4,0.25|leftEye#6.0,-1.7,-0.2|"
    )
    frame = parse_ifacialmocap_packet(data)
    w = dict(zip(ARKIT_NAMES, frame.weights.tolist(), strict=True))
    assert (w["mouthSmileRight"], w["eyeBlinkLeft"], w["jawOpen"]) == (0.40, 0.07, 1.0)
    assert sum(frame.weights) == pytest.approx(1.47)
    assert (frame.app, frame.missing, frame.ignored) == ("ifacialmocap", 48, ())
    # degrees X (pitch), Y (yaw), Z (roll) -> radians yaw, pitch, roll
    assert np.allclose(frame.head, np.radians([10.0, -21.5, -6.5]))
    assert np.allclose(frame.head_position, [-0.03, -0.1, -0.66])
    assert np.allclose(frame.right_eye, np.radians([6.0, 2.4, 0.25]))


def test_golden_facemotion3d_text_uses_arkit_names_and_skips_its_extras():
    data = b"eyeBlinkLeft&29|mouthSmileRight&3|FM_SAD&0|FM_browUpLeft&5|=head#1.0,2.0,3.0,0,0,0|"
    frame = parse_ifacialmocap_packet(data)
    w = dict(zip(ARKIT_NAMES, frame.weights.tolist(), strict=True))
    assert (w["eyeBlinkLeft"], w["mouthSmileRight"]) == (0.29, 0.03)
    assert frame.app == "facemotion3d" and frame.ignored == ("FM_SAD", "FM_browUpLeft")
    assert frame.right_eye is None and frame.left_eye is None


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.integers(0, 100), min_size=52, max_size=52),
    st.sampled_from(["-", "&"]),
    st.tuples(*[st.floats(-90, 90, allow_nan=False)] * 3),
)
def test_every_shape_round_trips_in_both_spellings(percent, separator, head):
    frame = parse_ifacialmocap_packet(ifacialmocap_text(percent, head, separator))
    assert np.array_equal(frame.weights, np.asarray(percent) / 100.0)
    assert frame.missing == 0
    assert np.allclose(frame.head, np.radians([head[1], head[0], head[2]]))


@pytest.mark.parametrize(
    ("data", "code"),
    [
        (b"x" * (MAX_PACKET_BYTES + 1), "too_large"),
        (b"jawOpen-1\xff|", "bad_text"),
        (b"", "bad_field"),
        (b"=head#0,0,0,0,0,0|", "bad_field"),
        (b"jawOpen|", "bad_field"),
        (b"jawOpen-101|", "bad_value"),
        (b"jawOpen-0.5|", "bad_value"),
        (b"jawOpen-1e2|", "bad_value"),
        (b"jawOpen-|", "bad_value"),
        (b"jawOpen-1|jawopen-2|", "duplicate_name"),
        (b"eyeBlink_L-1|eyeBlinkLeft-2|", "duplicate_name"),
        (b"jawOpen-1|=head#0,0,0|", "bad_pose"),
        (b"jawOpen-1|=head#a,0,0,0,0,0|", "bad_pose"),
        (b"jawOpen-1|=head#nan,0,0,0,0,0|", "non_finite"),
        (b"jawOpen-1|=tail#0,0,0|", "bad_field"),
    ],
)
def test_bad_packets_raise_a_coded_value_error(data, code):
    with pytest.raises(ValueError) as info:
        parse_ifacialmocap_packet(data)
    assert isinstance(info.value, FacialMocapPacketError) and info.value.code == code


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=600), st.text(max_size=300).map(str.encode)))
def test_parser_raises_only_its_own_error_on_arbitrary_bytes(data):
    try:
        frame = parse_ifacialmocap_packet(data)
    except FacialMocapPacketError as exc:
        assert exc.code
    else:
        assert np.isfinite(frame.weights).all() and (frame.weights >= 0).all()


# -- UDP, a stand-in phone, and a real server ---------------------------------------------


class FakePhone:
    """A UDP socket on 127.0.0.1 that answers the app's start request with frames.

    Like the app: it streams only once asked, to the address the request came from.
    """

    def __init__(self, frames: list[bytes], request: bytes) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.address = self.sock.getsockname()
        self.frames, self.request = frames, request
        self.requests = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, sender = self.sock.recvfrom(4096)
            except TimeoutError:
                continue
            if data == self.request:
                self.requests += 1
                for frame in self.frames:
                    self.sock.sendto(frame, sender)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.sock.close()


@pytest.mark.anyio
async def test_request_stream_sends_the_apps_request_from_the_receivers_port():
    receiver = await open_ifacialmocap_receiver("127.0.0.1", 0)
    phone = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    phone.bind(("127.0.0.1", 0))
    phone.settimeout(10)
    try:
        request_stream(receiver, *phone.getsockname()[:1], "facemotion3d", phone.getsockname()[1])
        data, sender = await asyncio.to_thread(phone.recvfrom, 4096)
    finally:
        phone.close()
        receiver.close()
    assert data == APPS["facemotion3d"][1] == b"FACEMOTION3D_OtherStreaming"
    assert sender[1] == receiver.address[1]


@pytest.fixture
def server_settings(tmp_path, cloning_rig):
    cloning_rig.save(tmp_path / f"{RIG_ID}.rig")
    return Settings(rigs_dir=tmp_path)


@pytest.mark.anyio
async def test_bridged_output_equals_offline_cloning_of_the_percent_weights(
    server_settings, source_rig, cloning_rig, ws_impl
):
    results: list[np.ndarray] = []
    arrived = asyncio.Event()

    def on_result(result: Result) -> None:
        results.append(np.asarray(result.weights, dtype=np.float64))
        arrived.set()

    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    async with run_server(server_settings, ws=ws_impl) as server:
        receiver = await open_ifacialmocap_receiver("127.0.0.1", 0)
        publisher = FramePublisher(
            stream_url(server.base_url), Hello(rig=RIG_ID), on_result=on_result
        )
        try:
            async with publisher:
                bridge = asyncio.create_task(run_tracker_bridge(receiver, source_rig, publisher))
                try:
                    for seed in range(3):
                        sender.sendto(ifacialmocap_text(_percent(seed)), receiver.address)
                        async with asyncio.timeout(10):
                            while len(results) <= seed:
                                arrived.clear()
                                await arrived.wait()
                        weights = _percent(seed) / 100.0
                        points = source_rig.points(weights).astype(np.float32)
                        expected = cloning_rig.weights(points.astype(np.float64))
                        assert np.allclose(results[seed], expected, atol=1e-5)
                finally:
                    bridge.cancel()
        finally:
            receiver.close()
            sender.close()


@pytest.mark.anyio
async def test_bridge_command_asks_the_phone_then_publishes_and_sends_the_head_as_vmc(
    server_settings, example_set, tmp_path, capsys, ws_impl
):
    example_set.save_npz(tmp_path / "source.npz")
    head_degrees = (-10.0, 20.0, 5.0)  # X pitch, Y yaw, Z roll
    frames = [ifacialmocap_text(_percent(s), head_degrees) for s in range(5)]
    phone = FakePhone(frames, APPS["ifacialmocap"][1])
    avatar = OscReceiver()
    try:
        async with run_server(server_settings, ws=ws_impl) as server:
            argv = [
                "bridge", "ifacialmocap", server.base_url, "--channel", "stage", "--rig", RIG_ID,
                "--source-rig", str(tmp_path / "source.npz"), "--listen", "127.0.0.1:0",
                "--phone", f"127.0.0.1:{phone.address[1]}",
                "--vmc-head", f"127.0.0.1:{avatar.address[1]}", "--frames", "3",
            ]  # fmt: skip
            code = await asyncio.wait_for(asyncio.to_thread(run_command, "bridge", argv), 60)
        heads = [avatar.get() for _ in range(3)]
    finally:
        phone.close()
        avatar.close()
    assert code == 0 and phone.requests >= 1
    expected = list(head_bone_message(np.radians([20.0, -10.0, 5.0])).params)
    for address, params in heads:
        assert address == "/VMC/Ext/Bone/Pos"
        assert params[0] == "Head"
        assert np.allclose(params[1:], expected[1:], atol=1e-6)
    err = capsys.readouterr().err
    assert "iFacialMocap on udp://127.0.0.1:" in err
    assert "3 frames published" in err and "VMC head 3 sent, 0 failed" in err

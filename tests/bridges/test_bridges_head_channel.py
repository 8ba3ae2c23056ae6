"""Head pose through a channel: tracker bridges in, ``bridge vmc`` out, the Head bone there.

The performer's ``facecast bridge livelink`` (its own process) gets a real Live Link UDP
packet and publishes to a channel on a real server; a viewer's ``facecast bridge vmc``
watches it and sends VMC to python-osc's UDP server, standing in for VSeeFace. The Head
bone there must be the packet's head rotation, in Unity's frame (PROTOCOL.md §5.3).
"""

from __future__ import annotations

import asyncio
import socket
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facecast.cli.bridges.ifacialmocap import open_ifacialmocap_receiver
from facecast.cli.bridges.tracker import run_tracker_bridge
from facecast.cli.bridges.vmc import VmcSender, run_vmc_bridge
from facecast.client.channel import FramePublisher, channel_url
from facecast.protocol import Head, Hello, Ready, Result
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import OscReceiver, livelink_packet, run_command

RIG_ID = "arkit"
YAW, PITCH, ROLL = 0.3, -0.2, 0.1


@pytest.fixture
def osc_receivers():
    receivers = (OscReceiver(), OscReceiver())
    yield receivers
    for receiver in receivers:
        receiver.close()


@pytest.fixture
def server_settings(tmp_path, cloning_rig) -> Settings:
    cloning_rig.save(tmp_path / f"{RIG_ID}.rig")
    return Settings(rigs_dir=tmp_path)


@pytest.fixture
def source_path(tmp_path, example_set) -> Path:
    path = tmp_path / "source.npz"
    example_set.save_npz(path)
    return path


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _unity_quaternion(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """What VSeeFace should get, written in Unity's own terms, not through the bridge code.

    Unity's ``Quaternion.Euler(x, y, z)`` turns about z, then x, then y (intrinsic Y-X-Z).
    Left-handed with +x the performer's right, a turn to the performer's left (Live
    Link's positive yaw) is a negative y; a tilt (roll) changes sign too; a nod does not.
    """
    return Rotation.from_euler("YXZ", [-yaw, pitch, -roll]).as_quat()


def _same_rotation(q: np.ndarray, expected: np.ndarray, atol: float) -> bool:
    return bool(np.allclose(q, expected, atol=atol) or np.allclose(q, -expected, atol=atol))


async def _viewers(base_url: str, timeout: float = 30.0) -> None:
    """Until the channel lists a viewer (the HTTP figure is the only signal there is)."""
    async with httpx.AsyncClient(base_url=base_url) as http, asyncio.timeout(timeout):
        while True:
            response = await http.get("/v1/channels/stage")
            if response.status_code == 200 and response.json()["viewers"] >= 1:
                return
            await asyncio.sleep(0.05)


async def _livelink_process(base_url: str, source: Path, port: int, *options: str):
    """``facecast bridge livelink ... --frames 1`` as its own process, once it listens."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "facecast.cli", "bridge", "livelink", base_url,
        "--channel", "stage", "--rig", RIG_ID, "--source-rig", str(source),
        "--listen", f"127.0.0.1:{port}", "--frames", "1", *options,
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert process.stderr is not None
    async with asyncio.timeout(60):
        lines = []
        while b"Live Link on udp://" not in (line := await process.stderr.readline()):
            lines.append(line)
            if not line:
                raise AssertionError(b"".join(lines).decode(errors="replace"))
    return process


def _head_bone(messages: list[tuple[str, list]]) -> tuple[list[float], np.ndarray]:
    bones = [params for address, params in messages if address == "/VMC/Ext/Bone/Pos"]
    assert len(bones) == 1 and bones[0][0] == "Head", messages
    return bones[0][1:4], np.array(bones[0][4:], dtype=np.float64)


@pytest.mark.anyio
@pytest.mark.parametrize("head_pose", [False, True], ids=["still-points", "head-pose"])
async def test_a_livelink_head_reaches_the_viewers_avatar_app_as_the_head_bone(
    server_settings, source_path, osc_receivers, head_pose, ws_impl
):
    viewer_app, performer_app = osc_receivers
    values = np.zeros(61, dtype=np.float32)
    values[0] = 0.5  # eyeBlinkLeft: a face
    values[52:55] = (YAW, PITCH, ROLL)  # Live Link's head yaw, pitch, roll (radians)
    host, port = viewer_app.address
    vmc_argv = ["bridge", "vmc", "", "--channel", "stage", "--rig", RIG_ID,
                "--send", f"{host}:{port}", "--frames", "1"]  # fmt: skip
    direct = "{}:{}".format(*performer_app.address)

    async with run_server(server_settings, ws=ws_impl) as server:
        vmc_argv[2] = server.base_url
        viewer = asyncio.create_task(asyncio.to_thread(run_command, "bridge", vmc_argv))
        await _viewers(server.base_url)
        udp_port = _free_udp_port()
        performer = await _livelink_process(
            server.base_url, source_path, udp_port, "--vmc-head", direct,
            *(["--head-pose"] if head_pose else []),
        )  # fmt: skip
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as phone:
                phone.sendto(livelink_packet(values), ("127.0.0.1", udp_port))
                async with asyncio.timeout(60):
                    assert await performer.wait() == 0
                    assert await viewer == 0
        finally:
            if performer.returncode is None:
                performer.kill()
                await performer.wait()

    # The viewer's frame: OK and T (channel_live's status first), then the frame's bundle.
    position, q = _head_bone(viewer_app.until_apply())
    assert position == [0.0, 0.0, 0.0]
    assert _same_rotation(q, _unity_quaternion(YAW, PITCH, ROLL), atol=1e-6)
    # ...the very bone the performer's own --vmc-head sends its local avatar app.
    direct_position, direct_q = _head_bone([performer_app.get()])
    assert direct_position == position
    assert _same_rotation(q, direct_q, atol=1e-7)


def test_the_unity_expectation_agrees_with_one_axis_turns():
    # The reference of the test above, checked against the half-angle formulas.
    for angles, expected in [
        ((0.3, 0.0, 0.0), (0.0, -np.sin(0.15), 0.0, np.cos(0.15))),
        ((0.0, 0.2, 0.0), (np.sin(0.1), 0.0, 0.0, np.cos(0.1))),
        ((0.0, 0.0, 0.1), (0.0, 0.0, -np.sin(0.05), np.cos(0.05))),
    ]:
        assert _same_rotation(_unity_quaternion(*angles), np.array(expected), atol=1e-12)


@pytest.mark.anyio
async def test_an_ifacialmocap_head_goes_out_in_the_channel_frames(
    server_settings, source_rig, ws_impl
):
    # The app's X, Y, Z degrees are pitch, yaw, roll (ifacialmocap.py's docstring).
    text = b"eyeBlink_L-50|jawOpen-20|=head#-10.0,20.0,5.0,-0.03,-0.1,-0.66|"
    results: list[Result] = []
    arrived = asyncio.Event()

    def on_result(result: Result) -> None:
        results.append(result)
        arrived.set()

    async with run_server(server_settings, ws=ws_impl) as server:
        receiver = await open_ifacialmocap_receiver("127.0.0.1", 0)
        publisher = FramePublisher(
            channel_url(server.base_url, "stage", "publish"), Hello(rig=RIG_ID),
            on_result=on_result,
        )  # fmt: skip
        try:
            async with publisher, asyncio.timeout(30):
                bridge = asyncio.create_task(
                    run_tracker_bridge(receiver, source_rig, publisher, max_frames=1)
                )
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as phone:
                    phone.sendto(text, receiver.address)
                    await bridge
                    await arrived.wait()
        finally:
            receiver.close()

    head = results[0].head
    assert head is not None and head.position is None
    expected = _unity_quaternion(*np.radians([20.0, -10.0, 5.0]))
    assert _same_rotation(np.asarray(head.rotation, dtype=np.float64), expected, atol=1e-6)


def _frame(seq: int, head: Head | None) -> Result:
    weights = np.array([0.2, 0.5, 0.3, 0.0, 0.0, 0.0], dtype=np.float32)
    return Result(seq=seq, ts=float(seq), weights=weights, head=head)


@pytest.mark.anyio
async def test_bridge_vmc_sends_a_results_head_and_no_bone_without_one(osc_receivers):
    receiver, _ = osc_receivers
    ready = Ready(session="s", rig=RIG_ID, names=("neutral", "a", "b", "c", "d", "e"),
                  num_points=6, num_vertices=12, output="weights", dtype="f32")  # fmt: skip
    rotation = np.array([0.0, -0.6, 0.0, 0.8], dtype=np.float16)
    position = np.array([0.0, 0.0625, 0.0], dtype=np.float32)

    async def messages():
        yield ready
        yield _frame(0, Head(rotation=rotation, position=position))
        yield _frame(1, None)

    with VmcSender(*receiver.address) as sender:
        stats = await run_vmc_bridge(messages(), sender, clock=lambda: 1.0)
    first, second = receiver.until_apply(), receiver.until_apply()
    assert stats.frames == 2
    bone_position, q = _head_bone(first)
    assert bone_position == [0.0, 0.0625, 0.0]
    assert np.array_equal(q, rotation.astype(np.float64))  # f16 values are float32-exact
    assert [a for a, _ in first][:3] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Bone/Pos"]
    assert all(address != "/VMC/Ext/Bone/Pos" for address, _ in second)

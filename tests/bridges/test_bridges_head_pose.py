"""Head-pose removal on the rig ``facecast import ict-facekit`` makes, offline and bridged.

The imported set names stable points (no jaw, no lips), ``facecast fit`` says which it
aligns on, and a frame of any example under a rigid motion comes back, with ``align``, as
the unmoved frame's weights; the same through ``facecast bridge livelink --head-pose``.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import sys
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facecast.client.channel import channel_url, watch_channel
from facecast.client.connection import Reconnect
from facecast.protocol import Result
from facecast.rig import fit, load_rig
from facecast.rig.characters.loaders import load_example_set
from facecast.rig.sources.ict import DEFAULT_LANDMARKS, DEFAULT_STABLE_LANDMARKS, locate_ict
from facecast.rig.sources.source_rig import ARKIT_NAMES, load_source_rig
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import livelink_packet, run_command

ARCHIVE = locate_ict()
pytestmark = [
    pytest.mark.ict,
    pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found ($FACECAST_ICT)"),
]

#: The issue's head pose: yaw 0.3, pitch -0.2, roll 0.1 rad, with a shift of a few cm.
YAW_PITCH_ROLL = (0.3, -0.2, 0.1)
SHIFT = np.array([1.5, -2.0, 4.0])
JAW_OPEN = 0.8


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ict") / "arkit"
    assert run_command("import_", ["import", "ict-facekit", str(ARCHIVE), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def examples(imported):
    """The imported folder, loaded once (it holds ICT's 52 target meshes)."""
    return load_example_set(imported)


@pytest.fixture(scope="module")
def fitted(imported, tmp_path_factory):
    """``facecast fit`` of the imported folder: (rig, the report it printed)."""
    path = tmp_path_factory.mktemp("rig") / "ict.rig"
    with contextlib.redirect_stdout(_Capture()) as printed, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert run_command("fit", ["fit", str(imported), "-o", str(path)]) == 0
    return load_rig(path), printed.text


@pytest.fixture(scope="module")
def noise_rig(examples):
    """The rig ``fit`` recommends for tracked input (0.1 mm landmark noise, bounded)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(examples, noise=0.01, clamp="nonneg")


class _Capture:
    def __init__(self) -> None:
        self.text = ""

    def write(self, text: str) -> int:
        self.text += text
        return len(text)

    def flush(self) -> None:
        pass


def _moved(points: np.ndarray) -> np.ndarray:
    rotation = Rotation.from_euler("yxz", YAW_PITCH_ROLL).as_matrix()
    return points @ rotation.T + SHIFT


def test_import_names_stable_points_off_the_jaw_and_lips(imported, examples):
    with (imported / "facecast.toml").open("rb") as handle:
        stable = tomllib.load(handle)["source"]["stable_points"]
    landmarks = [DEFAULT_LANDMARKS[i] for i in stable]
    assert landmarks == list(DEFAULT_STABLE_LANDMARKS)
    jaw_and_lips = set(range(0, 17)) | set(range(48, 68))
    assert not jaw_and_lips & set(landmarks)
    assert examples.stable_points.tolist() == stable


def test_import_without_the_stable_landmarks_says_so(tmp_path, capsys):
    out = tmp_path / "lips"
    landmarks = "48,51,54,57,62,66,8,31,35"
    assert (
        run_command(
            "import_",
            ["import", "ict-facekit", str(ARCHIVE), "-o", str(out), "--landmarks", landmarks],
        )
        == 0
    )
    assert "no stable points" in capsys.readouterr().err
    assert load_example_set(out).stable_points is None


def test_fit_says_which_points_it_aligns_on(fitted, examples):
    rig, printed = fitted
    stable = examples.stable_points
    assert rig.stable_points.tolist() == stable.tolist()
    assert f"on stable points {', '.join(map(str, stable.tolist()))}" in printed
    assert "refined against the examples' span" in printed


def test_each_example_under_rigid_motion_gives_the_unmoved_weights(fitted, examples):
    rig, _ = fitted
    points = examples.source_points
    unmoved = rig.weights(points)
    np.testing.assert_allclose(unmoved, np.eye(rig.num_examples), atol=1e-8)
    # Without alignment the motion ruins them; with it they come back.
    assert np.abs(rig.weights(_moved(points)) - unmoved).max() > 1.0
    np.testing.assert_allclose(rig.weights(_moved(points), align=True), unmoved, atol=1e-3)


def test_unmoved_examples_keep_their_weights_under_alignment(fitted, examples):
    # The offline case: align=True with no rotation at all gave jawOpen -20.8.
    rig, _ = fitted
    points = examples.source_points
    np.testing.assert_allclose(rig.weights(points, align=True), rig.weights(points), atol=1e-3)


def test_bounded_noise_rig_gives_the_unmoved_weights_too(noise_rig, examples):
    points = examples.source_points
    np.testing.assert_allclose(
        noise_rig.weights(_moved(points), align=True), noise_rig.weights(points), atol=1e-3
    )


def test_expression_mixes_under_rigid_motion_give_the_unmoved_weights(fitted, imported):
    rig, _ = fitted
    source_rig = load_source_rig(imported)
    arkit = np.random.default_rng(5).uniform(0, 1, size=(20, 52)) * (
        np.random.default_rng(6).uniform(size=(20, 52)) < 0.1
    )
    points = source_rig.points(arkit)
    np.testing.assert_allclose(
        rig.weights(_moved(points), align=True), rig.weights(points), atol=1e-3
    )


# -- facecast bridge livelink --head-pose, end to end -----------------------------------


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


async def _bridge_process(base_url: str, imported: Path, port: int):
    """``facecast bridge livelink --head-pose`` as its own process, once it listens."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "facecast.cli", "bridge", "livelink", base_url,
        "--channel", "stage", "--rig", "ict", "--source-rig", str(imported),
        "--listen", f"127.0.0.1:{port}", "--head-pose", "--frames", "1",
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


async def _first_result(messages) -> Result:
    async for message in messages:
        if isinstance(message, Result):
            return message
    raise AssertionError("the channel closed before a result")


@pytest.mark.anyio
async def test_livelink_head_pose_reaches_the_viewer_as_the_unmoved_weights(
    fitted, noise_rig, imported, tmp_path, ws_impl
):
    rig, _ = fitted
    rig.save(tmp_path / "ict.rig")
    noise_rig.save(tmp_path / "ict-noise.rig")
    values = np.zeros(61, dtype=np.float32)
    values[ARKIT_NAMES.index("jawOpen")] = JAW_OPEN
    values[52:55] = YAW_PITCH_ROLL  # Live Link's head yaw, pitch, roll (radians)
    source_rig = load_source_rig(imported)
    still = source_rig.points(values[:52].astype(np.float64))
    # What the bridge sends: the packet's float32 values turned into float32 points.
    sent = source_rig.points(values[:52].astype(np.float64), head=values[52:55].astype(np.float64))

    async with run_server(Settings(rigs_dir=tmp_path), ws=ws_impl) as server:
        watchers = {
            name: watch_channel(
                channel_url(server.base_url, "stage", "watch", {"rig": name}),
                reconnect=Reconnect(attempts=0),
            )
            for name in ("ict", "ict-noise")
        }
        results = {name: asyncio.create_task(_first_result(m)) for name, m in watchers.items()}
        port = _free_udp_port()
        process = await _bridge_process(server.base_url, imported, port)
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
                sender.sendto(livelink_packet(values), ("127.0.0.1", port))
                async with asyncio.timeout(60):
                    received = {name: await task for name, task in results.items()}
                    assert await process.wait() == 0
        finally:
            if process.returncode is None:
                process.kill()
                await process.wait()
            for task in results.values():
                task.cancel()
            # A cancelled reader must have left its generator before the generator closes
            # (else aclose() fails "already running" and hides what went wrong).
            await asyncio.gather(*results.values(), return_exceptions=True)
            for messages in watchers.values():
                await messages.aclose()

    jaw = rig.names.index("jawOpen")
    exact = np.asarray(received["ict"].weights, dtype=np.float64)
    # The server's weights are the offline ones of the float32 points it was sent...
    np.testing.assert_allclose(exact, rig.weights(sent.astype(np.float32), align=True), atol=1e-5)
    # ...which float32 rounding moves a little through the exact rig's noise gain, and
    # the bounded rig for tracked input not at all.
    np.testing.assert_allclose(exact, rig.weights(still), atol=1e-2)
    bounded = np.asarray(received["ict-noise"].weights, dtype=np.float64)
    np.testing.assert_allclose(bounded, noise_rig.weights(still), atol=1e-3)
    # The head pose is gone (above, to 1e-3); what is left of the packet's jawOpen is the
    # noise rig's own bias on this pose (0.803 with the default plain projection).
    assert abs(bounded[jaw] - JAW_OPEN) < 1e-2

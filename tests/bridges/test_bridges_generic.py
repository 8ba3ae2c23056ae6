"""``bridge livelink`` with no ``--source-rig``: facecast's generic ARKit set turns the
phone's weights into the points every character uploaded as a file is paired with."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import socket

import numpy as np
import pytest

from facecast.client.channel import channel_url, watch_channel
from facecast.client.connection import Reconnect
from facecast.protocol import Ready, Result
from facecast.rig import fit
from facecast.rig.characters.character import character_example_set, load_character
from facecast.rig.characters.character_examples import character_fit_options
from facecast.rig.sources.source_rig import generic_source_rig
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ..viewer._character import build_character
from ._helpers import livelink_packet, run_command

RIG_ID = "face"


@pytest.fixture(scope="module", params=[None, 24])
def character_rig(request):
    """The tests' small VRM character as ``PUT /v1/characters`` fits it (generic set): on
    the set's 26 points, or on its first 24 (a character stored before the set took the
    iris centres: the bridge sends it those)."""
    character = load_character(build_character("vrm1").glb, label="face.vrm")
    example_set, _ = character_example_set(character)
    if request.param is not None:
        example_set = dataclasses.replace(
            example_set, source_points=example_set.source_points[:, : request.param]
        )
    return fit(example_set, **character_fit_options({}))


@pytest.mark.anyio
async def test_bridge_livelink_drives_a_character_with_the_generic_set_by_default(
    tmp_path, character_rig
):
    character_rig.save(tmp_path / f"{RIG_ID}.rig")
    values = np.zeros(61, dtype=np.float32)
    values[17] = 0.8  # jawOpen
    values[0] = 0.6  # eyeBlinkLeft
    points = generic_source_rig().points(values[:52])[: character_rig.num_points]
    expected = character_rig.weights(points.astype(np.float32))
    results: list[np.ndarray] = []
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    async with run_server(Settings(rigs_dir=tmp_path)) as server:
        messages = watch_channel(
            channel_url(server.base_url, "stage", "watch", {"rig": RIG_ID}),
            reconnect=Reconnect(attempts=0),
        )
        assert isinstance(await anext(messages), Ready)

        async def collect() -> None:
            async for message in messages:
                if isinstance(message, Result):
                    results.append(np.asarray(message.weights, dtype=np.float64))

        collector = asyncio.create_task(collect())
        probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        probe.close()
        argv = ["bridge", "livelink", server.base_url, "--channel", "stage", "--rig", RIG_ID,
                "--listen", f"127.0.0.1:{port}", "--frames", "3"]  # fmt: skip
        command = asyncio.create_task(asyncio.to_thread(run_command, "bridge", argv))
        try:
            async with asyncio.timeout(30):
                while not command.done() or not results:
                    # Until the bridge listens, packets go nowhere: send until it is done.
                    if not command.done():
                        sender.sendto(livelink_packet(values), ("127.0.0.1", port))
                    await asyncio.sleep(0.05)
            status = await command
        finally:
            sender.close()
            collector.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await collector
            await messages.aclose()

    assert status == 0
    np.testing.assert_allclose(results[-1], expected, atol=1e-5)
    jaw = character_rig.names.index("jawOpen")
    assert results[-1][jaw] > 0.5  # the character's mouth opens

"""``facecast publish`` accounts for every frame it sent before it reports and leaves."""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

from facecast.client.cli import CommandError
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import run_command

RIG_ID = "arkit"
FRAMES = 40

_SUMMARY = re.compile(
    r"(\d+) frames to 'stage' \(results back (\d+), dropped by the server (\d+), "
    r"refused (\d+), dropped while reconnecting (\d+)"
)


@pytest.fixture
def take(tmp_path, source_rig):
    rng = np.random.default_rng(3)
    path = tmp_path / "take.npy"
    np.save(path, source_rig.points(rng.uniform(0, 1, size=(FRAMES, 52))).astype(np.float32))
    return path


@pytest.mark.anyio
async def test_publish_summary_accounts_for_the_last_frame(tmp_path, cloning_rig, take, capsys):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    cloning_rig.save(rigs / f"{RIG_ID}.rig")
    async with run_server(Settings(rigs_dir=rigs)) as server:
        code = await asyncio.to_thread(
            run_command,
            "publish",
            ["publish", server.base_url, "stage", str(take), "--rig", RIG_ID],
        )
    assert code == 0
    match = _SUMMARY.search(capsys.readouterr().err)
    assert match is not None
    sent, results, server_dropped, refused, reconnecting = map(int, match.groups())
    assert (sent, reconnecting) == (FRAMES, 0)
    assert results >= 1
    assert results + server_dropped + refused == sent


@pytest.mark.parametrize("timeout", ["-1", "nan", "inf"])
def test_publish_refuses_an_unbounded_or_negative_drain_timeout(take, timeout):
    with pytest.raises(CommandError, match="--drain-timeout"):
        run_command(
            "publish",
            ["publish", "http://127.0.0.1:9", "stage", str(take), "--drain-timeout", timeout],
        )

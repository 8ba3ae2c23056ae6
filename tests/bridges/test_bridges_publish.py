"""``facecast publish`` accounts for every frame it sent before it reports and leaves."""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

from facecast.cli.errors import CommandError
from facecast.client.channel import FramePublisher, channel_url
from facecast.protocol import Hello
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
async def test_publish_summary_accounts_for_the_last_frame(
    tmp_path, cloning_rig, take, capsys, ws_impl
):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    cloning_rig.save(rigs / f"{RIG_ID}.rig")
    async with run_server(Settings(rigs_dir=rigs), ws=ws_impl) as server:
        code = await asyncio.to_thread(
            run_command,
            "publish",
            ["publish", server.base_url, "stage", str(take), "--rig", RIG_ID, "--realtime"],
        )
    assert code == 0
    err = capsys.readouterr().err
    match = _SUMMARY.search(err)
    assert match is not None
    sent, results, server_dropped, refused, reconnecting = map(int, match.groups())
    # Every frame sent, the last one included, is a result or a drop the server counted
    # (a loaded machine may drop a few) before the command leaves.
    assert (sent, reconnecting, refused) == (FRAMES, 0, 0)
    assert results >= 1 and results + server_dropped == FRAMES
    assert "unaccounted" not in err and "did not arrive" not in err


@pytest.mark.parametrize("timeout", ["-1", "nan", "inf"])
def test_publish_refuses_an_unbounded_or_negative_drain_timeout(take, timeout):
    with pytest.raises(CommandError, match="--drain-timeout"):
        run_command(
            "publish",
            ["publish", "http://127.0.0.1:9", "stage", str(take), "--drain-timeout", timeout],
        )


@pytest.mark.anyio
async def test_drain_counts_a_refused_last_frame_as_answered(
    tmp_path, cloning_rig, source_rig, ws_impl
):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    cloning_rig.save(rigs / f"{RIG_ID}.rig")
    good = source_rig.points(np.full(52, 0.2)).astype(np.float32)
    async with run_server(Settings(rigs_dir=rigs), ws=ws_impl) as server:
        url = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(url, Hello(rig=RIG_ID)) as publisher:
            for seq in range(3):
                await publisher.send(good, ts=float(seq))
            await publisher.send(good[:-1], ts=3.0)  # one point short: WRONG_POINT_COUNT
            # The refusal comes at once, ahead of the three results: drain waits on.
            assert await publisher.drain(10.0)
            stats, last = publisher.stats, publisher.last_result
    assert (stats.sent, stats.refused) == (4, 1)
    assert last is not None and last.seq == 2


@pytest.mark.anyio
async def test_a_burst_over_the_rate_is_counted_from_the_rate_limited_total(
    tmp_path, cloning_rig, source_rig, ws_impl
):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    cloning_rig.save(rigs / f"{RIG_ID}.rig")
    good = source_rig.points(np.full(52, 0.2)).astype(np.float32)
    # A bucket of 5: a burst of 30 leaves a tail that only RATE_LIMITED's total reports.
    settings = Settings(rigs_dir=rigs, max_fps=1.0, rate_burst=5)
    async with run_server(settings, ws=ws_impl) as server:
        url = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(url, Hello(rig=RIG_ID)) as publisher:
            for seq in range(30):
                await publisher.send(good, ts=float(seq))
            # Settled by the totals (within the server's once-a-second report), not the
            # drain's timeout.
            assert await publisher.drain(5.0)
            stats = publisher.stats
            unaccounted = publisher.unaccounted
    assert stats.sent == 30 and stats.refused == 0
    assert stats.server_dropped >= 30 - 5 - 1
    assert stats.results + stats.server_dropped == 30 and unaccounted == 0

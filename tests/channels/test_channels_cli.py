"""``facecast publish`` / ``facecast watch`` against a real server; ``serve --workers 2 --redis``."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest

from facecast.cli.bench.harness import facecast_serve
from facecast.cli.main import main
from facecast.server.testing import run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points, wait_for

pytestmark = pytest.mark.anyio


async def test_publish_and_watch_commands_round_trip_an_animation(
    settings, rigs, tmp_path, ws_impl
):
    source = np.stack([points(rigs["alpha"], seed) for seed in range(30)])
    np.save(tmp_path / "performance.npy", source)
    out = tmp_path / "seen.npz"
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        watch = asyncio.create_task(asyncio.to_thread(
            main, ["watch", server.base_url, "stage", "--rig", "beta", "-o", str(out),
                   "--frames", "10", "--timeout", "20"],
        ))  # fmt: skip

        async def watching() -> bool:
            response = await http.get("/v1/channels/stage")
            return response.status_code == 200 and response.json()["viewers"] == 1

        await wait_for(watching, what="the watch command to join")
        published = await asyncio.to_thread(
            main, ["publish", server.base_url, "stage", str(tmp_path / "performance.npy"),
                   "--rig", "alpha", "--realtime", "-q"],
        )  # fmt: skip
        watched = await watch

    assert (published, watched) == (0, 0)
    recorded = np.load(out)
    assert recorded["weights"].shape == (10, len(rigs["beta"].names))
    expected = rigs["beta"].weights(source[recorded["seq"]].astype(np.float32))
    np.testing.assert_array_equal(recorded["weights"], expected.astype(np.float32))
    assert list(recorded["names"]) == list(rigs["beta"].names)


async def test_serve_with_workers_and_redis_fans_out_across_workers(rigs_dir, rigs, redis_server):
    server = facecast_serve(
        rigs_dir, "--workers", "2", "--redis", redis_server.url,
        env={"FACECAST_LOG_LEVEL": "warning"}, name="facecast serve --workers 2",
    ).start()  # fmt: skip
    try:
        await asyncio.to_thread(server.wait_ready, timeout=30)
        ws = server.ws_url
        watchers = [await Watcher.open(ws, "stage", RIG_IDS[i % 3]) for i in range(8)]
        publisher = await Publisher.open(ws, "stage", "alpha")
        seq = 0

        async def everyone_has_results() -> bool:
            nonlocal seq
            await publisher.send(seq, points(rigs["alpha"], seq))
            seq += 1
            return all(w.results for w in watchers)

        await wait_for(everyone_has_results, timeout=20, what="results on every worker")
        await publisher.close()
    finally:
        status = server.stop(timeout=30)  # SIGTERM

    assert status == 0


def test_serve_takes_redis_from_the_flag_or_the_environment():
    from facecast.cli.commands.serve import settings_from_args
    from facecast.cli.main import build_parser

    flag = build_parser().parse_args(["serve", "--redis", "redis://r:6379/0"])
    env = build_parser().parse_args(["serve"])

    assert settings_from_args(flag, env={}).redis_url == "redis://r:6379/0"
    assert (
        settings_from_args(env, env={"FACECAST_REDIS_URL": "redis://e/1"}).redis_url
        == "redis://e/1"
    )
    assert settings_from_args(env, env={}).redis_url == ""


def test_serve_refuses_a_redis_url_that_is_not_one(capsys):
    assert main(["serve", "--redis", "http://example.org"]) == 2
    assert "redis_url" in capsys.readouterr().err

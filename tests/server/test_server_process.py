"""`facecast serve` as a real process: rigs survive SIGKILL, SIGTERM closes sessions with 1001."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets
from _server_helpers import frame_points, open_session, serve_argv, server_process, stop

from facecast.protocol import Frame, Result, decode_server, encode
from facecast.rig import rig_from_bytes
from facecast.server.testing import free_port

pytestmark = pytest.mark.slow


def test_rig_survives_sigkill_and_restart(tmp_path, rig):
    port = free_port()
    rigs = tmp_path / "rigs"
    with server_process(port, rigs) as process:
        put = httpx.put(f"http://127.0.0.1:{port}/v1/rigs/face", content=rig.to_bytes())
        stop(process, signal.SIGKILL)
    with server_process(port, rigs):
        meta = httpx.get(f"http://127.0.0.1:{port}/v1/rigs/face")
        downloaded = httpx.get(f"http://127.0.0.1:{port}/v1/rigs/face/rig")
        weights = asyncio.run(_one_result(port, frame_points(rig, 3)))

    assert put.status_code == 201
    assert meta.status_code == 200 and meta.json()["checksum"] == rig.checksum
    assert rig_from_bytes(downloaded.content).checksum == rig.checksum
    np.testing.assert_array_equal(weights, rig.weights(frame_points(rig, 3)).astype(np.float32))
    assert not [p.name for p in rigs.iterdir() if p.name.startswith(".tmp-")]


async def _one_result(port: int, points: np.ndarray) -> np.ndarray:
    async with websockets.connect(f"ws://127.0.0.1:{port}/v1/stream") as ws:
        await open_session(ws, "face")
        await ws.send(encode(Frame(seq=0, ts=0.0, points=points)))
        result = decode_server(await asyncio.wait_for(ws.recv(), 10))
    assert isinstance(result, Result)
    return result.weights


def test_sigterm_closes_open_sessions_with_1001_and_exits_cleanly(tmp_path, rig):
    port = free_port()
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    rig.save(rigs / "face.rig")

    async def scenario(process) -> int | None:
        async with websockets.connect(f"ws://127.0.0.1:{port}/v1/stream") as ws:
            await open_session(ws, "face")
            process.send_signal(signal.SIGTERM)
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await asyncio.wait_for(ws.recv(), 15)
        return ws.close_code

    with server_process(port, rigs) as process:
        code = asyncio.run(scenario(process))
        exit_status = process.wait(15)
        log = process.stderr.read().decode()

    assert code == 1001
    # uvicorn re-raises the signal after its graceful shutdown; serve takes it and says 0,
    # as the --workers N supervisor does.
    assert exit_status == 0
    assert '"event":"session.close"' in log and '"code":1001' in log
    assert '"event":"server.stop"' in log  # the lifespan shutdown ran to its end


def test_public_bind_without_tokens_refuses_to_start_with_a_clear_message(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACECAST_")}
    completed = subprocess.run(
        serve_argv("--host", "0.0.0.0", "--port", str(free_port()), "--rigs", str(tmp_path)),
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
    )

    assert completed.returncode != 0
    assert "no API tokens are configured" in completed.stderr


def test_two_workers_share_the_rig_directory(tmp_path, rig):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    with server_process(port, tmp_path / "rigs", "--workers", "2") as process:
        put = httpx.put(f"{base}/v1/rigs/face", content=rig.to_bytes())
        # New connections are spread over both workers by the kernel; every one sees it.
        seen = [httpx.get(f"{base}/v1/rigs/face").status_code for _ in range(8)]
        metrics = httpx.get(f"{base}/metrics").text
        exit_status = stop(process, signal.SIGTERM)

    assert put.status_code == 201
    assert seen == [200] * 8
    assert "facecast_http_requests_total" in metrics
    assert exit_status == 0


def _worker_pids(parent: int) -> list[int]:
    children = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    commands = {int(pid): _cmdline(int(pid)) for pid in children}
    return [
        pid
        for pid, command in commands.items()
        if b"spawn_main" in command and b"resource_tracker" not in command
    ]


def _cmdline(pid: int) -> bytes:
    """The process's command line; empty once it has gone (a worker just killed can leave
    between the parent's list of children and this read: CI saw FileNotFoundError)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError):
        return b""


def _open_connections(base: str) -> float:
    for line in httpx.get(f"{base}/metrics", timeout=5).text.splitlines():
        if line.startswith("facecast_connections "):
            return float(line.split()[1])
    raise AssertionError("no facecast_connections in /metrics")


def test_a_killed_worker_no_longer_counts_its_connections(tmp_path, rig):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    (tmp_path / "rigs").mkdir()
    (tmp_path / "rigs" / "face.rig").write_bytes(rig.to_bytes())

    async def scenario(process) -> tuple[float, float]:
        async with websockets.connect(f"ws://127.0.0.1:{port}/v1/stream") as ws:
            await open_session(ws, "face")
            during = _open_connections(base)
            workers = _worker_pids(process.pid)
            assert len(workers) == 2
            for pid in workers:
                os.kill(pid, signal.SIGKILL)
        # Wait (bounded) for two new workers to serve, then read the gauge they share (a
        # worker just started may answer before any process has written the gauge: seen
        # once on a loaded machine, "no facecast_connections"; read again until it is there).
        deadline = asyncio.get_running_loop().time() + 30
        while True:
            replaced = [pid for pid in _worker_pids(process.pid) if pid not in workers]
            if len(replaced) == 2:
                with contextlib.suppress(httpx.HTTPError, AssertionError):
                    return during, _open_connections(base)
            assert asyncio.get_running_loop().time() < deadline, (
                f"workers restarted: {len(replaced)} of 2, or no facecast_connections gauge"
            )
            await asyncio.sleep(0.1)

    with server_process(port, tmp_path / "rigs", "--workers", "2") as process:
        during, after = asyncio.run(scenario(process))
        stop(process, signal.SIGTERM)

    assert during == 1.0
    assert after == 0.0


def test_a_supervisor_killed_with_sigkill_leaves_metrics_the_next_one_removes(tmp_path, rig):
    # kill -9 skips the supervisor's clean-up of its workers' metric files; the next
    # supervisor started on the machine removes the directory of one no longer running.
    port = free_port()
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {"TMPDIR": str(temp)}
    with server_process(port, tmp_path / "rigs", "--workers", "2", env=env) as process:
        left = [p for p in temp.iterdir() if p.name.startswith("facecast-metrics-")]
        workers = _worker_pids(process.pid)
        stop(process, signal.SIGKILL)
        for pid in workers:  # orphans now: they would go on serving
            os.kill(pid, signal.SIGKILL)
    assert [p.name.split("-")[2] for p in left] == [str(process.pid)]
    assert left[0].exists()

    with server_process(free_port(), tmp_path / "rigs", "--workers", "2", env=env) as second:
        now = [p.name for p in temp.iterdir() if p.name.startswith("facecast-metrics-")]
        stop(second, signal.SIGTERM)

    assert not left[0].exists()
    assert [name.split("-")[2] for name in now] == [str(second.pid)]

"""docker/: the compose file parses and has the broadcast topology; nginx passes WebSockets.

Docker cannot run on the test machine: the compose file and Dockerfile are checked for
structure; the nginx config runs for real (addresses moved to loopback) in front of a
real facecast when nginx is installed, and is skipped otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import re
import shutil
import socket
import subprocess
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml

from facecast.protocol import ChannelLive
from facecast.server.testing import free_port, run_server

from ._helpers import Publisher, Watcher, points
from .conftest import TOKENS

DOCKER = Path(__file__).resolve().parents[2] / "docker"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def test_compose_runs_redis_two_replicas_and_a_proxy(compose):
    services = compose["services"]
    facecast = services["facecast"]

    assert set(services) >= {"redis", "facecast", "proxy"}
    assert facecast["deploy"]["replicas"] >= 2
    assert facecast["environment"]["FACECAST_REDIS_URL"].startswith("redis://redis:")
    assert "rigs:/data/rigs" in facecast["volumes"] and "rigs" in compose["volumes"]
    assert "ports" not in facecast  # scalable: only the proxy publishes a port
    # ... so only nginx reaches it: its X-Forwarded-For names each viewer for the quota.
    assert facecast["environment"]["FACECAST_TRUSTED_PROXIES"] == "*"
    assert "container_name" not in facecast
    assert facecast["depends_on"]["redis"]["condition"] == "service_healthy"
    assert "./nginx.conf:/etc/nginx/nginx.conf:ro" in services["proxy"]["volumes"]


def test_dockerfile_builds_the_viewer_and_runs_unprivileged_with_a_healthcheck():
    text = (DOCKER / "Dockerfile").read_text()
    stages = re.findall(r"^FROM (\S+)", text, flags=re.MULTILINE)

    assert stages[-1] == "python:3.11-slim"
    assert any(stage.startswith("node:") for stage in stages[:-1])
    assert "npm run build" in text
    assert re.search(r"^USER (?!root)\w+", text, flags=re.MULTILINE)
    assert re.search(r"^HEALTHCHECK .*\n?.*/healthz", text, flags=re.MULTILINE)


def test_nginx_config_upgrades_websockets_with_long_timeouts():
    text = (DOCKER / "nginx.conf").read_text()

    assert "proxy_set_header Upgrade $http_upgrade;" in text
    assert "proxy_set_header Connection $connection_upgrade;" in text
    assert "proxy_http_version 1.1;" in text
    assert int(re.search(r"proxy_read_timeout (\d+)s;", text).group(1)) >= 600


@pytest.mark.skipif(shutil.which("nginx") is None, reason="nginx is not installed here")
def test_nginx_accepts_the_config(tmp_path):
    result = subprocess.run(
        ["nginx", "-t", "-c", str(DOCKER / "nginx.conf"), "-p", str(tmp_path)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip

    assert result.returncode == 0, result.stderr


@contextlib.contextmanager
def _nginx(upstream_port: int, tmp_path: Path):
    """Real nginx running docker/nginx.conf, with only its addresses moved to loopback."""
    port = free_port()
    text = (DOCKER / "nginx.conf").read_text()
    text = text.replace("listen 80;", f"listen 127.0.0.1:{port};")
    text = text.replace("http://facecast:8000", f"http://127.0.0.1:{upstream_port}")
    assert f"127.0.0.1:{port}" in text and f"127.0.0.1:{upstream_port}" in text
    (tmp_path / "logs").mkdir()
    (tmp_path / "nginx.conf").write_text(text)
    process = subprocess.Popen(
        ["nginx", "-c", str(tmp_path / "nginx.conf"), "-p", str(tmp_path),
         "-g", f"daemon off; pid {tmp_path / 'nginx.pid'}; error_log stderr;"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 10
        while True:
            with socket.socket() as sock:
                if sock.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, "nginx did not listen"
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(10)


@pytest.mark.skipif(shutil.which("nginx") is None, reason="nginx is not installed here")
def test_the_proxy_config_passes_rest_and_channel_websockets_with_auth(
    settings, rigs, tmp_path, ws_impl
):
    settings = dataclasses.replace(settings, auth=True, tokens=TOKENS)
    frame = points(rigs["alpha"], 3)

    async def scenario(base: str):
        async with httpx.AsyncClient(base_url=base) as http:
            listed = await http.get("/v1/rigs", headers={"Authorization": "Bearer admin-token"})
            denied = await http.get("/v1/rigs")
        watcher = await Watcher.open(base, "stage", "beta", token="viewer-token")
        publisher = await Publisher.open(base, "stage", "alpha", token="publisher-token")
        try:
            await watcher.next(ChannelLive)
            await publisher.send(1, frame)
            result = await watcher.result_with_seq(1)
        finally:
            await publisher.close()
            await watcher.close()
        return listed, denied, result

    async def main():
        async with run_server(settings, ws=ws_impl) as server:
            with _nginx(server.port, tmp_path) as base:
                return await scenario(base)

    listed, denied, result = asyncio.run(main())

    assert listed.status_code == 200
    assert {rig["id"] for rig in listed.json()["rigs"]} >= {"alpha", "beta"}
    assert denied.status_code == 401
    np.testing.assert_array_equal(
        result.weights, rigs["beta"].weights(frame.astype(np.float32)).astype(np.float32)
    )

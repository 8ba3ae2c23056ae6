"""docker/: the compose file parses and has the broadcast topology; nginx passes WebSockets.

Docker cannot run on the test machine: these check structure only. ``nginx -t`` runs
when nginx is installed and is skipped otherwise.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

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

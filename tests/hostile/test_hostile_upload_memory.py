"""What the costliest real face the limits let through costs a real `facecast serve` (issue
#31's goals; SERVER.md "What an upload can cost the server").

A server process of its own, warmed by a small upload (the modules a fit imports, the
generic source set), so that its peak RSS growth (VmHWM reset through clear_refs) is the
upload's alone; scripts/upload_costs.py measures the same and more.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from facecast.server.settings import Settings
from facecast.server.testing import free_port
from tests.hostile._glb import dense, zeros
from tests.server._server_helpers import server_process

MiB = 1 << 20


def _status(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def test_a_dense_face_at_the_limits_costs_at_most_three_and_a_half_bodies(tmp_path):
    # 52 float32 ARKit targets on a 76,729-vertex face (max_gltf_morph_values), padded to
    # max_upload_bytes. Its body held once, the BIN chunk a view of it, the deltas read
    # as stored and the .character written without joining it to its header: +206 MB.
    # With the BIN chunk and the deltas copied (float64) and the .character joined, +255.
    limit = Settings().max_upload_bytes
    body = dense(limit, Settings().max_gltf_morph_values)
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    port = free_port()
    with (
        server_process(port, rigs, ready_timeout=60) as process,
        httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as http,
    ):
        warm = http.put("/v1/characters/warm", content=zeros(3, 1))
        before = _status(process.pid, "VmRSS")
        Path(f"/proc/{process.pid}/clear_refs").write_text("5")
        response = http.put("/v1/characters/dense", content=body)
        grown = _status(process.pid, "VmHWM") - before

    assert warm.status_code == 201, warm.text
    assert response.status_code == 201, response.text
    assert len(response.json()["names"]) == 44  # the neutral, 52 ARKit shapes but gaze and tongue
    assert len(body) > limit - 8192
    assert grown < 3.5 * limit, grown / MiB

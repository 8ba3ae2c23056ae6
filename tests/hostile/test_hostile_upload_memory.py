"""What the costliest real faces the limits let through cost a real `facecast serve` (issue
#31's goal; SERVER.md "What an upload can cost the server").

A server process of its own, warmed by a small upload (the modules a fit imports, the
generic source set), so that each upload's peak RSS growth (VmHWM reset through
clear_refs) is its own; scripts/upload_costs.py measures the same and more.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from facecast.server.settings import Settings
from facecast.server.testing import free_port
from tests.hostile._glb import dense, padded, zeros
from tests.server._server_helpers import server_process

MiB = 1 << 20
#: SERVER.md's constant: what a fit holds besides its body and the arrays the limits bound
#: (the interpreter's and numpy's working set; a one-triangle upload: 2 MiB).
CONSTANT = 4 * MiB


def _status(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def _upload(http: httpx.Client, pid: int, name: str, body: bytes) -> tuple[httpx.Response, int]:
    """The answer to one upload and the server's peak RSS growth while it was served."""
    before = _status(pid, "VmRSS")
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    response = http.put(f"/v1/characters/{name}", content=body)
    return response, _status(pid, "VmHWM") - before


def test_the_costliest_faces_cost_at_most_three_bodies_and_a_constant(tmp_path):
    # At max_gltf_vertices and max_gltf_faces with max_gltf_morph_values in float32 targets
    # (8 sparse targets on 500,000 vertices, 1,000,000 triangles), padded to
    # max_upload_bytes: its body, float64 vertices, int32 triangles, float32 morph targets
    # and basis, +186 MB (2.9x). With a float64 copy of the face per expression (main before
    # issue 31's last pass) it took +311 MB at the old limits' worst; with the read's freed
    # temporaries kept by the allocator, +197. And the dense face at max_gltf_morph_values
    # (52 float32 ARKit targets on 76,729 vertices): +154 MB (2.4x), +206 before.
    settings = Settings()
    limit = settings.max_upload_bytes
    vertices, faces = settings.max_gltf_vertices, settings.max_gltf_faces
    targets = settings.max_gltf_morph_values // vertices
    largest = padded(zeros(vertices, targets, indices=3 * faces), limit)
    real = dense(limit, settings.max_gltf_morph_values)
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    port = free_port()
    with (
        server_process(port, rigs, ready_timeout=60) as process,
        httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as http,
    ):
        warm = http.put("/v1/characters/warm", content=zeros(3, 1))
        stored, grown = _upload(http, process.pid, "largest", largest)
        stored_dense, grown_dense = _upload(http, process.pid, "dense", real)

    assert warm.status_code == 201, warm.text
    assert stored.status_code == 201, stored.text
    assert stored.json()["num_vertices"] == vertices
    assert len(stored.json()["names"]) == 1 + targets  # every target paired and fitted
    assert stored_dense.status_code == 201, stored_dense.text
    assert len(stored_dense.json()["names"]) == 44  # the neutral, 52 ARKit but gaze and tongue
    assert min(len(largest), len(real)) > limit - 8192
    # The goal, 3x + CONSTANT: the largest face measured +185 MB (2.89x) in 8 runs of 8,
    # +184.9 to +185.5 (2026-12-04 16:10 UTC, loaded 2-core VM), but later that day +203 MB
    # (3.17x) in 5 runs of 13 (which arena a thread's blocks land in is timing); with the
    # trim between its read and its fit (server/heap.py release_freed) +185.0 to +185.4 in
    # 14 of 14 (19:45 UTC); without the upload mode (glibc's dynamic thresholds) +196 to
    # +214 MB.
    assert grown <= 3 * limit + CONSTANT, grown / MiB
    assert grown_dense <= 3 * limit + CONSTANT, grown_dense / MiB

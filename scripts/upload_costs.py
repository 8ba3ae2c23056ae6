#!/usr/bin/env python3
"""Measures what one character upload costs a real `facecast serve` on 127.0.0.1 (SERVER.md).

For each body (hostile ones the glTF checks refuse, and ones at the ``max_gltf_*`` limits
that are read), sent to a server of its own after a small upload has warmed it: the
server's peak RSS growth over the request (its ``VmHWM`` reset through
``/proc/PID/clear_refs`` just before; the growth is the peak minus the RSS then: a server
that served a large upload before keeps some of its heap, which hides part of the next
one's growth), the time to the answer, and the answer. The bodies are GLBs written byte by byte by the test
suite's builders (tests/hostile/_glb.py; neither folder ships in the wheel, and the suite's
hostile uploads are the same bodies); the largest is just under ``max_upload_bytes``.
Loopback only. Run from the repository: `.venv/bin/python scripts/upload_costs.py`.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from hostile_costs import start, stop

from facecast.rig.evaluation.remesh import decimate, sqrt3_retriangulate
from facecast.rig.io.gltf_check import max_decoded_bytes
from facecast.rig.sources.ict import locate_ict
from facecast.rig.transfer import ict_source_expressions
from facecast.server.http.character_upload import gltf_limits
from facecast.server.settings import Settings
from tests.hostile._glb import aliased, dense, glb, meshopt_zeros, padded, zeros
from tests.rig._avatars import avatar

MiB = 1 << 20


def json_values(count: int) -> bytes:
    return glb({"asset": {"version": "2.0"}, "extras": [{}] * count})


#: The limits the largest faces are built at (the settings' defaults).
VERTICES = Settings().max_gltf_vertices
FACES = Settings().max_gltf_faces
MORPH_VALUES = Settings().max_gltf_morph_values
#: The meshopt decode limit (4 bytes a value of max_gltf_accessor_values), in whole rows.
DECODED = max_decoded_bytes(gltf_limits(Settings())) // 16 * 16
#: The transfer path's face limit; a face decimated to n vertices and retriangulated twice
#: has about 8.75 n (5,600 gave 48,972), so n = limit / 8.9 stays under it.
TRANSFER_VERTICES = Settings().max_transfer_vertices

SCENARIOS: dict[str, Callable[[int], bytes]] = {
    "issue: POSITION of 33.3 M zeros (396 B)": lambda _: zeros(33_300_000, 1),
    "issue: 99,999,999 indices (zeros)": lambda _: zeros(3, 1, indices=99_999_999),
    "200,000 nodes (2.2 MB)": lambda _: zeros(3, 1, nodes=200_000),
    "20,000 nodes, the limit": lambda _: zeros(3, 1, nodes=20_000),
    "one triangle padded to 2 MiB (the large uploads' lane: a fit's constant)": lambda _: padded(
        zeros(3, 1), 2 * MiB
    ),
    "JSON: 499,990 empty objects, at max_gltf_json_values": lambda _: json_values(499_990),
    "morph values at the limit: 76,923 vertices x 52 sparse targets (2 kB)": lambda _: zeros(
        76_923, 52
    ),
    "a dense face at the limit (52 float32 targets) padded to max_upload_bytes": dense,
    f"{VERTICES:,} vertices, {FACES:,} triangles, {MORPH_VALUES // VERTICES} sparse float32 "
    "targets (2 kB): vertices, faces, morph values at their limits": lambda _: zeros(
        VERTICES, MORPH_VALUES // VERTICES, indices=3 * FACES
    ),
    "the same padded to max_upload_bytes": lambda limit: padded(
        zeros(VERTICES, MORPH_VALUES // VERTICES, indices=3 * FACES), limit
    ),
    f"the same with {MORPH_VALUES // VERTICES // 2} int16 (quantised, counted twice) targets, "
    "padded to max_upload_bytes": lambda limit: padded(
        zeros(VERTICES, MORPH_VALUES // VERTICES // 2, indices=3 * FACES, quantized=True), limit
    ),
    "1 M vertices, 2 M triangles, 4 sparse float32 targets, padded to max_upload_bytes "
    "(over the limits since 2026-12-04)": lambda limit: padded(
        zeros(1_000_000, 4, indices=6_000_000), limit
    ),
    f"meshopt: a view of {DECODED / 1e6:.0f} MB of zeros in {DECODED // 64 / 1e6:.0f} MB, "
    "max_gltf_accessor_values x 4 bytes": lambda _: meshopt_zeros(DECODED),
    "VRM: 44 expressions binding one morph of a 90,909-vertex face, at the limit": lambda _: (
        aliased(90_909, 44)
    ),
    f"VRM: 44 expressions binding one morph of a {VERTICES:,}-vertex face": lambda _: aliased(
        VERTICES, 44
    ),
}

#: Uploads with ``?expressions=transfer&markers=auto`` (the server given ICT-FaceKit as its
#: transfer source): the peak covers the request and the transfer job it starts, to its end.
TRANSFERS: dict[str, Callable[[int], bytes]] = {
    f"transfer: a neutral-only face of {VERTICES:,} vertices and {FACES:,} triangles, padded "
    "to max_upload_bytes (over max_transfer_vertices)": lambda limit: padded(
        zeros(VERTICES, 0, indices=3 * FACES), limit
    ),
    "transfer: the ICT test avatar without expressions (its 14,062-vertex face)": lambda _: avatar(
        "neutral_only"
    ),
    "transfer: ICT's face remeshed to ~10,000 vertices, no expressions (automatic "
    "correspondence)": lambda _: remeshed_face(3400, 1),
    f"transfer: ICT's face remeshed to just under max_transfer_vertices ({TRANSFER_VERTICES:,}), "
    "no expressions": lambda _: remeshed_face(round(TRANSFER_VERTICES / 8.9), 2),
}


def remeshed_face(kept: int, times: int) -> bytes:
    """ICT's neutral face decimated to ``kept`` vertices and retriangulated ``times`` (as
    `facecast bench transfer` makes its ~10k and ~50k targets): a neutral-only GLB whose
    topology is not ICT's (the transfer fits its correspondence)."""
    archive = locate_ict()
    assert archive is not None
    source = ict_source_expressions(archive)
    twice = decimate(source.vertices[0], source.faces, kept)
    for _ in range(times):
        twice = sqrt3_retriangulate(twice.vertices, twice.faces)
    positions = twice.vertices.astype("<f4")
    blob = positions.tobytes() + twice.faces.astype("<u4").tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteLength": positions.nbytes},
            {"buffer": 0, "byteOffset": positions.nbytes, "byteLength": twice.faces.size * 4},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
             "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
            {"bufferView": 1, "componentType": 5125, "count": twice.faces.size, "type": "SCALAR"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}],
    }  # fmt: skip
    return glb(doc, blob)


def peak_reset(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def status(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def measure(name: str, body: bytes, limit: int, transfer: str = "") -> None:
    """One upload to a server of its own, warmed up by a small character's (the modules a
    fit imports and the generic source set are loaded once per process, not per upload);
    ``transfer``: ICT-FaceKit's path, the upload a transfer's, waited for to its end."""
    env = [f"FACECAST_MAX_UPLOAD_BYTES={limit}"]
    params = {}
    if transfer:
        env.append(f"FACECAST_TRANSFER_SOURCE={transfer}")
        params = {"expressions": "transfer", "markers": "auto"}
    with tempfile.TemporaryDirectory() as tmp:
        process, port = start("websockets-sansio", Path(tmp), *env)
        try:
            with httpx.Client(
                base_url=f"http://127.0.0.1:{port}", timeout=600,
                headers={"Authorization": "Bearer secret"},
            ) as http:  # fmt: skip
                warm = http.put("/v1/characters/warm", content=zeros(3, 1))
                assert warm.status_code == 201, warm.text
                if transfer:  # the source's expressions are read once per process
                    warm = http.put("/v1/characters/warm", content=avatar("neutral_only"),
                                    params=params)  # fmt: skip
                    assert warm.status_code == 202, warm.text
                    finish(http, "warm")
                before = status(process.pid, "VmRSS")
                peak_reset(process.pid)
                started = time.perf_counter()
                response = http.put("/v1/characters/measured", content=body, params=params)
                if response.status_code == 202:
                    response = finish(http, "measured")
                seconds = time.perf_counter() - started
                grown = status(process.pid, "VmHWM") - before
        finally:
            stop(process)
    code = response.json().get("code", "") if response.status_code >= 400 else ""
    print(f"{name}: {len(body) / MiB:.2f} MiB body -> {response.status_code} {code} in "
          f"{seconds:.2f} s, peak RSS +{grown:.0f} MB over {before:.0f} MB "
          f"({grown / (limit / MiB):.2f}x max_upload_bytes)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=64 * MiB, help="max_upload_bytes")
    parser.add_argument("--only", default="", help="the uploads whose name holds this text")
    args = parser.parse_args()
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, "
          f"python {platform.python_version()}, max_upload_bytes {args.limit}, "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")  # fmt: skip
    for name, make in SCENARIOS.items():
        if args.only in name:
            measure(name, make(args.limit), args.limit)
    ict = locate_ict()
    for name, make in TRANSFERS.items():
        if args.only in name:
            if ict is None:
                print(f"{name}: not measured (no ICT-FaceKit: ../shared/data/ict-facekit)")
                continue
            measure(name, make(args.limit), args.limit, str(ict))


def finish(http: httpx.Client, rig_id: str) -> httpx.Response:
    """The transfer job of ``rig_id`` waited for, its record as the answer it stands for:
    201, or its error."""
    while (job := http.get(f"/v1/characters/{rig_id}/job").json())["state"] not in (
        "done", "failed", "cancelled"
    ):  # fmt: skip
        time.sleep(0.5)
    if job["state"] == "done":
        return httpx.Response(201, json=job)
    return httpx.Response(422, json={"code": f"job {job['state']}: {job['error']['code']}"})


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Measures what one character upload costs a real `facecast serve` on 127.0.0.1 (SERVER.md).

For each body (hostile ones the glTF checks refuse, and ones at the ``max_gltf_*`` limits
that are read), the server's peak RSS growth over the request (its ``VmHWM`` reset through
``/proc/PID/clear_refs`` just before; the growth is the peak minus the RSS then), the
time to the answer, and the answer. The bodies are tiny GLBs written here; the largest is
just under ``max_upload_bytes``. Loopback only. Run from the repository:
`.venv/bin/python scripts/upload_costs.py`.
"""

from __future__ import annotations

import argparse
import json
import platform
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from hostile_costs import start, stop

from facecast.rig.characters.expression_names import ARKIT_NAMES
from facecast.rig.io.gltf import export_glb

MiB = 1 << 20


def glb(doc: dict[str, Any], blob: bytes = b"") -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if blob:
        chunks += struct.pack("<I4s", len(blob), b"BIN\0") + blob
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def zeros(vertices: int, targets: int, nodes: int = 1, indices: int = 0) -> bytes:
    """A mesh whose accessors have no bufferView (all zeros): a few bytes declaring much.
    Each target moves one vertex (a sparse accessor of 16 bytes), so that it is read,
    paired and fitted as a real expression."""
    blob = struct.pack("<I3f", 1, 0.0, 0.0, 0.01)
    views = [
        {"buffer": 0, "byteOffset": 0, "byteLength": 4},
        {"buffer": 0, "byteOffset": 4, "byteLength": 12},
    ]
    sparse = {
        "count": 1,
        "indices": {"bufferView": 0, "componentType": 5125},
        "values": {"bufferView": 1},
    }
    accessors: list[dict[str, Any]] = [{"componentType": 5126, "count": vertices, "type": "VEC3"}]
    accessors += [
        {"componentType": 5126, "count": vertices, "type": "VEC3", "sparse": sparse}
    ] * targets
    prim: dict[str, Any] = {
        "attributes": {"POSITION": 0},
        "targets": [{"POSITION": 1 + t} for t in range(targets)],
    }
    if indices:
        accessors.append({"componentType": 5125, "count": indices, "type": "SCALAR"})
        prim["indices"] = len(accessors) - 1
    names = [*ARKIT_NAMES, *(f"extra{i}" for i in range(targets))][:targets]
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
        "meshes": [{"primitives": [prim], "extras": {"targetNames": names}}],
        "nodes": [{"mesh": 0}] + [{} for _ in range(nodes - 1)],
    }
    return glb(doc, blob)


def dense(limit: int) -> bytes:
    """A real face at ``max_gltf_morph_values``: a grid mesh of 76,900 vertices with 52
    ARKit targets in float32, padded to just under ``limit`` bytes by a bufferView nothing
    reads (as a texture's bytes would be)."""
    side = int(np.sqrt(4_000_000 / 52))
    u = np.linspace(0.0, 1.0, side)
    uu, vv = np.meshgrid(u, u)
    neutral = np.stack([uu * 0.16, vv * 0.2, 0.05 * np.sin(uu * 3)], axis=-1).reshape(-1, 3)
    i = np.arange(side - 1)
    a = (i[:, None] * side + i[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([a, a + 1, a + side + 1], 1), np.stack([a, a + side + 1, a + side], 1)]
    )
    rng = np.random.default_rng(0)
    shape = np.sin(neutral[None, :, :1] * rng.uniform(5, 40, (52, 1, 1)))
    deltas = rng.normal(0, 0.003, (52, 1, 3)) * shape
    data = export_glb(neutral, faces, deltas, list(ARKIT_NAMES), normals=False)
    (length,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20 : 20 + length])
    blob = data[28 + length :]
    pad = limit - len(data) - 4096
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": pad})
    doc["buffers"][0]["byteLength"] = len(blob) + pad
    return glb(doc, blob + b"\x01" * pad)


def json_values(count: int) -> bytes:
    return glb({"asset": {"version": "2.0"}, "extras": [{}] * count})


SCENARIOS: dict[str, Callable[[int], bytes]] = {
    "issue: POSITION of 33.3 M zeros (396 B)": lambda _: zeros(33_300_000, 1),
    "issue: 99,999,999 indices (zeros)": lambda _: zeros(3, 1, indices=99_999_999),
    "200,000 nodes (2.2 MB)": lambda _: zeros(3, 1, nodes=200_000),
    "20,000 nodes, the limit": lambda _: zeros(3, 1, nodes=20_000),
    "JSON: 499,990 empty objects, at max_gltf_json_values": lambda _: json_values(499_990),
    "morph values at the limit: 76,923 vertices x 52 sparse targets (2 kB)": lambda _: zeros(
        76_923, 52
    ),
    "a dense face at the limit (52 float32 targets) padded to max_upload_bytes": dense,
}


def peak_reset(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def status(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=64 * MiB, help="max_upload_bytes")
    args = parser.parse_args()
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, "
          f"python {platform.python_version()}, max_upload_bytes {args.limit}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        process, port = start(
            "websockets-sansio", Path(tmp), f"FACECAST_MAX_UPLOAD_BYTES={args.limit}"
        )
        headers = {"Authorization": "Bearer secret"}
        try:
            with httpx.Client(
                base_url=f"http://127.0.0.1:{port}", timeout=600, headers=headers
            ) as http:
                http.get("/v1/rigs")  # warm up
                print(f"# floor: server RSS {status(process.pid, 'VmRSS'):.0f} MB idle")
                for number, (name, make) in enumerate(SCENARIOS.items()):
                    body = make(args.limit)
                    before = status(process.pid, "VmRSS")
                    peak_reset(process.pid)
                    started = time.perf_counter()
                    response = http.put(f"/v1/characters/c{number}", content=body)
                    seconds = time.perf_counter() - started
                    grown = status(process.pid, "VmHWM") - before
                    code = response.json().get("code", "") if response.status_code >= 400 else ""
                    print(f"{name}: {len(body) / MiB:.2f} MiB body -> {response.status_code} "
                          f"{code} in {seconds:.2f} s, peak RSS +{grown:.0f} MB "
                          f"({grown * MiB / max(len(body), 1):.1f}x the body, "
                          f"{grown / (args.limit / MiB):.2f}x max_upload_bytes)")  # fmt: skip
        finally:
            stop(process)


if __name__ == "__main__":
    main()

"""GLB bodies written byte by byte for the hostile uploads: the container, and the costliest
characters the ``max_gltf_*`` limits let through.

Shared by tests/hostile and scripts/upload_costs.py (which measures what these cost a
server, SERVER.md "What an upload can cost the server"); they never call facecast's reader.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from facecast.rig.characters.expression_names import ARKIT_NAMES
from facecast.rig.io.gltf import export_glb

#: ARKit's gaze shapes: the generic pairing leaves them out (generic.GAZE_SHAPES).
_GAZE = ("eyeLook",)
_MESHOPT = "EXT_meshopt_compression"


def glb(doc: dict[str, Any], blob: bytes = b"") -> bytes:
    """A glTF binary: the JSON chunk, and a BIN chunk when ``blob`` is given."""
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if blob:
        chunks += struct.pack("<I4s", len(blob), b"BIN\0") + blob
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def split(data: bytes) -> tuple[dict[str, Any], bytes]:
    """A GLB's JSON document and BIN chunk (of a GLB written by ``glb`` or export_glb)."""
    (length,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[20 : 20 + length]), data[28 + length :]


def zeros(
    vertices: int, targets: int, nodes: int = 1, indices: int = 0, *, quantized: bool = False
) -> bytes:
    """A mesh whose accessors have no bufferView (all zeros): a few bytes declaring much.
    Each target moves one vertex (a sparse accessor of 16 bytes), so that it is read,
    paired and fitted as a real expression; ARKit's names, gaze last (the generic pairing
    leaves gaze out). ``quantized``: the targets as normalised int16 (KHR_mesh_quantization),
    which a reader turns into float64."""
    if quantized:
        blob = struct.pack("<I3h2x", 1, 0, 0, 300)
    else:
        blob = struct.pack("<I3f", 1, 0.0, 0.0, 0.01)
    views = [
        {"buffer": 0, "byteOffset": 0, "byteLength": 4},
        {"buffer": 0, "byteOffset": 4, "byteLength": 6 if quantized else 12},
    ]
    sparse = {
        "count": 1,
        "indices": {"bufferView": 0, "componentType": 5125},
        "values": {"bufferView": 1},
    }
    accessors: list[dict[str, Any]] = [{"componentType": 5126, "count": vertices, "type": "VEC3"}]
    target: dict[str, Any] = {"componentType": 5126, "count": vertices, "type": "VEC3"}
    if quantized:
        target.update(componentType=5122, normalized=True)
    accessors += [{**target, "sparse": sparse}] * targets
    prim: dict[str, Any] = {
        "attributes": {"POSITION": 0},
        "targets": [{"POSITION": 1 + t} for t in range(targets)],
    }
    if indices:
        accessors.append({"componentType": 5125, "count": indices, "type": "SCALAR"})
        prim["indices"] = len(accessors) - 1
    arkit = sorted(ARKIT_NAMES, key=lambda n: n.startswith(_GAZE))
    names = [*arkit, *(f"extra{i}" for i in range(targets))][:targets]
    doc: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
        "meshes": [{"primitives": [prim], "extras": {"targetNames": names}}],
        "nodes": [{"mesh": 0}] + [{} for _ in range(nodes - 1)],
    }
    if quantized:
        doc["extensionsUsed"] = doc["extensionsRequired"] = ["KHR_mesh_quantization"]
    return glb(doc, blob)


def grid_face(vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A curved grid of about ``vertices`` vertices (the largest square not above it): its
    (V, 3) vertices and (F, 3) triangles."""
    side = int(np.sqrt(vertices))
    u = np.linspace(0.0, 1.0, side)
    uu, vv = np.meshgrid(u, u)
    neutral = np.stack([uu * 0.16, vv * 0.2, 0.05 * np.sin(uu * 3)], axis=-1).reshape(-1, 3)
    i = np.arange(side - 1)
    a = (i[:, None] * side + i[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([a, a + 1, a + side + 1], 1), np.stack([a, a + side + 1, a + side], 1)]
    )
    return neutral, faces


def padded(data: bytes, size: int) -> bytes:
    """``data`` (a GLB with a BIN chunk) grown to about ``size`` bytes by a bufferView nothing
    reads (as a texture's bytes would be); as it is when it is that large already."""
    doc, blob = split(data)
    pad = size - len(data) - 4096
    if pad <= 0:
        return data
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": pad})
    doc["buffers"][0]["byteLength"] = len(blob) + pad
    return glb(doc, blob + b"\x01" * pad)


def dense(size: int, morph_values: int = 4_000_000) -> bytes:
    """A real face at ``morph_values`` (``max_gltf_morph_values``): a grid mesh of
    ``morph_values / 52`` vertices with the 52 ARKit targets in float32, padded to just
    under ``size`` bytes."""
    neutral, faces = grid_face(morph_values // len(ARKIT_NAMES))
    rng = np.random.default_rng(0)
    shape = np.sin(neutral[None, :, :1] * rng.uniform(5, 40, (len(ARKIT_NAMES), 1, 1)))
    deltas = rng.normal(0, 0.003, (len(ARKIT_NAMES), 1, 3)) * shape
    return padded(export_glb(neutral, faces, deltas, list(ARKIT_NAMES), normals=False), size)


def aliased(vertices: int, expressions: int) -> bytes:
    """A VRM 1.0 face of ``vertices`` vertices with one morph target (``jawOpen``) and
    ``expressions`` - 1 more ARKit-named custom expressions, each binding that one morph at
    weight 1: a few bytes each, yet each is paired and fitted as a face of its own."""
    neutral, faces = grid_face(vertices)
    deltas = np.zeros((1, len(neutral), 3))
    deltas[0, :, 2] = 0.01 * np.sin(neutral[:, 0] * 20)
    doc, blob = split(export_glb(neutral, faces, deltas, ["jawOpen"], normals=False))
    names = [n for n in ARKIT_NAMES if n != "jawOpen" and not n.startswith(_GAZE)]
    if expressions - 1 > len(names):
        raise ValueError(f"at most {len(names) + 1} expressions")
    bind = [{"node": 0, "index": 0, "weight": 1.0}]
    custom = {name: {"morphTargetBinds": bind} for name in names[: expressions - 1]}
    doc["extensionsUsed"] = [*doc.get("extensionsUsed", []), "VRMC_vrm"]
    doc["extensions"] = {"VRMC_vrm": {"specVersion": "1.0", "expressions": {"custom": custom}}}
    return glb(doc, blob)


def triangle() -> tuple[dict[str, Any], bytes]:
    """One triangle with a ``jawOpen`` morph target: the document and its BIN chunk."""
    positions = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
    delta = struct.pack("<9f", 0, 0, 0.1, 0, 0, 0.1, 0, 0, 0.1)
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": 72}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 36},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
        ],
        "meshes": [
            {
                "primitives": [{"attributes": {"POSITION": 0}, "targets": [{"POSITION": 1}]}],
                "extras": {"targetNames": ["jawOpen"]},
            }
        ],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    return doc, positions + delta


def meshopt_zeros(decoded: int, stride: int = 16, read_rows: int | None = None) -> bytes:
    """``triangle`` plus a bufferView that EXT_meshopt_compression stores compressed:
    ``decoded`` bytes of zeros (rounded down to ``stride``) in about ``decoded / 64``
    bytes, in a fallback buffer, and an accessor no mesh uses reading the first byte of
    each of its first ``read_rows`` rows (every row by default; 0: no accessor)."""
    import meshopt  # facecast's own dependency (rig/io/gltf_compression.py)

    count = decoded // stride
    doc, blob = triangle()
    encoded = meshopt.encode_gltf_buffer(np.zeros((count, stride), np.uint8), "ATTRIBUTES")
    compressed = {
        "buffer": 0, "byteOffset": len(blob), "byteLength": len(encoded), "byteStride": stride,
        "count": count, "mode": "ATTRIBUTES",
    }  # fmt: skip
    doc["extensionsUsed"] = ["EXT_meshopt_compression"]
    doc["buffers"] = [
        {"byteLength": len(blob) + len(encoded)},
        {"byteLength": count * stride, "extensions": {_MESHOPT: {"fallback": True}}},
    ]
    doc["bufferViews"].append(
        {
            "buffer": 1,
            "byteLength": count * stride,
            "byteStride": stride,
            "extensions": {_MESHOPT: compressed},
        }
    )
    rows = count if read_rows is None else read_rows
    if rows:
        view = len(doc["bufferViews"]) - 1
        doc["accessors"].append(
            {"bufferView": view, "componentType": 5121, "count": rows, "type": "SCALAR"}
        )
    return glb(doc, blob + encoded)

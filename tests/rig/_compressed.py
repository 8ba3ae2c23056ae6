"""Compressed twins of a test avatar, made at test time by the codecs' own encoders.

``compressed(glb, kind)`` rewrites a GLB written by pygltflib (one accessor a buffer view,
as tests/rig/_avatars.py writes them) the way an exporter or optimiser would:

- ``meshopt``: every accessor's view through meshoptimizer's encoder (``meshopt``, the
  package facecast decodes with), vertex data as ATTRIBUTES (morph targets through the
  exponential filter, as gltfpack does), indices as TRIANGLES, behind a fallback buffer;
- ``quantized``: ``KHR_mesh_quantization`` with positions and morph targets as 16-bit
  integers, normals as normalised bytes and UVs as normalised shorts; the dequantisation
  (one scale and offset for the file) folded into the skin's inverse bind matrices;
- ``draco``: each primitive's positions, normals, UVs and triangles through Draco's
  encoder (DracoPy, order preserved), joints, weights and morph targets left as accessors.

``gltfpack(glb)`` runs the real tool: npm's gltfpack (meshoptimizer's own glTF optimiser, a
devDependency of client/viewer) with ``-cc``, meshopt compression over quantisation as
published files have it (filters, 14-bit positions, dequantisation in the nodes).

Nothing here is a decoder: the reader under test and three.js decode these files.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import DracoPy
import meshopt
import numpy as np

from facecast.rig.io.gltf import pack_glb

KINDS = ("meshopt", "quantized", "draco")
GLTFPACK = Path(__file__).resolve().parents[2] / "client/viewer/node_modules/gltfpack/cli.js"
#: Why a gltfpack test cannot run here, or None; never on CI (its setup installs it).
GLTFPACK_MISSING = (
    None
    if GLTFPACK.is_file() or os.environ.get("CI") == "true"
    else "npm's gltfpack is not installed (npm ci in client/viewer)"
)

_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}  # fmt: skip
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def split_glb(glb: bytes) -> tuple[dict[str, Any], bytes]:
    length = int.from_bytes(glb[12:16], "little")
    doc = json.loads(glb[20 : 20 + length])
    at = 20 + length
    return doc, glb[at + 8 : at + 8 + int.from_bytes(glb[at : at + 4], "little")]


class _Blob:
    """A BIN chunk being written: each part 4-byte aligned; returns its offset."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0

    def add(self, data: bytes) -> int:
        at = self.size
        self.parts.append(data + b"\0" * ((-len(data)) % 4))
        self.size += len(self.parts[-1])
        return at

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def _array(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = _DTYPES[acc["componentType"]]
    ncomp = _NCOMP[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    count = acc["count"]
    return np.frombuffer(blob, dtype, count * ncomp, start).reshape(count, ncomp).copy()


def _uses(doc: dict[str, Any]) -> tuple[set[int], set[int]]:
    """Accessor indices used as triangle indices, and as morph target positions."""
    indices, targets = set(), set()
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            if "indices" in prim:
                indices.add(prim["indices"])
            for target in prim.get("targets", []):
                targets.update(v for k, v in target.items() if k == "POSITION")
    return indices, targets


def _require(doc: dict[str, Any], extension: str) -> None:
    doc["extensionsUsed"] = sorted({*doc.get("extensionsUsed", []), extension})
    doc["extensionsRequired"] = sorted({*doc.get("extensionsRequired", []), extension})


def _meshopt(doc: dict[str, Any], blob: bytes) -> bytes:
    indices, targets = _uses(doc)
    out = _Blob()
    fallback = 0
    by_view = {
        acc["bufferView"]: i for i, acc in enumerate(doc["accessors"]) if "bufferView" in acc
    }
    for number, view in enumerate(doc["bufferViews"]):
        data = blob[view.get("byteOffset", 0) : view.get("byteOffset", 0) + view["byteLength"]]
        index = by_view.get(number)
        if index is None:  # an image: stored as it is
            view["byteOffset"] = out.add(data)
            continue
        values = _array(doc, blob, index)
        if index in indices:
            encoded = meshopt.encode_gltf_buffer(values.reshape(-1).astype(np.uint32), "TRIANGLES")
            ext = {"byteStride": 4, "count": values.size, "mode": "TRIANGLES"}
        elif index in targets:
            rows = meshopt.encode_filter_exp(values, 16, "Separate")
            encoded = meshopt.encode_gltf_buffer(rows, "ATTRIBUTES")
            ext = {"byteStride": rows.shape[1], "count": len(values), "mode": "ATTRIBUTES", "filter": "EXPONENTIAL"}  # fmt: skip
        else:
            encoded = meshopt.encode_gltf_buffer(values, "ATTRIBUTES")
            ext = {"byteStride": values.nbytes // len(values), "count": len(values), "mode": "ATTRIBUTES"}  # fmt: skip
        ext.update(buffer=0, byteOffset=out.add(encoded), byteLength=len(encoded))
        view.update(buffer=1, byteOffset=fallback, extensions={"EXT_meshopt_compression": ext})
        fallback += view["byteLength"] + (-view["byteLength"]) % 4
    body = out.bytes()
    doc["buffers"] = [
        {"byteLength": len(body)},
        {"byteLength": fallback, "extensions": {"EXT_meshopt_compression": {"fallback": True}}},
    ]
    _require(doc, "EXT_meshopt_compression")
    return pack_glb(doc, body)


def _replace(
    doc: dict[str, Any], out: _Blob, index: int, values: np.ndarray, **fields: Any
) -> None:
    """Accessor ``index`` now holds ``values`` (its own new view), with ``fields`` set."""
    doc["bufferViews"].append({"buffer": 0, "byteOffset": out.add(values.tobytes()), "byteLength": values.nbytes})  # fmt: skip
    acc = doc["accessors"][index]
    acc.update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=0, **fields)


def _rebuilt(doc: dict[str, Any], blob: bytes, keep: set[int]) -> tuple[_Blob, dict[int, int]]:
    """A new blob holding the views ``keep`` (renumbered: old -> new); other views dropped."""
    out = _Blob()
    views, numbers = [], {}
    for number, view in enumerate(doc["bufferViews"]):
        if number in keep:
            data = blob[view.get("byteOffset", 0) : view.get("byteOffset", 0) + view["byteLength"]]
            numbers[number] = len(views)
            views.append({**view, "byteOffset": out.add(data)})
    doc["bufferViews"] = views
    for acc in doc["accessors"]:
        if "bufferView" in acc:
            acc["bufferView"] = numbers.get(acc["bufferView"], -1)
    for image in doc.get("images", []):
        image["bufferView"] = numbers[image["bufferView"]]
    return out, numbers


def _quantized(doc: dict[str, Any], blob: bytes) -> bytes:
    original = copy.deepcopy(doc)
    _, targets = _uses(doc)
    positions = {p["attributes"]["POSITION"] for m in doc["meshes"] for p in m["primitives"]}
    normals = {p["attributes"]["NORMAL"] for m in doc["meshes"] for p in m["primitives"]}
    uvs = {
        p["attributes"]["TEXCOORD_0"]
        for m in doc["meshes"]
        for p in m["primitives"]
        if "TEXCOORD_0" in p["attributes"]
    }
    everything = np.concatenate([_array(original, blob, i) for i in positions])
    low, high = everything.min(axis=0), everything.max(axis=0)
    offset = (low + high) / 2
    scale = float((high - low).max() / 65000)  # one scale for the file: int16 covers it
    changed = positions | targets | normals | uvs
    keep = {acc["bufferView"] for i, acc in enumerate(doc["accessors"]) if i not in changed}
    keep |= {image["bufferView"] for image in doc.get("images", [])}
    out, _ = _rebuilt(doc, blob, keep)
    for i in positions:
        q = np.round((_array(original, blob, i) - offset) / scale).astype(np.int16)
        _replace(doc, out, i, q, componentType=5122, normalized=False,
                 min=q.min(axis=0).tolist(), max=q.max(axis=0).tolist())  # fmt: skip
    for i in targets:
        q = np.round(_array(original, blob, i) / scale).astype(np.int16)
        _replace(doc, out, i, q, componentType=5122, normalized=False,
                 min=q.min(axis=0).tolist(), max=q.max(axis=0).tolist())  # fmt: skip
    for i in normals:
        q = np.round(np.clip(_array(original, blob, i), -1, 1) * 127).astype(np.int8)
        q = np.concatenate([q, np.zeros((len(q), 1), np.int8)], axis=1)  # rows of 4 bytes
        doc["bufferViews"].append({"buffer": 0, "byteOffset": out.add(q.tobytes()), "byteLength": q.nbytes, "byteStride": 4})  # fmt: skip
        doc["accessors"][i].update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=0, componentType=5120, normalized=True)  # fmt: skip
        doc["accessors"][i].pop("min", None), doc["accessors"][i].pop("max", None)
    for i in uvs:
        q = np.round(np.clip(_array(original, blob, i), 0, 1) * 65535).astype(np.uint16)
        _replace(doc, out, i, q, componentType=5123, normalized=True)
    # Dequantisation: mesh space = offset + scale * stored; a skinned mesh's node transform
    # is ignored, so it goes into every inverse bind matrix (column-major in glTF).
    dequantise = np.eye(4)
    dequantise[:3, :3] *= scale
    dequantise[:3, 3] = offset
    for skin in doc.get("skins", []):
        index = skin["inverseBindMatrices"]
        matrices = _array(original, blob, index).reshape(-1, 4, 4).transpose(0, 2, 1)
        folded = (matrices @ dequantise).transpose(0, 2, 1).reshape(-1, 16).astype(np.float32)
        doc["bufferViews"].append({"buffer": 0, "byteOffset": out.add(folded.tobytes()), "byteLength": folded.nbytes})  # fmt: skip
        doc["accessors"][index]["bufferView"] = len(doc["bufferViews"]) - 1
    body = out.bytes()
    doc["buffers"] = [{"byteLength": len(body)}]
    _require(doc, "KHR_mesh_quantization")
    return pack_glb(doc, body)


def _draco(doc: dict[str, Any], blob: bytes) -> bytes:
    original = copy.deepcopy(doc)
    compressed: set[int] = set()
    encoded: list[tuple[dict[str, Any], bytes]] = []
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            attributes = prim["attributes"]
            points = _array(original, blob, attributes["POSITION"])
            faces = _array(original, blob, prim["indices"]).reshape(-1, 3)
            kw = {}
            if "NORMAL" in attributes:
                kw["normals"] = _array(original, blob, attributes["NORMAL"]).astype(np.float64)
            if "TEXCOORD_0" in attributes:
                kw["tex_coord"] = _array(original, blob, attributes["TEXCOORD_0"]).astype(
                    np.float64
                )
            data = DracoPy.encode(
                points, faces, quantization_bits=16, preserve_order=True, compression_level=7, **kw
            )
            decoded = DracoPy.decode(data)
            ids = {a["attribute_type"]: a["unique_id"] for a in decoded.attributes}
            names = {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 3}
            draco_ids = {n: ids[t] for n, t in names.items() if n in attributes and t in ids}
            assert decoded.points.shape == points.shape, "Draco kept every vertex in order"
            for name in draco_ids:
                compressed.add(attributes[name])
            compressed.add(prim["indices"])
            encoded.append((prim, data))
            prim.setdefault("extensions", {})["KHR_draco_mesh_compression"] = {
                "attributes": draco_ids
            }
    keep = {acc["bufferView"] for i, acc in enumerate(doc["accessors"]) if i not in compressed} | {
        image["bufferView"] for image in doc.get("images", [])
    }
    out, _ = _rebuilt(doc, blob, keep)
    for i in compressed:
        acc = doc["accessors"][i]
        acc.pop("bufferView", None), acc.pop("byteOffset", None)
    for prim, data in encoded:
        doc["bufferViews"].append({"buffer": 0, "byteOffset": out.add(data), "byteLength": len(data)})  # fmt: skip
        prim["extensions"]["KHR_draco_mesh_compression"]["bufferView"] = len(doc["bufferViews"]) - 1
    body = out.bytes()
    doc["buffers"] = [{"byteLength": len(body)}]
    _require(doc, "KHR_draco_mesh_compression")
    return pack_glb(doc, body)


def compressed(glb: bytes, kind: str) -> bytes:
    """``glb`` (a pygltflib GLB, one accessor a view) rewritten as ``kind`` of ``KINDS``."""
    doc, blob = split_glb(glb)
    make = {"meshopt": _meshopt, "quantized": _quantized, "draco": _draco}[kind]
    return make(doc, blob)


def gltfpack(glb: bytes) -> bytes:
    """``glb`` through ``gltfpack -cc`` (meshopt over quantisation)."""
    with tempfile.TemporaryDirectory(prefix="gltfpack-") as folder:
        source, packed = Path(folder) / "in.glb", Path(folder) / "out.glb"
        source.write_bytes(glb)
        subprocess.run(
            ["node", str(GLTFPACK), "-i", str(source), "-o", str(packed), "-cc"],
            check=True, capture_output=True, timeout=300,
        )  # fmt: skip
        return packed.read_bytes()

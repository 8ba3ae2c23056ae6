"""glTF 2.0 binary (GLB) export of a blend-shape rig: one mesh, one morph target per example.

Each example that moves something becomes a morph target with POSITION and NORMAL offsets,
plus an optional weights animation; ``pack_glb`` frames a document and its blob as GLB. It
does no reading (gltf_read.py), fitting or blending.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .gltf_read import TRIANGLES, TYPE_SIZES

__all__ = ["export_glb", "pack_glb", "vertex_normals"]

_GLB_MAGIC = 0x46546C67  # b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT = 5126
_UNSIGNED_INT = 5125


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    (V, 3) float32
        Unit normals; vertices on no (or only degenerate) triangles get +y, because
        glTF requires every NORMAL to have unit length.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    # The cross product's length is twice the triangle area: summing it weights by area.
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    corners = faces.reshape(-1)
    normals = np.empty_like(v)
    for axis in range(3):
        # Each face's normal goes to its three corners (bincount sums repeated indices).
        normals[:, axis] = np.bincount(
            corners, weights=np.repeat(face_normals[:, axis], 3), minlength=v.shape[0]
        )
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-20
    normals[ok] /= length[ok, None]
    normals[~ok] = (0.0, 1.0, 0.0)
    return normals.astype(np.float32)


def _sanitize_export(
    neutral: npt.ArrayLike,
    faces: npt.ArrayLike,
    deltas: npt.ArrayLike,
    names: Sequence[str],
    weights: npt.ArrayLike | None,
    fps: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str], np.ndarray | None, float]:
    """``export_glb``'s arguments as checked arrays, in the same order."""
    base = np.asarray(neutral, dtype=np.float64)
    if base.ndim != 2 or base.shape[1] != 3 or base.shape[0] < 1:
        raise InputError(f"export_glb: expected neutral of shape (V, 3), got {base.shape}")
    v = base.shape[0]
    tri = np.asarray(faces)
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] < 1:
        raise InputError(f"export_glb: expected faces of shape (F, 3), got {tri.shape}")
    if not np.issubdtype(tri.dtype, np.integer):
        raise InputError(f"export_glb: faces must be integers, got {tri.dtype}")
    if tri.min() < 0 or tri.max() >= v:
        raise InputError(f"export_glb: face indices must lie in [0, {v})")
    offsets = np.asarray(deltas, dtype=np.float64)
    if offsets.ndim == 2 and offsets.shape[1] == 3 * v:
        offsets = offsets.reshape(offsets.shape[0], v, 3)
    if offsets.ndim != 3 or offsets.shape[1:] != (v, 3):
        raise InputError(f"export_glb: expected deltas of shape (M, {v}, 3), got {offsets.shape}")
    m = offsets.shape[0]
    labels = [str(n) for n in names]
    if len(labels) != m:
        raise InputError(f"export_glb: {len(labels)} names for {m} morph targets")
    if not (np.isfinite(base).all() and np.isfinite(offsets).all()):
        raise InputError("export_glb: NaN or Inf in neutral or deltas")
    rate = float(fps)
    if not (np.isfinite(rate) and rate > 0):
        raise InputError(f"export_glb: fps must be positive, got {rate}")
    frames = None
    if weights is not None:
        frames = np.asarray(weights, dtype=np.float64)
        if frames.ndim != 2 or frames.shape[1] != m or frames.shape[0] < 1:
            raise InputError(f"export_glb: expected weights of shape (F, {m}), got {frames.shape}")
        if not np.isfinite(frames).all():
            raise InputError("export_glb: NaN or Inf in weights")
    return base, tri.astype(np.uint32), offsets, labels, frames, rate


class _BlobWriter:
    """Appends 4-byte-aligned buffer views and their accessors to a glTF document."""

    def __init__(self, doc: dict[str, Any]) -> None:
        self.doc = doc
        self.parts: list[bytes] = []
        self.size = 0

    def add(self, array: np.ndarray, *, type_: str, target: int | None, minmax: bool) -> int:
        data = np.ascontiguousarray(array)
        raw = data.tobytes()
        view: dict[str, int] = {"buffer": 0, "byteOffset": self.size, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.parts.append(raw)
        self.size += len(raw)
        pad = (-self.size) % 4
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        self.doc["bufferViews"].append(view)
        component = _FLOAT if data.dtype == np.float32 else _UNSIGNED_INT
        count = data.size // TYPE_SIZES[type_]
        accessor: dict[str, Any] = {
            "bufferView": len(self.doc["bufferViews"]) - 1,
            "componentType": component,
            "count": int(count),
            "type": type_,
        }
        if minmax:
            cols = data.reshape(accessor["count"], -1)
            accessor["min"] = [float(x) for x in cols.min(axis=0)]
            accessor["max"] = [float(x) for x in cols.max(axis=0)]
        self.doc["accessors"].append(accessor)
        return len(self.doc["accessors"]) - 1

    def blob(self) -> bytes:
        return b"".join(self.parts)


def export_glb(
    neutral: npt.ArrayLike,
    faces: npt.ArrayLike,
    deltas: npt.ArrayLike,
    names: Sequence[str],
    *,
    weights: npt.ArrayLike | None = None,
    fps: float = 60.0,
    normals: bool = True,
) -> bytes:
    """Encode a target mesh and its examples as a GLB with morph targets.

    Parameters
    ----------
    neutral : (V, 3) float
        Target neutral vertices (the base mesh).
    faces : (F, 3) int
        Triangles, 0-based.
    deltas : (M, V, 3) or (M, 3V) float
        Per-example vertex offsets from the neutral. Examples whose offsets are all zero
        (a rig's neutral, weight 0) are left out: such a target moves nothing, and its
        animation track would only cost loaders and players. The others are written in
        order, so weight column i is the target named ``names[i]``.
    names : sequence of M str
        Example names; those of the targets written go to ``mesh.extras.targetNames``.
    weights : (F_frames, M) float, optional
        Per-frame weights, written (the columns of the written targets) as an animation
        with a LINEAR sampler over t = frame / fps targeting the node's ``weights``.
    fps : float
    normals : bool
        Write NORMAL computed from the neutral, and on each morph target the NORMAL
        offsets to that example's own normals, so shading follows the expression.

    Returns
    -------
    bytes
        A glTF 2.0 binary file.
    """
    base, tri, offsets, labels, frames, rate = _sanitize_export(
        neutral, faces, deltas, names, weights, fps
    )
    # Targets that move nothing (exact zeros: a rig's neutral row) are not written.
    kept = np.flatnonzero(np.abs(offsets).reshape(offsets.shape[0], -1).max(axis=1, initial=0) > 0)
    kept_names = [labels[int(i)] for i in kept]
    m = len(kept_names)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "facecast"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "face"}],
        "accessors": [],
        "bufferViews": [],
    }
    writer = _BlobWriter(doc)
    indices = writer.add(
        tri.reshape(-1), type_="SCALAR", target=_ELEMENT_ARRAY_BUFFER, minmax=False
    )
    attributes = {
        "POSITION": writer.add(
            base.astype(np.float32), type_="VEC3", target=_ARRAY_BUFFER, minmax=True
        )
    }
    int_faces = tri.astype(np.int64)
    if normals:
        base_normals = vertex_normals(base, int_faces)
        attributes["NORMAL"] = writer.add(
            base_normals, type_="VEC3", target=_ARRAY_BUFFER, minmax=False
        )
    targets = []
    for i in kept:
        target = {
            "POSITION": writer.add(
                offsets[i].astype(np.float32), type_="VEC3", target=_ARRAY_BUFFER, minmax=True
            )
        }
        if normals:
            # glTF blends normal offsets with the same weights as positions (and the player
            # renormalises), so a weight of 1 shades as the example's own normals.
            posed = vertex_normals(base + offsets[i], int_faces)
            target["NORMAL"] = writer.add(
                posed - base_normals, type_="VEC3", target=_ARRAY_BUFFER, minmax=False
            )
        targets.append(target)
    primitive: dict[str, Any] = {"attributes": attributes, "indices": indices, "mode": TRIANGLES}
    mesh: dict[str, Any] = {
        "name": "face",
        "primitives": [primitive],
        "extras": {"targetNames": kept_names},
    }
    if m:  # glTF wants at least one target where there is a targets array
        primitive["targets"] = targets
        mesh["weights"] = [0.0] * m
    doc["meshes"] = [mesh]
    if frames is not None and m:
        kept_weights = frames[:, kept]
        times = (np.arange(kept_weights.shape[0], dtype=np.float64) / rate).astype(np.float32)
        t_in = writer.add(times, type_="SCALAR", target=None, minmax=True)
        w_out = writer.add(
            kept_weights.astype(np.float32).reshape(-1), type_="SCALAR", target=None, minmax=False
        )
        doc["animations"] = [
            {
                "name": "clone",
                "samplers": [{"input": t_in, "output": w_out, "interpolation": "LINEAR"}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
            }
        ]
    blob = writer.blob()
    doc["buffers"] = [{"byteLength": len(blob)}]
    return pack_glb(doc, blob)


def pack_glb(doc: dict[str, Any], blob: bytes) -> bytes:
    json_bytes = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * ((-len(json_bytes)) % 4)
    blob += b"\0" * ((-len(blob)) % 4)
    total = 12 + 8 + len(json_bytes) + 8 + len(blob)
    return b"".join(
        [
            struct.pack("<III", _GLB_MAGIC, 2, total),
            struct.pack("<II", len(json_bytes), _CHUNK_JSON),
            json_bytes,
            struct.pack("<II", len(blob), _CHUNK_BIN),
            blob,
        ]
    )

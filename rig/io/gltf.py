"""glTF 2.0 binary (GLB) export of a blend-shape rig and import of a mesh's morph targets.

Writes one mesh with one morph target per example that moves something (plus an optional
weights animation), each target with POSITION and NORMAL offsets, and reads morph targets
back for the example-set loader; it does no fitting or blending.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pygltflib

from ..errors import ExampleSetError, InputError

__all__ = [
    "BufferReader",
    "export_glb",
    "load_document",
    "pack_glb",
    "read_glb_morph_targets",
    "read_gltf_mesh",
    "read_mesh",
    "target_names",
]

_GLB_MAGIC = 0x46546C67  # b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT = 5126
_UNSIGNED_INT = 5125
_TRIANGLES = 4

_COMPONENT_DTYPES = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
# Largest array (in values) the reader will allocate: ~20x the ICT head's 57 targets, so a
# corrupted count cannot make it ask for terabytes.
MAX_VALUES = 100_000_000
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


# -- export ----------------------------------------------------------------------------


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
        count = data.size // _TYPE_SIZES[type_]
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
    primitive: dict[str, Any] = {"attributes": attributes, "indices": indices, "mode": _TRIANGLES}
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


# -- import ----------------------------------------------------------------------------


#: What the reader takes: a file's path or its bytes.
GltfSource = str | os.PathLike[str] | bytes | bytearray | memoryview


def load_document(path_or_bytes: GltfSource, label: str) -> pygltflib.GLTF2:
    if isinstance(path_or_bytes, bytes | bytearray | memoryview):
        data = bytes(path_or_bytes)
    else:
        try:
            data = Path(path_or_bytes).read_bytes()
        except FileNotFoundError:
            raise ExampleSetError(f"{label}: file not found", code="missing_file") from None
        except OSError as exc:
            raise ExampleSetError(f"{label}: cannot read ({exc})", code="missing_file") from None
    if data[:4] == b"glTF" and (len(data) < 12 or struct.unpack_from("<I", data, 4)[0] != 2):
        raise ExampleSetError(
            f"{label}: not a glTF 2.0 binary (GLB version is not 2)", code="bad_gltf"
        )
    try:
        if data[:4] == b"glTF":
            gltf = pygltflib.GLTF2.load_from_bytes(data)
        else:
            gltf = pygltflib.GLTF2.from_json(data.decode("utf-8"))
    except Exception as exc:  # the parser raises many unrelated types on garbage input
        raise ExampleSetError(
            f"{label}: not a readable glTF/GLB file ({type(exc).__name__}: {exc})",
            code="bad_gltf",
        ) from None
    if gltf is None:
        raise ExampleSetError(f"{label}: not a readable glTF/GLB file", code="bad_gltf")
    return gltf


class BufferReader:
    def __init__(self, gltf: pygltflib.GLTF2, base: Path | None, label: str) -> None:
        self.gltf = gltf
        self.base = base
        self.label = label
        self.cache: dict[int, bytes] = {}

    def buffer(self, index: int) -> bytes:
        if index in self.cache:
            return self.cache[index]
        try:
            buf = self.gltf.buffers[index]
        except (IndexError, TypeError):
            raise ExampleSetError(
                f"{self.label}: buffer {index} does not exist", code="bad_gltf"
            ) from None
        uri = buf.uri
        data: bytes | None
        if uri is None:
            data = self.gltf.binary_blob()
            if data is None:
                raise ExampleSetError(f"{self.label}: GLB has no binary chunk", code="bad_gltf")
        elif uri.startswith("data:"):
            try:
                data = base64.b64decode(uri.split(",", 1)[1])
            except (IndexError, ValueError):
                raise ExampleSetError(
                    f"{self.label}: bad data URI in buffer {index}", code="bad_gltf"
                ) from None
        else:
            if self.base is None:
                raise ExampleSetError(
                    f"{self.label}: buffer {index} refers to external file {uri!r}", code="bad_gltf"
                )
            file = (self.base / uri).resolve()
            if not file.is_relative_to(self.base.resolve()):
                raise ExampleSetError(
                    f"{self.label}: buffer uri {uri!r} escapes the folder", code="path_escape"
                )
            try:
                data = file.read_bytes()
            except OSError as exc:
                raise ExampleSetError(
                    f"{self.label}: cannot read buffer {uri!r} ({exc})", code="missing_file"
                ) from None
        self.cache[index] = data
        return data

    def _view(
        self, view_index: int, offset: int, count: int, dtype: npt.DTypeLike, ncomp: int
    ) -> np.ndarray:
        view = self.gltf.bufferViews[view_index]
        data = self.buffer(view.buffer)
        itemsize = np.dtype(dtype).itemsize
        stride = view.byteStride or itemsize * ncomp
        start = (view.byteOffset or 0) + offset
        need = stride * (count - 1) + itemsize * ncomp if count else 0
        if start + need > min(len(data), (view.byteOffset or 0) + view.byteLength):
            raise ExampleSetError(
                f"{self.label}: accessor runs past its buffer view", code="bad_gltf"
            )
        return np.ndarray(
            (count, ncomp), dtype=dtype, buffer=data, offset=start, strides=(stride, itemsize)
        ).copy()

    def accessor(self, index: int) -> np.ndarray:
        """Decode accessor ``index`` into a (count, ncomp) array (float64 or int64)."""
        try:
            acc = self.gltf.accessors[index]
            dtype = _COMPONENT_DTYPES[acc.componentType]
            ncomp = _TYPE_SIZES[acc.type]
            count = int(acc.count)
            if count < 0 or count * ncomp > MAX_VALUES:
                raise ExampleSetError(
                    f"{self.label}: accessor {index} count {count} is out of bounds",
                    code="bad_gltf",
                )
            if acc.bufferView is None:
                out = np.zeros((count, ncomp), dtype=dtype)
            else:
                out = self._view(acc.bufferView, acc.byteOffset or 0, count, dtype, ncomp)
            if acc.sparse is not None:
                sp = acc.sparse
                idx_dtype = _COMPONENT_DTYPES[sp.indices.componentType]
                where = self._view(
                    sp.indices.bufferView, sp.indices.byteOffset or 0, sp.count, idx_dtype, 1
                )[:, 0]
                values = self._view(
                    sp.values.bufferView, sp.values.byteOffset or 0, sp.count, dtype, ncomp
                )
                if where.size and where.max() >= count:
                    raise ExampleSetError(
                        f"{self.label}: sparse index out of range", code="bad_gltf"
                    )
                out[where.astype(np.int64)] = values
        except ExampleSetError:
            raise
        except (IndexError, KeyError, TypeError, AttributeError, ValueError) as exc:
            raise ExampleSetError(
                f"{self.label}: malformed accessor {index} ({type(exc).__name__}: {exc})",
                code="bad_gltf",
            ) from None
        if np.issubdtype(dtype, np.floating):
            return out.astype(np.float64)
        if acc.normalized:
            # glTF 2.0 §3.11: normalized integers map to [0, 1] or [-1, 1].
            info = np.iinfo(out.dtype)
            return np.maximum(out.astype(np.float64) / info.max, -1.0)
        return out.astype(np.int64)


def read_glb_morph_targets(
    path_or_bytes: GltfSource,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Read the first mesh that has morph targets from a glTF/GLB file.

    All triangle primitives of that mesh are concatenated (primitives that share one
    POSITION accessor share its vertices). Node transforms are not applied: vertices
    are in the mesh's own space.

    Parameters
    ----------
    path_or_bytes : path or bytes
        A ``.glb``/``.gltf`` file, or its bytes.

    Returns
    -------
    neutral : (V, 3) float64
    faces : (F, 3) int64
    deltas : (M', V, 3) float64
        POSITION offsets of each morph target.
    names : list of M' str
        From ``mesh.extras.targetNames`` (or the first primitive's extras); unnamed
        targets are called ``target_<i>``.

    Raises
    ------
    ExampleSetError
        Unreadable file, no mesh with morph targets, non-triangle primitives, or
        primitives that disagree on the number of targets.
    """
    return _read_chosen_mesh(path_or_bytes, _morph_mesh)


def read_gltf_mesh(path_or_bytes: GltfSource) -> tuple[np.ndarray, np.ndarray]:
    """The neutral of a glTF/GLB/VRM file's face: its first mesh with morph targets, else its
    first mesh, as (V, 3) float64 vertices and (F, 3) int64 triangles (mesh space).

    Raises
    ------
    ExampleSetError
        As ``read_glb_morph_targets``; ``no_mesh`` for a file without meshes.
    """
    neutral, faces, _, _ = _read_chosen_mesh(path_or_bytes, _face_mesh)
    return neutral, faces


def _read_chosen_mesh(
    path_or_bytes: GltfSource, choose: Callable[[pygltflib.GLTF2, str], pygltflib.Mesh]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The mesh ``choose(gltf, label)`` picks, read as ``read_mesh`` reads it."""
    is_bytes = isinstance(path_or_bytes, bytes | bytearray | memoryview)
    label = "<glTF bytes>" if is_bytes else str(path_or_bytes)
    gltf = load_document(path_or_bytes, label)
    base = (
        None
        if isinstance(path_or_bytes, bytes | bytearray | memoryview)
        else Path(path_or_bytes).parent
    )
    reader = BufferReader(gltf, base, label)
    try:
        return read_mesh(choose(gltf, label), reader, label)
    except ExampleSetError:
        raise
    except (AttributeError, TypeError, KeyError, IndexError, ValueError) as exc:
        # dataclasses-json leaves wrongly typed JSON fields as they are; say so, don't crash.
        raise ExampleSetError(
            f"{label}: malformed glTF ({type(exc).__name__}: {exc})", code="bad_gltf"
        ) from None


def _morph_mesh(gltf: pygltflib.GLTF2, label: str) -> pygltflib.Mesh:
    mesh = next((m for m in gltf.meshes or [] if any(p.targets for p in m.primitives or [])), None)
    if mesh is None:
        raise ExampleSetError(f"{label}: no mesh with morph targets", code="no_morph_targets")
    return mesh


def _face_mesh(gltf: pygltflib.GLTF2, label: str) -> pygltflib.Mesh:
    meshes = [m for m in gltf.meshes or [] if m.primitives]
    if not meshes:
        raise ExampleSetError(f"{label}: holds no mesh", code="no_mesh")
    return next((m for m in meshes if any(p.targets for p in m.primitives)), meshes[0])


def read_mesh(
    mesh: pygltflib.Mesh, reader: BufferReader, label: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """All triangle primitives of ``mesh`` concatenated, with its morph targets (maybe 0)."""
    num_targets = {len(p.targets or []) for p in mesh.primitives}
    if len(num_targets) != 1:
        raise ExampleSetError(
            f"{label}: primitives of mesh {mesh.name!r} have different numbers of morph targets",
            code="bad_gltf",
        )
    m = num_targets.pop()

    positions: list[np.ndarray] = []
    deltas: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    first_vertex: dict[int, int] = {}
    vertex_count: dict[int, int] = {}
    total = 0
    for number, prim in enumerate(mesh.primitives):
        mode = _TRIANGLES if prim.mode is None else prim.mode
        if mode != _TRIANGLES:
            raise ExampleSetError(
                f"{label}: primitive {number} has mode {mode}; only triangles (4) are supported",
                code="bad_gltf",
            )
        pos_index = prim.attributes.POSITION
        if pos_index is None:
            raise ExampleSetError(f"{label}: primitive {number} has no POSITION", code="bad_gltf")
        if pos_index not in first_vertex:
            pos = reader.accessor(pos_index)
            if pos.shape[1] != 3:
                raise ExampleSetError(f"{label}: POSITION is not VEC3", code="bad_gltf")
            first_vertex[pos_index] = total
            vertex_count[pos_index] = pos.shape[0]
            total += pos.shape[0]
            positions.append(pos)
            if m * total * 3 > MAX_VALUES:
                raise ExampleSetError(
                    f"{label}: {m} morph targets of {total} vertices exceed the reader's limit "
                    f"of {MAX_VALUES} values",
                    code="too_large",
                )
            prim_deltas = np.zeros((m, pos.shape[0], 3))
            for t, target in enumerate(prim.targets or []):
                t_pos = target.POSITION if hasattr(target, "POSITION") else target.get("POSITION")
                if t_pos is not None:
                    d = reader.accessor(t_pos)
                    if d.shape != pos.shape:
                        raise ExampleSetError(
                            f"{label}: morph target {t} has {d.shape[0]} vertices, "
                            f"the mesh has {pos.shape[0]}",
                            code="bad_gltf",
                        )
                    prim_deltas[t] = d
            deltas.append(prim_deltas)
        if prim.indices is None:
            tri = np.arange(vertex_count[pos_index], dtype=np.int64)
        else:
            tri = reader.accessor(prim.indices)[:, 0]
        if tri.size % 3:
            raise ExampleSetError(
                f"{label}: primitive {number} index count is not a multiple of 3", code="bad_gltf"
            )
        if tri.size and (tri.min() < 0 or tri.max() >= vertex_count[pos_index]):
            raise ExampleSetError(
                f"{label}: primitive {number} has triangle indices out of range", code="bad_gltf"
            )
        faces.append(tri.reshape(-1, 3) + first_vertex[pos_index])

    neutral = np.concatenate(positions)
    all_faces = np.concatenate(faces)
    names = target_names(mesh, m)
    return neutral, all_faces, np.concatenate(deltas, axis=1), names


def target_names(mesh: pygltflib.Mesh, m: int) -> list[str]:
    for extras in (mesh.extras, mesh.primitives[0].extras):
        if isinstance(extras, dict) and isinstance(extras.get("targetNames"), list):
            names = extras["targetNames"]
            if len(names) == m and all(isinstance(n, str) and n for n in names):
                return list(names)
    return [f"target_{i}" for i in range(m)]

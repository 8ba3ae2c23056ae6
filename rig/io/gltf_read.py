"""Reading glTF 2.0 (JSON or GLB): a document, its buffers, and a mesh with its morph targets.

Bounded reading of untrusted files: every accessor is checked against its buffer and
MAX_VALUES before an array is made, compressed views and primitives (meshopt, Draco:
gltf_compression.py) against MAX_DECODED_BYTES and their accessors before they are decoded;
quantised attributes (KHR_mesh_quantization) are read as stored. Errors are
``ExampleSetError`` with a code. It does no writing (gltf_export.py), fitting or blending.
"""

from __future__ import annotations

import base64
import os
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pygltflib

from ..errors import ExampleSetError
from .gltf_compression import (
    DracoGeometry,
    decode_draco,
    decode_meshopt_view,
    draco_extension,
    meshopt_extension,
)

__all__ = [
    "MAX_DECODED_BYTES",
    "MAX_VALUES",
    "TRIANGLES",
    "TYPE_SIZES",
    "BufferReader",
    "GltfSource",
    "load_document",
    "read_glb_morph_targets",
    "read_gltf_mesh",
    "read_mesh",
    "target_names",
]

TRIANGLES = 4

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
#: Most bytes one read decodes out of compressed views (meshopt): MAX_VALUES float32 values.
#: Each view's declared size is checked against what is left before it is decoded.
MAX_DECODED_BYTES = 4 * MAX_VALUES
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


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
        self.decoded: dict[int, bytes] = {}
        self.decoded_left = MAX_DECODED_BYTES
        self.draco: dict[int, DracoGeometry] = {}

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
        if uri is None and index != 0:
            # A meshopt fallback buffer, say: only a GLB's first buffer is its BIN chunk.
            raise ExampleSetError(
                f"{self.label}: buffer {index} has no bytes (no uri, and only buffer 0 is a "
                "GLB's binary chunk)",
                code="bad_gltf",
            )
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
        itemsize = np.dtype(dtype).itemsize
        stride = view.byteStride or itemsize * ncomp
        need = stride * (count - 1) + itemsize * ncomp if count else 0
        if meshopt_extension(view) is not None:
            data, start, end = self.view_bytes(view_index), offset, view.byteLength
        else:
            data = self.buffer(view.buffer)
            start = (view.byteOffset or 0) + offset
            end = (view.byteOffset or 0) + view.byteLength
        if start + need > min(len(data), end):
            raise ExampleSetError(
                f"{self.label}: accessor runs past its buffer view", code="bad_gltf"
            )
        return np.ndarray(
            (count, ncomp), dtype=dtype, buffer=data, offset=start, strides=(stride, itemsize)
        ).copy()

    def view_bytes(self, view_index: int) -> bytes:
        """A meshopt-compressed view's bytes, decoded once (bounded by ``decoded_left``)."""
        if view_index not in self.decoded:
            view = self.gltf.bufferViews[view_index]
            ext = meshopt_extension(view)
            assert ext is not None
            if view.byteStride is not None and view.byteStride != ext.get("byteStride"):
                raise ExampleSetError(
                    f"{self.label}: bufferView {view_index} byteStride {view.byteStride} is "
                    f"not its meshopt byteStride {ext.get('byteStride')}",
                    code="bad_compression",
                )
            data = decode_meshopt_view(
                ext, int(view.byteLength), self.buffer, self.decoded_left, self.label
            )
            self.decoded_left -= len(data)
            self.decoded[view_index] = data
        return self.decoded[view_index]

    def draco_geometry(self, primitive: pygltflib.Primitive) -> DracoGeometry | None:
        """A Draco primitive's (positions, triangle corners), decoded once; None if the
        primitive is not Draco-compressed. Its accessors' counts are bounded first."""
        ext = draco_extension(primitive)
        if ext is None:
            return None
        view_index = ext.get("bufferView")
        attributes = ext.get("attributes")
        if not isinstance(view_index, int) or not isinstance(attributes, dict):
            raise ExampleSetError(
                f"{self.label}: a Draco primitive names no bufferView or attributes",
                code="bad_compression",
            )
        if view_index not in self.draco:
            position_id = attributes.get("POSITION")
            if not isinstance(position_id, int) or primitive.attributes.POSITION is None:
                raise ExampleSetError(
                    f"{self.label}: a Draco primitive without POSITION", code="bad_compression"
                )
            vertices = self._declared(primitive.attributes.POSITION, 3)
            corners = None if primitive.indices is None else self._declared(primitive.indices, 1)
            view = self.gltf.bufferViews[view_index]
            data = self.buffer(view.buffer)
            start = view.byteOffset or 0
            if start + view.byteLength > len(data):
                raise ExampleSetError(
                    f"{self.label}: a Draco primitive's view runs past its buffer",
                    code="bad_compression",
                )
            self.draco[view_index] = decode_draco(
                data[start : start + view.byteLength], position_id, vertices, corners, self.label
            )
        return self.draco[view_index]

    def _declared(self, index: int, ncomp: int) -> int:
        """Accessor ``index``'s count, checked against MAX_VALUES (before any decoding)."""
        count = int(self.gltf.accessors[index].count)
        if count < 0 or count * ncomp > MAX_VALUES:
            raise ExampleSetError(
                f"{self.label}: accessor {index} count {count} is out of bounds", code="bad_gltf"
            )
        return count

    def decode_all(self) -> None:
        """Decode every compressed view and primitive of the file (each bounded), so that a
        part that does not decode is found now, not by a viewer."""
        for index, view in enumerate(self.gltf.bufferViews or []):
            if meshopt_extension(view) is not None:
                self.view_bytes(index)
        for mesh in self.gltf.meshes or []:
            for primitive in mesh.primitives or []:
                self.draco_geometry(primitive)

    def accessor(self, index: int) -> np.ndarray:
        """Decode accessor ``index`` into a (count, ncomp) array (float64 or int64)."""
        try:
            acc = self.gltf.accessors[index]
            dtype = _COMPONENT_DTYPES[acc.componentType]
            ncomp = TYPE_SIZES[acc.type]
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
        mode = TRIANGLES if prim.mode is None else prim.mode
        if mode != TRIANGLES:
            raise ExampleSetError(
                f"{label}: primitive {number} has mode {mode}; only triangles (4) are supported",
                code="bad_gltf",
            )
        pos_index = prim.attributes.POSITION
        if pos_index is None:
            raise ExampleSetError(f"{label}: primitive {number} has no POSITION", code="bad_gltf")
        draco = reader.draco_geometry(prim)
        if pos_index not in first_vertex:
            # Quantised positions (KHR_mesh_quantization) come as integers: as floats here.
            pos = (reader.accessor(pos_index) if draco is None else draco[0]).astype(np.float64)
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
        elif draco is not None and draco[1] is not None:
            tri = draco[1]
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

"""Reading glTF 2.0 (JSON or GLB): a document, its buffers, and a mesh with its morph targets.

Bounded reading of untrusted files: the document is checked whole first (``gltf_check``:
every count, index and extent against its bytes and ``GltfLimits``), then read as plain
JSON, in time linear in its size; compressed views and primitives (meshopt, Draco:
gltf_compression.py) are checked against ``max_decoded_bytes`` of the limits and their
accessors before they are decoded; quantised attributes (KHR_mesh_quantization) are read as stored. Errors are
``ExampleSetError`` with a code. It does no writing (gltf_export.py), fitting or blending.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ExampleSetError
from ..examples import face_index_dtype
from .gltf_check import (
    TYPE_SIZES,
    Buffer,
    GltfLimits,
    check_document,
    external_uri_error,
    max_decoded_bytes,
    parse_json,
    split_glb,
)
from .gltf_compression import (
    DracoGeometry,
    decode_draco,
    decode_meshopt_view,
    draco_extension,
    meshopt_extension,
)

__all__ = [
    "TRIANGLES",
    "TYPE_SIZES",
    "BufferReader",
    "GltfDocument",
    "GltfLimits",
    "GltfSource",
    "load_document",
    "read_glb_morph_targets",
    "read_gltf_mesh",
    "read_mesh",
    "target_names",
]

TRIANGLES = 4
_FLOAT = 5126

_COMPONENT_DTYPES: dict[int, type[np.generic]] = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}


#: What the reader takes: a file's path or its bytes.
GltfSource = str | os.PathLike[str] | bytes | bytearray | memoryview


@dataclass(frozen=True)
class GltfDocument:
    """A checked glTF document: its JSON and each buffer's bytes (``check_document``)."""

    json: dict[str, Any]
    buffers: list[Buffer]


def load_document(
    path_or_bytes: GltfSource, label: str, limits: GltfLimits | None = None
) -> GltfDocument:
    """Read and check a .glb/.gltf (a .gltf on disk may name buffer files in its folder)."""
    limits = GltfLimits() if limits is None else limits
    folder: Path | None = None
    if isinstance(path_or_bytes, bytes | bytearray | memoryview):
        data = bytes(path_or_bytes)
    else:
        folder = Path(path_or_bytes).parent
        try:
            data = Path(path_or_bytes).read_bytes()
        except FileNotFoundError:
            raise ExampleSetError(f"{label}: file not found", code="missing_file") from None
        except OSError as exc:
            raise ExampleSetError(f"{label}: cannot read ({exc})", code="missing_file") from None
    blob: memoryview | None = None
    if data[:4] == b"glTF":
        text, blob = split_glb(data, label)
    else:
        text = data
    doc = parse_json(text, limits, label)
    resolve = None if folder is None else _folder_reader(folder, label)
    return GltfDocument(doc, check_document(doc, blob, limits, label, resolve=resolve))


def _folder_reader(folder: Path, label: str) -> Callable[[str], bytes]:
    def read(uri: str) -> bytes:
        file = (folder / uri).resolve()
        if not file.is_relative_to(folder.resolve()):
            raise external_uri_error(uri, label, "outside the .gltf's folder")
        try:
            return file.read_bytes()
        except OSError as exc:
            raise ExampleSetError(
                f"{label}: cannot read buffer {uri[:200]!r} ({exc})", code="missing_file"
            ) from None

    return read


class BufferReader:
    """Accessors of a checked document as arrays (every extent was checked before).

    Meshopt views are decoded within ``max_decoded_bytes(limits)`` (the limits the
    document was checked with; their defaults without), each view's declared size
    checked against what is left before it is decoded.
    """

    def __init__(
        self, document: GltfDocument, label: str, limits: GltfLimits | None = None
    ) -> None:
        self.doc = document.json
        self.buffers = document.buffers
        self.label = label
        self.decoded: dict[int, Buffer] = {}
        self.decoded_left = max_decoded_bytes(GltfLimits() if limits is None else limits)
        self.draco: dict[int, DracoGeometry] = {}

    def _view(
        self, view_index: int, offset: int, count: int, dtype: type[np.generic], ncomp: int
    ) -> np.ndarray:
        """The elements as they lie in the file's bytes: a read-only view, not a copy."""
        view = self.doc["bufferViews"][view_index]
        itemsize = np.dtype(dtype).itemsize
        stride = view.get("byteStride") or itemsize * ncomp
        if meshopt_extension(view) is not None:
            data, start = self.view_bytes(view_index), offset
        else:
            data, start = self.buffers[view["buffer"]], view.get("byteOffset", 0) + offset
        return np.ndarray(
            (count, ncomp), dtype=dtype, buffer=data, offset=start, strides=(stride, itemsize)
        )

    def view_bytes(self, view_index: int) -> Buffer:
        """A meshopt-compressed view's bytes, decoded once and kept (bounded by
        ``decoded_left``)."""
        if view_index not in self.decoded:
            data = self._decode(view_index)
            self.decoded_left -= len(data)
            self.decoded[view_index] = data
        return self.decoded[view_index]

    def _decode(self, view_index: int) -> Buffer:
        view = self.doc["bufferViews"][view_index]
        ext = meshopt_extension(view)
        assert ext is not None
        if view.get("byteStride") is not None and view["byteStride"] != ext.get("byteStride"):
            raise ExampleSetError(
                f"{self.label}: bufferView {view_index} byteStride {view['byteStride']} is "
                f"not its meshopt byteStride {ext.get('byteStride')}",
                code="bad_compression",
            )
        return decode_meshopt_view(
            ext, view["byteLength"], self.buffers.__getitem__, self.decoded_left, self.label
        )

    def draco_geometry(
        self, primitive: dict[str, Any], *, keep: bool = True
    ) -> DracoGeometry | None:
        """A Draco primitive's (positions, triangle corners), decoded once and kept (``keep``
        False: decoded, or the kept one, and not kept); None if the primitive is not
        Draco-compressed. Its accessors' counts were bounded by the check."""
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
            if not isinstance(position_id, int):
                raise ExampleSetError(
                    f"{self.label}: a Draco primitive without POSITION", code="bad_compression"
                )
            accessors = self.doc["accessors"]
            vertices = accessors[primitive["attributes"]["POSITION"]]["count"]
            indices = primitive.get("indices")
            corners = None if indices is None else accessors[indices]["count"]
            view = self.doc["bufferViews"][view_index]
            start = view.get("byteOffset", 0)
            data = self.buffers[view["buffer"]][start : start + view["byteLength"]]
            geometry = decode_draco(data, position_id, vertices, corners, self.label)
            if not keep:
                return geometry
            self.draco[view_index] = geometry
        return self.draco[view_index]

    def decode_all(self) -> None:
        """Decode every compressed view and primitive of the file (each bounded), so that a
        part that does not decode is found now, not by a viewer. Each is decoded, checked and
        let go (one at a time): only the meshopt views an accessor is read from
        (``view_bytes``) and the Draco primitives of meshes read (``draco_geometry``, which
        decodes them again) are kept, not the normals, UVs, skins and meshes no fit reads."""
        for index, view in enumerate(self.doc.get("bufferViews", [])):
            if meshopt_extension(view) is not None and index not in self.decoded:
                self._decode(index)
        for mesh in self.doc.get("meshes", []):
            for primitive in mesh["primitives"]:
                self.draco_geometry(primitive, keep=False)

    def accessor(
        self,
        index: int,
        floats: type[np.floating[Any]] = np.float64,
        integers: type[np.signedinteger[Any]] = np.int64,
    ) -> np.ndarray:
        """Decode accessor ``index`` into a (count, ncomp) array: ``integers`` (int64 by
        default; a uint32 index past int32's range read as int32 wraps to a negative one,
        which a range check refuses), or ``floats`` (float32 reads a float32 accessor as
        stored, without a float64 copy)."""
        acc = self.doc["accessors"][index]
        dtype = _COMPONENT_DTYPES[acc["componentType"]]
        ncomp = TYPE_SIZES[acc["type"]]
        count = acc["count"]
        # A view of the file's bytes is copied once, by the conversion to what is returned.
        stored = acc.get("bufferView") is not None
        if stored:
            out = self._view(acc["bufferView"], acc.get("byteOffset", 0), count, dtype, ncomp)
        else:
            out = np.zeros((count, ncomp), dtype=dtype)
        sparse = acc.get("sparse")
        if sparse is not None:
            if stored:
                out, stored = out.copy(), False
            indices, values, n = sparse["indices"], sparse["values"], sparse["count"]
            idx_dtype = _COMPONENT_DTYPES[indices["componentType"]]
            where = self._view(
                indices["bufferView"], indices.get("byteOffset", 0), n, idx_dtype, 1
            )[:, 0]
            found = self._view(values["bufferView"], values.get("byteOffset", 0), n, dtype, ncomp)
            if where.size and where.max() >= count:
                raise ExampleSetError(
                    f"{self.label}: accessor {index} has a sparse index out of range",
                    code="bad_gltf",
                )
            out[where.astype(np.int64)] = found
        if np.issubdtype(dtype, np.floating):
            return out.astype(floats, copy=stored)
        if acc.get("normalized", False):
            # glTF 2.0 §3.11: normalized integers map to [0, 1] or [-1, 1].
            scaled = out.astype(np.float64)
            scaled /= np.iinfo(out.dtype).max
            return np.maximum(scaled, -1.0, out=scaled)
        return out.astype(integers, copy=stored)


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
    faces : (F, 3) int32 (int64 from 2^31 vertices on: ``face_index_dtype``)
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
    neutral, faces, deltas, names = _read_chosen_mesh(path_or_bytes, _morph_mesh)
    return neutral, faces, deltas.astype(np.float64, copy=False), names


def read_gltf_mesh(path_or_bytes: GltfSource) -> tuple[np.ndarray, np.ndarray]:
    """The neutral of a glTF/GLB/VRM file's face: its first mesh with morph targets, else its
    first mesh, as (V, 3) float64 vertices and (F, 3) int32 triangles (mesh space; int64
    from 2^31 vertices on, ``face_index_dtype``).

    Raises
    ------
    ExampleSetError
        As ``read_glb_morph_targets``; ``no_mesh`` for a file without meshes.
    """
    neutral, faces, _, _ = _read_chosen_mesh(path_or_bytes, _face_mesh)
    return neutral, faces


def _read_chosen_mesh(
    path_or_bytes: GltfSource, choose: Callable[[dict[str, Any], str], dict[str, Any]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The mesh ``choose(document, label)`` picks, read as ``read_mesh`` reads it."""
    is_bytes = isinstance(path_or_bytes, bytes | bytearray | memoryview)
    label = "<glTF bytes>" if is_bytes else str(path_or_bytes)
    document = load_document(path_or_bytes, label)
    return read_mesh(choose(document.json, label), BufferReader(document, label), label)


def _has_targets(mesh: dict[str, Any]) -> bool:
    return any(p.get("targets") for p in mesh["primitives"])


def _morph_mesh(doc: dict[str, Any], label: str) -> dict[str, Any]:
    mesh: dict[str, Any] | None = next((m for m in doc.get("meshes", []) if _has_targets(m)), None)
    if mesh is None:
        raise ExampleSetError(f"{label}: no mesh with morph targets", code="no_morph_targets")
    return mesh


def _face_mesh(doc: dict[str, Any], label: str) -> dict[str, Any]:
    meshes: list[dict[str, Any]] = doc.get("meshes", [])
    if not meshes:
        raise ExampleSetError(f"{label}: holds no mesh", code="no_mesh")
    return next((m for m in meshes if _has_targets(m)), meshes[0])


def read_mesh(
    mesh: dict[str, Any], reader: BufferReader, label: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """All triangle primitives of ``mesh`` (a mesh of the checked document ``reader``
    reads) concatenated, with its morph targets (maybe 0).

    Returns
    -------
    neutral : (V, 3) float64
    faces : (F, 3) int32 (int64 from 2^31 vertices on: ``face_index_dtype``)
    deltas : (M, V, 3) float32 when every morph target is stored as float32 (the values
        as stored), else float64
    names : list of M str
    """
    primitives = mesh["primitives"]
    num_targets = {len(p.get("targets", [])) for p in primitives}
    if len(num_targets) != 1:
        raise ExampleSetError(
            f"{label}: primitives of mesh {str(mesh.get('name'))[:200]!r} have different "
            "numbers of morph targets",
            code="bad_gltf",
        )
    m = num_targets.pop()
    accessors = reader.doc["accessors"]
    # The deltas are the largest arrays a character upload makes: one array filled in
    # place (no per-primitive arrays concatenated), float32 when every target is stored
    # so (its values as they are, in half float64's bytes), else float64.
    stored = [
        accessors[target["POSITION"]]["componentType"]
        for prim in primitives
        for target in prim.get("targets", [])
        if target.get("POSITION") is not None
    ]
    dtype = np.float32 if all(kind == _FLOAT for kind in stored) else np.float64
    counts = {p["attributes"]["POSITION"]: accessors[p["attributes"]["POSITION"]]["count"]
              for p in primitives}  # fmt: skip
    all_deltas = np.zeros((m, sum(counts.values()), 3), dtype=dtype)
    # The triangles too (F x 3, int32 below 2^31 vertices, as ``face_index_dtype``): one
    # primitive's as read, several filled in place; never an int64 copy of them all.
    corners = [
        accessors[p["indices"]]["count"] if p.get("indices") is not None else counts[pos]
        for p in primitives
        for pos in [p["attributes"]["POSITION"]]
    ]
    index_dtype = face_index_dtype(sum(counts.values()))
    several = len(primitives) > 1
    all_faces = np.empty((sum(c // 3 for c in corners) if several else 0, 3), dtype=index_dtype)
    row = 0

    positions: list[np.ndarray] = []
    first_vertex: dict[int, int] = {}
    vertex_count: dict[int, int] = {}
    total = 0
    for number, prim in enumerate(primitives):
        mode = prim.get("mode", TRIANGLES)
        if mode != TRIANGLES:
            raise ExampleSetError(
                f"{label}: primitive {number} has mode {mode}; only triangles (4) are supported",
                code="bad_gltf",
            )
        pos_index = prim["attributes"]["POSITION"]
        draco = reader.draco_geometry(prim)
        if pos_index not in first_vertex:
            # Quantised positions (KHR_mesh_quantization) come as integers: as floats here.
            read = reader.accessor(pos_index) if draco is None else draco[0].copy()
            pos = read.astype(np.float64, copy=False)
            if pos.shape[1] != 3 or pos.shape[0] != counts[pos_index]:
                raise ExampleSetError(f"{label}: POSITION is not VEC3", code="bad_gltf")
            if not np.isfinite(pos).all():  # a float accessor, or a decoded one, may hold NaN
                raise ExampleSetError(
                    f"{label}: primitive {number} has NaN or Inf positions", code="non_finite"
                )
            first_vertex[pos_index] = total
            vertex_count[pos_index] = pos.shape[0]
            total += pos.shape[0]
            positions.append(pos)
            rows = slice(first_vertex[pos_index], total)
            for t, target in enumerate(prim.get("targets", [])):
                t_pos = target.get("POSITION")
                if t_pos is not None:
                    _read_target(reader, t_pos, t, all_deltas[t, rows], label)
        if prim.get("indices") is None:
            tri = np.arange(vertex_count[pos_index], dtype=index_dtype)
        elif draco is not None and draco[1] is not None:
            tri = draco[1].astype(index_dtype)  # a copy: the reader keeps the decoded corners
        else:
            tri = reader.accessor(prim["indices"], integers=index_dtype)[:, 0]
        if tri.size % 3:
            raise ExampleSetError(
                f"{label}: primitive {number} index count is not a multiple of 3", code="bad_gltf"
            )
        if tri.size and (tri.min() < 0 or tri.max() >= vertex_count[pos_index]):
            raise ExampleSetError(
                f"{label}: primitive {number} has triangle indices out of range", code="bad_gltf"
            )
        triangles = tri.reshape(-1, 3)
        triangles += first_vertex[pos_index]
        if not several:
            all_faces = triangles
        else:
            all_faces[row : row + len(triangles)] = triangles
            row += len(triangles)

    neutral = positions[0] if len(positions) == 1 else np.concatenate(positions)
    return neutral, all_faces, all_deltas, target_names(mesh, m)


def _read_target(
    reader: BufferReader, accessor: int, number: int, out: np.ndarray, label: str
) -> None:
    """Morph target ``number``'s POSITION offsets (accessor ``accessor``) into ``out`` (V, 3):
    what it is read into goes when it is copied, before the next target is read."""
    deltas = reader.accessor(accessor, floats=out.dtype.type)
    if deltas.shape != out.shape:
        raise ExampleSetError(
            f"{label}: morph target {number} is not VEC3 as POSITION is", code="bad_gltf"
        )
    if not np.isfinite(deltas).all():
        raise ExampleSetError(
            f"{label}: morph target {number} has NaN or Inf offsets", code="non_finite"
        )
    out[:] = deltas


def target_names(mesh: dict[str, Any], m: int) -> list[str]:
    for extras in (mesh.get("extras"), mesh["primitives"][0].get("extras")):
        if isinstance(extras, dict) and isinstance(extras.get("targetNames"), list):
            names = extras["targetNames"]
            if len(names) == m and all(isinstance(n, str) and n for n in names):
                return list(names)
    return [f"target_{i}" for i in range(m)]

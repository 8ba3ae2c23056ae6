"""A neutral-only character file given its key-expressions: transferred shapes as morph targets.

``plan_transfer`` checks what a transfer onto a loaded character needs (its face mesh,
markers, a vertex bound, which ARKit shapes it lacks) before any solving;
``with_transferred_expressions`` runs it and writes the shapes into the character's GLB as
morph targets named by ARKit (``add_morph_targets``), so the file drives them like any
authored morph. It must not fit or store anything.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeGuard

import numpy as np
import numpy.typing as npt

from ..characters.character import Character
from ..errors import ExampleSetError, MarkerError
from .correspondence import check_markers, identity_correspondence
from .expressions import GeneratedExpressions, SourceExpressions, transfer_expressions, weld
from .mesh import check_mesh
from .solve import STILL

__all__ = [
    "TransferPlan",
    "add_morph_targets",
    "check_targetable",
    "plan_transfer",
    "with_transferred_expressions",
]

_GLB_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<I4s")
_FLOAT = 5126
_ARRAY_BUFFER = 34962


@dataclass(frozen=True, eq=False)
class TransferPlan:
    """What ``with_transferred_expressions`` will do, checked.

    Attributes
    ----------
    character : Character
    names : tuple of str
        The source expressions to make (ARKit names the character lacks), in the source's order.
    markers : (N, 2) int64, "auto" or None
        None when the face mesh shares the source's topology (identity correspondence).
    method : str
        "identity", "markers" or "automatic".
    """

    character: Character
    names: tuple[str, ...]
    markers: np.ndarray | str | None
    method: str

    @property
    def vertices(self) -> int:
        return int(self.character.face_vertices.shape[0])


def plan_transfer(
    character: Character,
    source: SourceExpressions,
    *,
    markers: npt.ArrayLike | str | None = None,
    names: Sequence[str] | None = None,
    max_vertices: int | None = None,
    max_faces: int | None = None,
    label: str = "character",
) -> TransferPlan:
    """Check a transfer onto ``character``'s face mesh; cheap next to the transfer itself.

    Parameters
    ----------
    character : Character
        As ``load_character`` reads it; its face mesh (the mesh with most expressions, or
        with most vertices when it has none) is the target.
    source : SourceExpressions
    markers : (N, 2) int, "auto" or None
        As ``transfer_expressions`` takes them; checked even when the face mesh shares the
        source's topology (then unused).
    names : sequence of str, optional
        Source expressions to make; default all. Those the character already has are
        skipped: an authored expression is never replaced.
    max_vertices, max_faces : int, optional
        Largest face mesh the transfer takes, in vertices and in triangles.

    Raises
    ------
    ExampleSetError
        ``too_many_vertices``, ``too_many_faces``; ``bad_gltf`` (``check_targetable``);
        ``expressions_complete`` (nothing left to make);
        ``unknown_expression``.
    MeshError, MarkerError
        The face mesh is not a manifold triangle mesh; markers bad, or needed.
    """
    vertices, faces = character.face_vertices, character.face_faces
    if max_vertices is not None and vertices.shape[0] > max_vertices:
        raise ExampleSetError(
            f"{label}: its face mesh {character.mesh_names[character.face_mesh]!r} has "
            f"{vertices.shape[0]} vertices, more than the {max_vertices} a transfer takes "
            "here: decimate it, or run `facecast expressions` on your own machine and fit "
            "the folder it writes",
            code="too_many_vertices",
        )
    if max_faces is not None and faces.shape[0] > max_faces:
        raise ExampleSetError(
            f"{label}: its face mesh {character.mesh_names[character.face_mesh]!r} has "
            f"{faces.shape[0]} triangles, more than the {max_faces} a transfer takes here: "
            "decimate it, or run `facecast expressions` on your own machine and fit the "
            "folder it writes",
            code="too_many_faces",
        )
    check_targetable(character.glb, character.face_mesh)
    known = set(source.names[1:])
    asked = list(source.names[1:]) if names is None else list(dict.fromkeys(names))
    unknown = [n for n in asked if n not in known]
    if unknown:
        raise ExampleSetError(
            f"no source expression named {unknown[0]!r}; expected ARKit names such as "
            f"{', '.join(source.names[1:4])} ({len(known)} in all)",
            code="unknown_expression",
        )
    making = tuple(n for n in source.names[1:] if n in asked and n not in character.expressions)
    if not making:
        raise ExampleSetError(
            f"{label} already has every expression asked for "
            f"({len(asked)}); nothing to transfer: upload it without expressions=transfer",
            code="expressions_complete",
        )
    target, target_faces = check_mesh(vertices, faces, what=f"{label}'s face mesh")
    welded, welded_faces, _ = weld(target, target_faces)
    same = identity_correspondence(source.vertices[0], source.faces, welded, welded_faces)
    if same is None:
        same = identity_correspondence(source.vertices[0], source.faces, target, target_faces)
    if isinstance(markers, str):
        if markers != "auto":
            raise MarkerError(
                f"markers: {markers!r} is neither marker pairs nor 'auto'", code="bad_markers"
            )
        checked: np.ndarray | str | None = markers
    elif markers is not None:
        checked = check_markers(
            markers, source.vertices.shape[1], target.shape[0], source=source.vertices[0]
        )
    else:
        checked = None
    if same is not None:
        return TransferPlan(character, making, None, "identity")
    if checked is None:
        raise MarkerError(
            f"{label}'s face mesh has another topology than the source's (ICT-FaceKit's face), "
            "so the correspondence needs markers: 'source_vertex target_vertex' lines "
            "(0-based, at least 3, about 20), or 'auto' for a fit without them (the face "
            "looking along +z with y up)",
            code="markers_needed",
        )
    return TransferPlan(
        character, making, checked, "automatic" if isinstance(checked, str) else "markers"
    )


def with_transferred_expressions(
    plan: TransferPlan,
    source: SourceExpressions,
    *,
    still: float | None = STILL,
    progress: Callable[[int], object] | None = None,
) -> tuple[bytes, GeneratedExpressions]:
    """The character's GLB with the planned expressions as morph targets of its face mesh.

    Returns the new GLB (everything else byte for byte as it was; the new targets appended
    to every primitive of the face mesh, named in ``extras.targetNames``) and what
    ``transfer_expressions`` made. ``progress`` is called with 1 after each expression.
    """
    character = plan.character
    generated = transfer_expressions(
        source,
        character.face_vertices,
        character.face_faces,
        markers=plan.markers,
        names=plan.names,
        still=still,
        progress=progress,
    )
    made = generated.target_vertices
    # float32 as the file stores them, each the float64 difference rounded once (as
    # ``(made[1:] - made[0]).astype(np.float32)``), without that float64 array.
    displacements = np.empty((len(made) - 1, *made.shape[1:]), dtype=np.float32)
    np.subtract(made[1:], made[0], out=displacements, casting="same_kind")
    glb = add_morph_targets(character.glb, character.face_mesh, generated.names[1:], displacements)
    return glb, generated


def add_morph_targets(
    glb: bytes, mesh: int, names: Sequence[str], displacements: npt.ArrayLike
) -> bytes:
    """``glb`` with one morph target per name appended to every primitive of mesh ``mesh``.

    Parameters
    ----------
    glb : bytes
        A glTF binary whose buffer 0 is its BIN chunk.
    mesh : int
        Index in ``meshes``.
    names : sequence of M str
    displacements : (M, V, 3) float
        On the mesh's vertices as ``gltf.read_mesh`` concatenates them (each POSITION
        accessor once, in the order primitives first name it).

    The targets' POSITION accessors (float32, with min and max) go at the end of the BIN
    chunk; ``extras.targetNames`` and ``weights`` (zeros) of the mesh, and ``weights`` of
    nodes that give them, grow to match. Nothing else changes.
    """
    doc, binary = _split_glb(glb)
    deltas = np.asarray(displacements, dtype=np.float32)
    starts, total = _targetable(doc, mesh)
    meshes = doc["meshes"]
    primitives = meshes[mesh]["primitives"]
    accessors = doc["accessors"]
    views = doc.setdefault("bufferViews", [])
    if deltas.shape != (len(names), total, 3):
        raise ExampleSetError(
            f"displacements: expected shape ({len(names)}, {total}, 3), got {deltas.shape}",
            code="bad_gltf",
        )
    # The new BIN chunk as its pieces (the old one, padding, each target's rows: views, not
    # copies), joined once with the rest of the file by ``_join_glb``.
    pieces: list[bytes | memoryview] = [binary]
    size = len(binary)
    made: dict[tuple[int, int], int] = {}  # (POSITION accessor, expression) -> new accessor
    for position, start in starts.items():
        count = int(accessors[position]["count"])
        for index in range(len(names)):
            rows = np.ascontiguousarray(deltas[index, start : start + count])
            pieces.append(b"\0" * (-size % 4))
            size += -size % 4
            views.append(
                {"buffer": 0, "byteOffset": size, "byteLength": rows.nbytes,
                 "target": _ARRAY_BUFFER}
            )  # fmt: skip
            pieces.append(rows.data.cast("B") if rows.size else b"")
            size += rows.nbytes
            accessors.append(
                {
                    "bufferView": len(views) - 1,
                    "componentType": _FLOAT,
                    "count": count,
                    "type": "VEC3",
                    "min": rows.min(axis=0).tolist() if count else [0.0, 0.0, 0.0],
                    "max": rows.max(axis=0).tolist() if count else [0.0, 0.0, 0.0],
                }
            )
            made[position, index] = len(accessors) - 1
    before = len(primitives[0].get("targets") or [])
    for prim in primitives:
        position = prim["attributes"]["POSITION"]
        prim.setdefault("targets", []).extend(
            {"POSITION": made[position, i]} for i in range(len(names))
        )
    entry = meshes[mesh]
    extras = entry.get("extras")
    if not isinstance(extras, dict):
        extras = entry["extras"] = {}
    old_names = extras.get("targetNames")
    if not isinstance(old_names, list) or len(old_names) != before:
        old_names = [f"target_{i}" for i in range(before)]
    extras["targetNames"] = [*old_names, *names]
    if "weights" in entry or before:
        entry["weights"] = [*(entry.get("weights") or [0.0] * before), *[0.0] * len(names)]
    for node in doc.get("nodes") or []:
        if node.get("mesh") == mesh and "weights" in node:
            node["weights"] = [*node["weights"], *[0.0] * len(names)]
    pieces.append(b"\0" * (-size % 4))
    size += -size % 4
    buffers = doc.setdefault("buffers", [])
    if not buffers:
        buffers.append({})
    buffers[0]["byteLength"] = size
    return _join_glb(doc, pieces)


def check_targetable(glb: bytes, mesh: int) -> None:
    """Raise ``ExampleSetError`` (``bad_gltf``) unless ``add_morph_targets`` can write
    targets into mesh ``mesh`` of ``glb``: every part of the document it reads or grows
    has the type glTF gives it. Cheap (the JSON only): run it before a transfer starts."""
    _targetable(_split_glb(glb)[0], mesh)


def _bad(message: str) -> ExampleSetError:
    return ExampleSetError(f"the file cannot take morph targets: {message}", code="bad_gltf")


def _numbers(value: Any) -> bool:
    return isinstance(value, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    )


def _index(value: Any, length: int) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < length


def _targetable(doc: Any, mesh: int) -> tuple[dict[int, int], int]:
    """Check what ``add_morph_targets`` touches; each POSITION accessor's first row, and
    the rows in all (``gltf.read_mesh``'s order)."""
    if not isinstance(doc, dict):
        raise _bad("its JSON is not an object")
    meshes, accessors = doc.get("meshes"), doc.get("accessors")
    if not isinstance(meshes, list) or not _index(mesh, len(meshes)):
        raise _bad(f"no mesh {mesh}")
    if not isinstance(accessors, list):
        raise _bad("accessors is not an array")
    for key in ("bufferViews", "buffers", "nodes"):
        if not isinstance(doc.get(key, []), list):
            raise _bad(f"{key} is not an array")
    entry = meshes[mesh]
    primitives = entry.get("primitives") if isinstance(entry, dict) else None
    if not isinstance(primitives, list) or not primitives:
        raise _bad(f"mesh {mesh} has no primitives array")
    starts: dict[int, int] = {}
    total = 0
    for number, prim in enumerate(primitives):
        attributes = prim.get("attributes") if isinstance(prim, dict) else None
        position = attributes.get("POSITION") if isinstance(attributes, dict) else None
        if not isinstance(position, int) or not _index(position, len(accessors)):
            raise _bad(f"mesh {mesh} primitive {number} has no valid POSITION accessor")
        if not isinstance(prim.get("targets", []), list):
            raise _bad(f"mesh {mesh} primitive {number}: targets is not an array")
        if position not in starts:
            accessor = accessors[position]
            count = accessor.get("count") if isinstance(accessor, dict) else None
            if not isinstance(count, int) or isinstance(count, bool) or count < 0:
                raise _bad(f"accessor {position}: count is not a non-negative integer")
            starts[position] = total
            total += count
    if "weights" in entry and not _numbers(entry["weights"]):
        raise _bad(f"mesh {mesh}: weights is not an array of numbers")
    for number, node in enumerate(doc.get("nodes", [])):
        if not isinstance(node, dict):
            raise _bad(f"node {number} is not an object")
        if node.get("mesh") == mesh and "weights" in node and not _numbers(node["weights"]):
            raise _bad(f"node {number}: weights is not an array of numbers")
    buffers = doc.get("buffers", [])
    if buffers and not isinstance(buffers[0], dict):
        raise _bad("buffer 0 is not an object")
    return starts, total


def _split_glb(glb: bytes) -> tuple[dict[str, Any], memoryview]:
    """The JSON document and the BIN chunk (empty if none; a view of ``glb``) of a glTF
    binary."""
    magic, version, _ = _GLB_HEADER.unpack_from(glb)
    if magic != b"glTF" or version != 2:
        raise ExampleSetError("not a glTF 2.0 binary", code="bad_gltf")
    offset = _GLB_HEADER.size
    length, kind = _CHUNK.unpack_from(glb, offset)
    if kind != b"JSON":
        raise ExampleSetError("the GLB's first chunk is not JSON", code="bad_gltf")
    doc = json.loads(glb[offset + _CHUNK.size : offset + _CHUNK.size + length])
    offset += _CHUNK.size + length
    binary = memoryview(b"")
    if offset + _CHUNK.size <= len(glb):
        length, kind = _CHUNK.unpack_from(glb, offset)
        if kind == b"BIN\0":
            binary = memoryview(glb)[offset + _CHUNK.size : offset + _CHUNK.size + length]
    buffers = doc.get("buffers") or []
    if buffers and "uri" in buffers[0]:
        raise ExampleSetError(
            "the GLB's first buffer is not its BIN chunk: re-export it as one .glb",
            code="bad_gltf",
        )
    return doc, binary


def _join_glb(doc: dict[str, Any], binary: list[bytes | memoryview]) -> bytes:
    """The glTF binary of ``doc`` and the BIN chunk made of ``binary``'s pieces, joined in
    one copy."""
    text = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode()
    text += b" " * (-len(text) % 4)
    size = sum(len(piece) for piece in binary)
    chunks: list[bytes | memoryview] = [_CHUNK.pack(len(text), b"JSON"), text]
    if size:
        chunks += [_CHUNK.pack(size, b"BIN\0"), *binary]
    total = _GLB_HEADER.size + sum(len(chunk) for chunk in chunks)
    return b"".join([_GLB_HEADER.pack(b"glTF", 2, total), *chunks])

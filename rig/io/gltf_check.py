"""Checking an untrusted glTF document before anything is read: sizes, types, the node tree.

Every count, index, offset and length a glTF/GLB/VRM declares is checked against the
bytes really there and against ``GltfLimits`` before any array is allocated, in time
linear in the document; it decodes no accessor and builds no mesh (gltf_read.py does).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from typing import Any

from ..errors import ExampleSetError
from .gltf_compression import MESHOPT, draco_extension, meshopt_extension

__all__ = [
    "COMPONENT_SIZES",
    "TYPE_SIZES",
    "Buffer",
    "GltfLimits",
    "check_document",
    "decode_data_uri",
    "external_uri_error",
    "max_decoded_bytes",
    "parse_json",
    "split_glb",
]

#: Bytes of each accessor componentType (glTF 2.0 §3.6.2.2).
COMPONENT_SIZES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
#: Components of each accessor type.
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_INDEX_TYPES = (5121, 5123, 5125)
_FLOAT = 5126
#: A buffer's bytes: the GLB's BIN chunk is a view of the file's bytes (never a copy of
#: them: it is most of a 64 MiB upload), a data URI's or a file's are bytes of their own.
Buffer = bytes | memoryview

_GLB_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<I4s")


@dataclass(frozen=True)
class GltfLimits:
    """The most a glTF document may declare; the server's are its ``max_gltf_*`` settings.

    Counts are inclusive. ``json_values``: JSON values (objects, arrays, strings, numbers)
    in its JSON text, counted before it is parsed; ``nodes`` and ``depth``: the node
    tree's size and levels (a root alone is depth 1); ``meshes``, ``primitives`` (all
    meshes together); ``vertices``: every distinct POSITION accessor's count summed;
    ``faces``: triangles of every primitive summed (a primitive's index count / 3);
    ``morph_targets``: per mesh; ``morph_values``: morph targets x vertices, summed over
    meshes, counted twice for a mesh whose morph targets are not all float32 (what reading
    them allocates: 12 bytes a value as float32, 24 quantised, read as float64;
    ``load_character`` bounds the face's morph values with VRM expressions that mix
    morphs x face vertices, counted twice (float64), and expressions paired x face
    vertices, by it too); ``accessor_values``: count x components summed over every
    accessor (with or without a bufferView).
    """

    json_values: int = 1_000_000
    nodes: int = 20_000
    depth: int = 256
    meshes: int = 1_000
    primitives: int = 10_000
    vertices: int = 500_000
    faces: int = 1_000_000
    morph_targets: int = 1_000
    morph_values: int = 4_000_000
    accessor_values: int = 32_000_000

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"GltfLimits.{f.name}: expected an int >= 1, got {value!r}")


def max_decoded_bytes(limits: GltfLimits) -> int:
    """Most bytes the meshopt views of one document may decode to: 4 (a float32 or uint32)
    for each value ``limits.accessor_values`` lets its accessors hold. The check holds the
    views' declared sizes to it, and the reader (gltf_read.BufferReader) what it decodes."""
    return 4 * limits.accessor_values


def _bad(label: str, message: str) -> ExampleSetError:
    return ExampleSetError(f"{label}: {message}", code="bad_gltf")


def _over(label: str, what: str, declared: int, limit: int, name: str) -> ExampleSetError:
    return ExampleSetError(
        f"{label}: declares {declared} {what}; at most {limit} are read "
        f"(limit max_gltf_{name}): simplify or split the model",
        code="gltf_exceeds_limits",
    )


def external_uri_error(uri: str, label: str, where: str = "outside the file") -> ExampleSetError:
    return ExampleSetError(
        f"{label}: refers to {uri[:200]!r}, {where}: a character's files must travel with "
        "it (a .glb, or a .gltf with its files beside it)",
        code="external_uri",
    )


# -- the container ----------------------------------------------------------------------


def split_glb(data: bytes, label: str) -> tuple[bytes, memoryview | None]:
    """The JSON and BIN chunks of a GLB, every length checked against the bytes there; the
    BIN chunk is a read-only view of ``data``, not a copy."""
    if len(data) < _GLB_HEADER.size:
        raise ExampleSetError(f"{label}: GLB cut short in its header", code="truncated_file")
    _magic, version, length = _GLB_HEADER.unpack_from(data)
    if version != 2:
        raise ExampleSetError(f"{label}: GLB version {version}, expected 2", code="bad_gltf")
    if length > len(data):
        raise ExampleSetError(
            f"{label}: GLB cut short: its header says {length} bytes, the file has {len(data)} "
            "(upload the whole file)",
            code="truncated_file",
        )
    chunks: list[tuple[bytes, memoryview]] = []
    whole = memoryview(data).toreadonly()
    pos = _GLB_HEADER.size
    while pos < length:
        if pos + _CHUNK.size > length:
            raise ExampleSetError(
                f"{label}: GLB cut short in a chunk header", code="truncated_file"
            )
        size, kind = _CHUNK.unpack_from(data, pos)
        start = pos + _CHUNK.size
        if start + size > length:
            raise ExampleSetError(
                f"{label}: GLB cut short: a chunk of {size} bytes runs past the end",
                code="truncated_file",
            )
        chunks.append((kind, whole[start : start + size]))
        pos = start + size + (-size) % 4
    if not chunks or chunks[0][0] != b"JSON":
        raise ExampleSetError(f"{label}: GLB without a JSON chunk first", code="bad_gltf")
    blob = next((c for k, c in chunks[1:] if k == b"BIN\0"), None)
    return bytes(chunks[0][1]), blob


def parse_json(text: bytes, limits: GltfLimits, label: str) -> dict[str, Any]:
    """The glTF JSON as a dict, its number of values bounded before it is parsed.

    Every JSON value but the first follows a ``[``, ``,`` or ``:``, and each object
    adds a ``{``: their count bounds the Python objects ``json.loads`` would make (each
    tens of bytes, whatever the text's size), so a body of ``[{},{},...]`` cannot turn
    64 MiB into gigabytes. Punctuation inside strings only over-counts.
    """
    values = sum(text.count(c) for c in (b"[", b",", b":", b"{")) + 1
    if values > limits.json_values:
        raise _over(label, "JSON values or more", values, limits.json_values, "json_values")
    try:
        doc = json.loads(text)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise _bad(label, f"glTF JSON is not readable ({type(exc).__name__})") from None
    asset = doc.get("asset") if isinstance(doc, dict) else None
    if not isinstance(asset, dict) or not str(asset.get("version", "")).startswith("2"):
        raise _bad(label, "not a glTF 2.0 document")
    checked: dict[str, Any] = doc
    return checked


# -- typed reads --------------------------------------------------------------------------


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _int(value: object, where: str, label: str, low: int = 0) -> int:
    if not _is_int(value):
        raise _bad(label, f"{where} is {str(value)[:40]!r}, not an integer")
    assert isinstance(value, int)
    if value < low:
        raise _bad(label, f"{where} is {value}, below {low}")
    return value


def _index(value: object, size: int, where: str, label: str) -> int:
    index = _int(value, where, label)
    if index >= size:
        raise _bad(label, f"{where} is {index}; there are {size}")
    return index


def _list(doc: dict[str, Any], key: str, label: str) -> list[dict[str, Any]]:
    items = doc.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise _bad(label, f"{key} is not a list of objects")
    return items


def _weights(value: object, where: str, limits: GltfLimits, label: str) -> None:
    if value is None:
        return
    if not isinstance(value, list) or not all(
        isinstance(w, int | float) and not isinstance(w, bool) and math.isfinite(w) for w in value
    ):
        raise _bad(label, f"{where} weights is not a list of numbers")
    if len(value) > limits.morph_targets:
        raise _over(label, "morph weights", len(value), limits.morph_targets, "morph_targets")


# -- the document -------------------------------------------------------------------------


def _uris(doc: dict[str, Any]) -> Iterator[str]:
    """Every ``"uri"`` string anywhere in the document, walked iteratively (a deep
    document cannot exhaust the stack)."""
    stack: list[object] = [doc]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            for key, child in item.items():
                if key == "uri" and isinstance(child, str):
                    yield child
                elif isinstance(child, dict | list):
                    stack.append(child)
        elif isinstance(item, list):
            stack.extend(child for child in item if isinstance(child, dict | list))


def decode_data_uri(uri: str, label: str) -> bytes:
    """The bytes of a base64 ``data:`` URI (the only form a glTF embeds buffers in)."""
    header, comma, payload = uri.partition(",")
    if not comma or not header.endswith(";base64"):
        raise _bad(label, f"data URI {uri[:60]!r} is not base64")
    try:
        return base64.b64decode(payload, validate=True)
    except (binascii.Error, ValueError):
        raise _bad(label, f"malformed data URI {uri[:60]!r}") from None


def _is_fallback(buffer: dict[str, Any]) -> bool:
    """An ``EXT_meshopt_compression`` fallback buffer: a size with no bytes behind it."""
    extensions = buffer.get("extensions")
    ext = extensions.get(MESHOPT) if isinstance(extensions, dict) else None
    return isinstance(ext, dict) and ext.get("fallback") is True


def _buffers(
    doc: dict[str, Any],
    blob: Buffer | None,
    resolve: Callable[[str], bytes] | None,
    label: str,
) -> tuple[list[Buffer], list[int]]:
    """Each buffer's bytes (the BIN chunk, a data URI, or what ``resolve`` gives for a
    file; none for a meshopt fallback buffer), and the size its views may span."""
    found: list[Buffer] = []
    sizes: list[int] = []
    for number, buffer in enumerate(_list(doc, "buffers", label)):
        where = f"buffer {number}"
        declared = _int(buffer.get("byteLength"), f"{where} byteLength", label, low=1)
        uri = buffer.get("uri")
        if uri is None and not (number == 0 and blob is not None) and _is_fallback(buffer):
            found.append(b"")  # only meshopt views may lie in it: they decode their bytes
            sizes.append(declared)
            continue
        if uri is None:
            if number != 0 or blob is None:
                raise _bad(label, f"{where} has no uri and is not the GLB's BIN chunk")
            data: Buffer = blob
        elif not isinstance(uri, str):
            raise _bad(label, f"{where} uri is not a string")
        elif number == 0 and blob is not None:
            # glTF 2.0 §4.4.3.3: the BIN chunk is buffer 0, which then has no uri; one
            # given anyway would be fetched by some readers and ignored by others.
            raise _bad(label, f"{where} is the GLB's BIN chunk but also names {uri[:200]!r}")
        elif uri.startswith("data:"):
            data = decode_data_uri(uri, label)
        elif resolve is None:
            raise external_uri_error(uri, label)
        else:
            data = resolve(uri)
        if declared > len(data):
            raise _bad(label, f"{where} declares {declared} bytes; it holds {len(data)}")
        found.append(data)
        sizes.append(len(data))
    return found, sizes


def _views(
    doc: dict[str, Any], buffers: list[Buffer], sizes: list[int], limits: GltfLimits, label: str
) -> list[dict[str, Any]]:
    views = _list(doc, "bufferViews", label)
    decoded = 0  # bytes meshopt views decode to, at most max_decoded_bytes
    for number, view in enumerate(views):
        where = f"bufferView {number}"
        buffer = _index(view.get("buffer"), len(buffers), f"{where} buffer", label)
        offset = _int(view.get("byteOffset", 0), f"{where} byteOffset", label)
        length = _int(view.get("byteLength"), f"{where} byteLength", label, low=1)
        if offset + length > sizes[buffer]:
            raise _bad(
                label,
                f"{where} spans bytes {offset}..{offset + length} of buffer {buffer}, "
                f"which holds {sizes[buffer]}",
            )
        compressed = meshopt_extension(view)
        if len(buffers[buffer]) < sizes[buffer] and compressed is None:
            raise _bad(label, f"{where} lies in a meshopt fallback buffer but is not compressed")
        if compressed is not None:
            # Its compressed bytes: in a buffer with bytes (gltf_compression checks the
            # rest of the extension, and the decoded size against byteLength, before decoding).
            source = _index(
                compressed.get("buffer"), len(buffers), f"{where} meshopt buffer", label
            )
            start = _int(compressed.get("byteOffset", 0), f"{where} meshopt byteOffset", label)
            size = _int(compressed.get("byteLength"), f"{where} meshopt byteLength", label, low=1)
            if start + size > len(buffers[source]):
                raise _bad(label, f"{where}'s compressed bytes run past buffer {source}")
            decoded += length
            if decoded > max_decoded_bytes(limits):
                raise _over(
                    label, "bytes of meshopt views to decode or more", decoded,
                    max_decoded_bytes(limits), "accessor_values (x 4 bytes)",
                )  # fmt: skip
        stride = view.get("byteStride")
        if stride is not None and (
            not _is_int(stride) or not 4 <= stride <= 252 or stride % 4 != 0
        ):
            raise _bad(label, f"{where} byteStride {str(stride)[:40]!r} is not 4..252, by 4")
    return views


def _extent(
    views: list[dict[str, Any]], view_index: object, offset: object, count: int, size: int,
    where: str, label: str, reads: dict[int, int],
) -> None:  # fmt: skip
    """Raise unless ``count`` elements of ``size`` bytes at ``offset`` fit in the view;
    ``reads[view]``: the furthest byte of the view read so far."""
    number = _index(view_index, len(views), f"{where} bufferView", label)
    view = views[number]
    start = _int(offset if offset is not None else 0, f"{where} byteOffset", label)
    stride = view.get("byteStride") or size
    if stride < size:
        raise _bad(label, f"{where}: elements of {size} bytes in a view with stride {stride}")
    end = start + stride * (count - 1) + size
    if end > view["byteLength"]:
        raise _bad(label, f"{where} runs past its bufferView ({view['byteLength']} bytes)")
    reads[number] = max(reads.get(number, 0), end)


def _accessors(
    doc: dict[str, Any],
    views: list[dict[str, Any]],
    limits: GltfLimits,
    label: str,
    reads: dict[int, int],
) -> list[dict[str, Any]]:
    """The accessors, checked; ``reads`` gets the furthest byte each bufferView is read to."""
    accessors = _list(doc, "accessors", label)
    total = 0
    for number, acc in enumerate(accessors):
        where = f"accessor {number}"
        count = _int(acc.get("count"), f"{where} count", label, low=1)
        component = acc.get("componentType")
        kind = acc.get("type")
        if not _is_int(component) or component not in COMPONENT_SIZES:
            raise _bad(label, f"{where} componentType {str(component)[:40]!r} is unknown")
        if not isinstance(kind, str) or kind not in TYPE_SIZES:
            raise _bad(label, f"{where} type {str(kind)[:40]!r} is unknown")
        if not isinstance(acc.get("normalized", False), bool):
            raise _bad(label, f"{where} normalized is not true or false")
        ncomp = TYPE_SIZES[kind]
        total += count * ncomp
        if total > limits.accessor_values:
            raise _over(
                label, "accessor values or more", total, limits.accessor_values, "accessor_values"
            )
        size = COMPONENT_SIZES[component] * ncomp
        if acc.get("bufferView") is not None:
            _extent(
                views, acc["bufferView"], acc.get("byteOffset"), count, size, where, label, reads
            )
        elif acc.get("byteOffset", 0) != 0:
            raise _bad(label, f"{where} has a byteOffset but no bufferView")
        sparse = acc.get("sparse")
        if sparse is not None:
            _sparse(sparse, views, count, size, where, label, reads)
    return accessors


def _sparse(
    sparse: object, views: list[dict[str, Any]], count: int, size: int, where: str, label: str,
    reads: dict[int, int],
) -> None:  # fmt: skip
    indices = sparse.get("indices") if isinstance(sparse, dict) else None
    values = sparse.get("values") if isinstance(sparse, dict) else None
    if not isinstance(indices, dict) or not isinstance(values, dict):
        raise _bad(label, f"{where} sparse is malformed")
    assert isinstance(sparse, dict)
    n = _int(sparse.get("count"), f"{where} sparse count", label, low=1)
    if n > count:
        raise _bad(label, f"{where} sparse count {n} exceeds its count {count}")
    component = indices.get("componentType")
    if not _is_int(component) or component not in _INDEX_TYPES:
        raise _bad(label, f"{where} sparse indices componentType {str(component)[:40]!r}")
    _extent(
        views, indices.get("bufferView"), indices.get("byteOffset"), n,
        COMPONENT_SIZES[component], f"{where} sparse indices", label, reads,
    )  # fmt: skip
    _extent(
        views, values.get("bufferView"), values.get("byteOffset"), n, size,
        f"{where} sparse values", label, reads,
    )  # fmt: skip


def _meshes(
    doc: dict[str, Any], accessors: list[dict[str, Any]], limits: GltfLimits, label: str
) -> None:
    meshes = _list(doc, "meshes", label)
    if len(meshes) > limits.meshes:
        raise _over(label, "meshes", len(meshes), limits.meshes, "meshes")
    primitives = vertices = faces = morph_values = 0
    positions: set[int] = set()
    for number, mesh in enumerate(meshes):
        prims = mesh.get("primitives")
        if not isinstance(prims, list) or not prims or not all(isinstance(p, dict) for p in prims):
            raise _bad(label, f"mesh {number} has no list of primitives")
        primitives += len(prims)
        if primitives > limits.primitives:
            raise _over(label, "primitives or more", primitives, limits.primitives, "primitives")
        _weights(mesh.get("weights"), f"mesh {number}", limits, label)
        mesh_vertices = 0
        mesh_positions: set[int] = set()
        targets = 0
        quantised = False  # a morph target not stored as float32: all are read as float64
        for p, prim in enumerate(prims):
            where = f"mesh {number} primitive {p}"
            attributes = prim.get("attributes")
            if not isinstance(attributes, dict) or "POSITION" not in attributes:
                raise _bad(label, f"{where} has no POSITION attribute")
            position = _index(attributes["POSITION"], len(accessors), f"{where} POSITION", label)
            count = accessors[position]["count"]
            for name, index in attributes.items():
                i = _index(index, len(accessors), f"{where} attribute {name}", label)
                if accessors[i]["count"] != count:
                    raise _bad(label, f"{where} attribute {name} has a count unlike POSITION's")
            draco = draco_extension(prim)
            if draco is not None:
                views = len(doc.get("bufferViews", []))
                _index(draco.get("bufferView"), views, f"{where} Draco bufferView", label)
            mode = _int(prim.get("mode", 4), f"{where} mode", label)
            if mode > 6:
                raise _bad(label, f"{where} mode {mode} is not 0..6")
            if prim.get("indices") is not None:
                i = _index(prim["indices"], len(accessors), f"{where} indices", label)
                if accessors[i]["type"] != "SCALAR" or accessors[i]["componentType"] not in (
                    _INDEX_TYPES
                ):
                    raise _bad(label, f"{where} indices are not unsigned integer scalars")
                faces += accessors[i]["count"] // 3
            else:
                faces += count // 3
            if faces > limits.faces:
                raise _over(label, "triangles or more", faces, limits.faces, "faces")
            prim_targets = prim.get("targets", [])
            if not isinstance(prim_targets, list) or not all(
                isinstance(t, dict) for t in prim_targets
            ):
                raise _bad(label, f"{where} targets is not a list of objects")
            if len(prim_targets) > limits.morph_targets:
                raise _over(
                    label, "morph targets", len(prim_targets), limits.morph_targets,
                    "morph_targets",
                )  # fmt: skip
            targets = max(targets, len(prim_targets))
            for t, target in enumerate(prim_targets):
                for name, index in target.items():
                    i = _index(index, len(accessors), f"{where} target {t} {name}", label)
                    quantised |= name == "POSITION" and accessors[i]["componentType"] != _FLOAT
                    if accessors[i]["count"] != count:
                        called = mesh.get("name")
                        called = called[:200] if isinstance(called, str) else f"mesh {number}"
                        raise ExampleSetError(
                            f"{label}: mesh {called!r} morph target {t} {name} has "
                            f"{accessors[i]['count']} vertices, the mesh has {count}: "
                            "re-export it with the morph targets of this mesh",
                            code="morph_vertex_mismatch",
                        )
            if position not in mesh_positions:
                mesh_positions.add(position)
                mesh_vertices += count
            if position not in positions:
                positions.add(position)
                vertices += count
                if vertices > limits.vertices:
                    raise _over(label, "vertices or more", vertices, limits.vertices, "vertices")
        morph_values += targets * mesh_vertices * (2 if quantised else 1)
        if morph_values > limits.morph_values:
            raise _over(
                label, "morph target values (targets x vertices, twice for quantised "
                "targets) or more", morph_values, limits.morph_values, "morph_values",
            )  # fmt: skip


def _node_tree(doc: dict[str, Any], limits: GltfLimits, label: str) -> None:
    """Nodes form a forest: no node with two parents, no cycle, depth and size bounded."""
    nodes = _list(doc, "nodes", label)
    if len(nodes) > limits.nodes:
        raise _over(label, "nodes", len(nodes), limits.nodes, "nodes")
    meshes = len(doc.get("meshes") or [])
    parent = [-1] * len(nodes)
    for number, node in enumerate(nodes):
        where = f"node {number}"
        if node.get("mesh") is not None:
            _index(node["mesh"], meshes, f"{where} mesh", label)
        _weights(node.get("weights"), where, limits, label)
        children = node.get("children", [])
        if not isinstance(children, list):
            raise _bad(label, f"{where} children is not a list")
        for child in children:
            c = _index(child, len(nodes), f"{where} child", label)
            if parent[c] != -1 or c == number:
                raise _bad(
                    label,
                    f"node {c} has two parents (or is its own child): the nodes must form a tree",
                )
            parent[c] = number
    # Breadth first from the roots: a node in a cycle has a parent but no root above it.
    level = [i for i, p in enumerate(parent) if p == -1]
    reached = len(level)
    depth = 1 if level else 0
    while level:
        below = [c for i in level for c in nodes[i].get("children", [])]
        if below:
            depth += 1
            if depth > limits.depth:
                raise _over(label, "levels of nodes or more", depth, limits.depth, "depth")
        reached += len(below)
        level = below
    if reached != len(nodes):
        raise _bad(label, f"{len(nodes) - reached} nodes form a cycle: the nodes must form a tree")
    for number, scene in enumerate(_list(doc, "scenes", label)):
        roots = scene.get("nodes", [])
        if not isinstance(roots, list):
            raise _bad(label, f"scene {number} nodes is not a list")
        for root in roots:
            if parent[_index(root, len(nodes), f"scene {number} node", label)] != -1:
                raise _bad(label, f"scene {number} names node {root}, which is not a root")
    if doc.get("scene") is not None:
        _index(doc["scene"], len(doc.get("scenes") or []), "scene", label)


def _meshopt_reads(views: list[dict[str, Any]], reads: dict[int, int], label: str) -> None:
    """Each meshopt view decodes to no more than what reads it needs: its accessors' (and
    images') furthest byte, to a whole element of its byteStride. Within the document's
    decode budget (``max_decoded_bytes``) a view named by a 3-vertex accessor could
    otherwise decode megabytes that nothing reads, or a view nothing names at all."""
    for number, view in enumerate(views):
        compressed = meshopt_extension(view)
        if compressed is None:
            continue
        declared = compressed.get("byteStride")
        # (A byteStride that is no positive integer is refused when the view is decoded.)
        stride = declared if isinstance(declared, int) and declared >= 1 else 1
        read = reads.get(number, 0)
        needed = -(-read // stride) * stride
        if view["byteLength"] > needed:
            raise ExampleSetError(
                f"{label}: bufferView {number} decodes to {view['byteLength']} bytes "
                "(EXT_meshopt_compression), but "
                + (f"its accessors read {read} of them" if read else "no accessor reads it")
                + ": a compressed view may hold only what its accessors read",
                code="bad_compression",
            )


def _images(
    doc: dict[str, Any], views: list[dict[str, Any]], label: str, reads: dict[int, int]
) -> None:
    for number, image in enumerate(_list(doc, "images", label)):
        if image.get("bufferView") is not None:
            view = _index(image["bufferView"], len(views), f"image {number} bufferView", label)
            reads[view] = views[view]["byteLength"]  # an image is its whole view
        elif not isinstance(image.get("uri"), str):
            raise _bad(label, f"image {number} has neither a uri nor a bufferView")


def check_document(
    doc: dict[str, Any],
    blob: Buffer | None,
    limits: GltfLimits,
    label: str,
    *,
    resolve: Callable[[str], bytes] | None = None,
) -> list[Buffer]:
    """Check a parsed glTF document against its bytes and ``limits``; its buffers' bytes.

    Parameters
    ----------
    doc : dict
        The glTF JSON (``parse_json``).
    blob : bytes, memoryview or None
        The GLB's BIN chunk (buffer 0 when that has no uri); None for a .gltf.
    limits : GltfLimits
    label : str
        Names the file in errors (never a path on the server).
    resolve : callable, optional
        Reads a buffer's non-``data:`` URI (a file beside a .gltf, never outside its
        folder); without it every such URI is ``external_uri``. Images may only be
        embedded or ``data:`` URIs, and no other ``uri`` may appear anywhere.

    Returns
    -------
    list of Buffer
        Each buffer's bytes (``blob`` itself for the BIN chunk): after this every bufferView lies in its buffer, every
        accessor (and sparse part) in its bufferView, every index is in range and of the
        right type, and the node graph is a tree.

    Raises
    ------
    ExampleSetError
        ``gltf_exceeds_limits`` for a count over ``limits`` (naming the limit),
        ``external_uri``, ``bad_compression`` for a meshopt view decoding to more than its
        accessors read, ``bad_gltf`` for everything else malformed.
    """
    # A file on disk read by the CLI may name files beside it (``resolve`` reads its
    # buffers; images are not read): only an upload must hold everything it uses.
    if resolve is None:
        for uri in _uris(doc):
            if not uri.startswith("data:"):
                raise external_uri_error(uri, label)
    buffers, sizes = _buffers(doc, blob, resolve, label)
    views = _views(doc, buffers, sizes, limits, label)
    reads: dict[int, int] = {}
    accessors = _accessors(doc, views, limits, label, reads)
    _meshes(doc, accessors, limits, label)
    _node_tree(doc, limits, label)
    _images(doc, views, label, reads)
    _meshopt_reads(views, reads, label)
    return buffers

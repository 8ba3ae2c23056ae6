"""A character as its author made it: a .glb, .vrm or .gltf read into its expressions.

Reads the file once, bounded (truncated files, external URIs, texture bombs, broken VRM
binds are named errors), keeps it byte for byte as one GLB and finds its expressions on
every mesh and in its VRM binds, names normalised (``expression_names``). It does not fit,
pair with source points (``character_examples``) or render; docs/characters.md explains it.
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
import urllib.parse
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import ExampleSetError
from ..sources.generic import GENERIC_ATTRIBUTION, generic_sources
from .expression_names import ARKIT_NAMES, VRM_PRESETS, half_of, normalise_name, vrm0_preset
from .gltf import BufferReader, load_document, pack_glb, read_mesh, target_names
from .image_headers import image_size, sniff_mime
from .vrm import VrmExpression, vrm_expressions, vrm_format, vrm_meta

__all__ = [
    "MAX_CHARACTER_BYTES",
    "MAX_TEXTURE_PIXELS",
    "MAX_TEXTURE_SIDE",
    "Binding",
    "Character",
    "Expression",
    "PairingEntry",
    "PairingReport",
    "character_example_set",
    "load_character",
]

#: Largest character file (a .glb/.vrm, or a .gltf with all its files) read.
MAX_CHARACTER_BYTES = 256 * 2**20
#: Largest texture side a header may declare (WebGL 2 guarantees 2048, desktops 16384).
MAX_TEXTURE_SIDE = 8192
#: All textures together, in pixels: 2^27 is 512 MiB decoded as RGBA in a viewer.
MAX_TEXTURE_PIXELS = 2**27

_GLB_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<I4s")
_UNSUPPORTED = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_mesh_quantization")
# Expression order: ARKit's, then VRM's presets, then the rest as found.
_ORDER = {name: i for i, name in enumerate((*ARKIT_NAMES, *VRM_PRESETS))}


@dataclass(frozen=True)
class Binding:
    """Morph target ``morph`` of glTF mesh ``mesh`` (its index in ``meshes``) at ``weight``."""

    mesh: int
    morph: int
    weight: float


@dataclass(frozen=True, eq=False)
class Expression:
    """One expression of the character: the morphs it sets, and what it does to the face.

    ``face_displacement`` (V, 3) float64 is the face mesh's vertex offsets at weight 1.
    ``origin`` is "morph" (morph targets of that name) or "vrm" (a VRM expression's binds).
    """

    name: str
    bindings: tuple[Binding, ...]
    face_displacement: np.ndarray
    origin: str


@dataclass(frozen=True)
class PairingEntry:
    """What became of one authored name (a morph target name or a VRM expression).

    ``authored`` as in the file; ``origin`` "morph target", "VRM 0.x expression" or "VRM
    1.0 expression"; ``meshes`` the names of the meshes it moves; ``expression`` the
    normalised name it became (None if none); ``paired`` whether that expression has
    source points; ``reason`` why (which normalisation matched, or what was tried).
    """

    authored: str
    origin: str
    meshes: tuple[str, ...]
    expression: str | None
    paired: bool
    reason: str


@dataclass(frozen=True)
class PairingReport:
    """Every authored name, what it became, and whether it was paired with source points."""

    entries: tuple[PairingEntry, ...]
    source: str
    face_mesh: str

    @property
    def paired(self) -> tuple[str, ...]:
        """Names of the paired expressions, each once, in the report's order."""
        return tuple(dict.fromkeys(e.expression for e in self.entries if e.paired and e.expression))

    @property
    def unpaired(self) -> tuple[PairingEntry, ...]:
        return tuple(e for e in self.entries if not e.paired)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: ``{"source", "face_mesh", "paired": [...], "entries": [{...}]}``."""
        return {
            "source": self.source,
            "face_mesh": self.face_mesh,
            "paired": list(self.paired),
            "entries": [
                {
                    "authored": e.authored,
                    "origin": e.origin,
                    "meshes": list(e.meshes),
                    "expression": e.expression,
                    "paired": e.paired,
                    "reason": e.reason,
                }
                for e in self.entries
            ],
        }

    def lines(self) -> list[str]:
        """The report as text, paired first: one line per authored name."""
        out = [
            f"pairing with {self.source}: {len(self.paired)} expressions paired; "
            f"face mesh (vertex outputs) {self.face_mesh!r}"
        ]
        for entry in sorted(self.entries, key=lambda e: not e.paired):
            mark = "paired  " if entry.paired else "unpaired"
            target = f" -> {entry.expression}" if entry.expression else ""
            meshes = f" [{', '.join(entry.meshes)}]" if entry.meshes else ""
            out.append(
                f"  {mark} {entry.origin} {entry.authored!r}{target}{meshes}: {entry.reason}"
            )
        return out


@dataclass(frozen=True, eq=False)
class Character:
    """A loaded character (see ``load_character``).

    ``glb`` the file as one self-contained GLB; ``format`` "gltf", "vrm0" or "vrm1";
    ``meta`` the VRM licence meta (``vrm.vrm_meta``; {} for glTF); ``mesh_names`` one per
    glTF mesh; ``face_mesh`` the index of the mesh vertex outputs blend (the one with the
    most expressions bound; ties: more vertices, then the earlier); ``face_vertices``
    (V, 3) float64 and ``face_faces`` (F, 3) int64 its neutral in mesh space;
    ``expressions`` by normalised name in ARKit, VRM preset, then file order; ``report``
    the names as paired with facecast's generic ARKit source set; ``names`` the same
    entries before pairing.
    """

    glb: bytes
    format: Literal["gltf", "vrm0", "vrm1"]
    meta: dict[str, Any]
    mesh_names: tuple[str, ...]
    face_mesh: int
    face_vertices: np.ndarray
    face_faces: np.ndarray
    expressions: dict[str, Expression]
    report: PairingReport = field(repr=False)
    #: What each authored name became, before pairing (``report`` adds the pairing).
    names: tuple[PairingEntry, ...] = field(default=(), repr=False)

    def mesh_label(self, index: int) -> str:
        return self.mesh_names[index]


# -- reading the file -------------------------------------------------------------------


def _split_glb(data: bytes, label: str) -> tuple[bytes, bytes | None]:
    """The JSON and BIN chunks of a GLB, every length checked against the bytes there."""
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
    chunks: list[tuple[bytes, bytes]] = []
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
        chunks.append((kind, data[start : start + size]))
        pos = start + size + (-size) % 4
    if not chunks or chunks[0][0] != b"JSON":
        raise ExampleSetError(f"{label}: GLB without a JSON chunk first", code="bad_gltf")
    blob = next((c for k, c in chunks[1:] if k == b"BIN\0"), None)
    return chunks[0][1], blob


def _parse_json(text: bytes, label: str) -> dict[str, Any]:
    try:
        doc = json.loads(text)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ExampleSetError(
            f"{label}: glTF JSON is not readable ({exc})", code="bad_gltf"
        ) from None
    if not isinstance(doc, dict) or not str((doc.get("asset") or {}).get("version", "")).startswith(
        "2"
    ):
        raise ExampleSetError(f"{label}: not a glTF 2.0 document", code="bad_gltf")
    required = doc.get("extensionsRequired") or []
    blocked = [e for e in required if e in _UNSUPPORTED] if isinstance(required, list) else []
    if blocked:
        raise ExampleSetError(
            f"{label}: uses {blocked[0]}, which facecast cannot read: export without mesh "
            "compression or quantisation",
            code="unsupported_extension",
        )
    return doc


def _read_uri(uri: str, folder: Path | None, label: str, budget: list[int]) -> bytes:
    """A buffer's or image's bytes: a data URI, or a file inside the .gltf's folder."""
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1], validate=False)
        except (IndexError, binascii.Error, ValueError):
            raise ExampleSetError(f"{label}: malformed data URI", code="bad_gltf") from None
    relative = urllib.parse.unquote(uri)
    outside = (
        folder is None
        or urllib.parse.urlsplit(uri).scheme != ""
        or relative.startswith(("/", "\\"))
        or not (folder / relative).resolve().is_relative_to(folder.resolve())
    )
    if outside:
        where = "outside the .gltf's folder" if folder is not None else "outside the file"
        raise ExampleSetError(
            f"{label}: refers to {uri[:200]!r}, {where}: a character's files must travel with "
            "it (a .glb, or a .gltf with its files beside it)",
            code="external_uri",
        )
    assert folder is not None
    file = (folder / relative).resolve()
    try:
        size = file.stat().st_size
        if size > budget[0]:
            raise ExampleSetError(
                f"{label}: with {uri[:200]!r} the character exceeds {MAX_CHARACTER_BYTES} bytes",
                code="too_large",
            )
        budget[0] -= size
        return file.read_bytes()
    except OSError:
        raise ExampleSetError(
            f"{label}: file {uri[:200]!r} is missing", code="missing_file"
        ) from None


def _pack_gltf(doc: dict[str, Any], folder: Path | None, label: str, budget: list[int]) -> bytes:
    """The .gltf as one GLB: its buffers concatenated in one BIN chunk, images embedded."""
    buffers = doc.get("buffers") or []
    if not isinstance(buffers, list):
        raise ExampleSetError(f"{label}: buffers is not a list", code="bad_gltf")
    parts: list[bytes] = []
    starts: list[int] = []
    size = 0
    for buffer in buffers:
        uri = buffer.get("uri") if isinstance(buffer, dict) else None
        if not isinstance(uri, str):
            raise ExampleSetError(f"{label}: a .gltf buffer without a uri", code="bad_gltf")
        data = _read_uri(uri, folder, label, budget)
        starts.append(size)
        pad = (-len(data)) % 4  # keeps every buffer's views aligned as they were
        parts.append(data + b"\0" * pad)
        size += len(data) + pad
    views = doc.setdefault("bufferViews", [])
    for view in views:
        if (
            not isinstance(view, dict)
            or not isinstance(view.get("buffer"), int)
            or not 0 <= view["buffer"] < len(buffers)
        ):
            raise ExampleSetError(f"{label}: a bufferView names no buffer", code="bad_gltf")
        view["byteOffset"] = int(view.get("byteOffset", 0)) + starts[view["buffer"]]
        view["buffer"] = 0
    for image in doc.get("images") or []:
        if isinstance(image, dict) and isinstance(image.get("uri"), str):
            data = _read_uri(image.pop("uri"), folder, label, budget)
            image["mimeType"] = sniff_mime(data) or image.get("mimeType") or "image/png"
            views.append({"buffer": 0, "byteOffset": size, "byteLength": len(data)})
            image["bufferView"] = len(views) - 1
            parts.append(data + b"\0" * ((-len(data)) % 4))
            size += len(data) + (-len(data)) % 4
    if parts:
        doc["buffers"] = [{"byteLength": size}]
    else:
        doc.pop("buffers", None)
    return pack_glb(doc, b"".join(parts))


def _check_textures(doc: dict[str, Any], blob: bytes, label: str) -> None:
    """Refuse images whose headers declare more pixels than a viewer should decode."""
    views = doc.get("bufferViews") or []
    total = 0
    for number, image in enumerate(doc.get("images") or []):
        if not isinstance(image, dict):
            raise ExampleSetError(f"{label}: image {number} is not an object", code="bad_gltf")
        where = f"{label}: image {number}"
        if isinstance(image.get("uri"), str):
            data = _read_uri(image["uri"], None, label, [0])
        else:
            view_index = image.get("bufferView")
            try:
                view = views[int(view_index)]  # type: ignore[arg-type]
                start = int(view.get("byteOffset", 0))
                data = blob[start : start + int(view["byteLength"])]
            except (TypeError, IndexError, KeyError, ValueError, AttributeError):
                raise ExampleSetError(f"{where} names no bufferView", code="bad_gltf") from None
        width, height = image_size(data[: 1 << 20], where)
        if max(width, height) > MAX_TEXTURE_SIDE or width < 1 or height < 1:
            raise ExampleSetError(
                f"{where} declares {width} x {height} pixels; textures may be at most "
                f"{MAX_TEXTURE_SIDE} a side: scale it down",
                code="texture_too_large",
            )
        total += width * height
        if total > MAX_TEXTURE_PIXELS:
            raise ExampleSetError(
                f"{label}: its textures declare more than {MAX_TEXTURE_PIXELS} pixels in all; "
                "scale them down",
                code="texture_too_large",
            )


def _read_source(source: Path | bytes, label: str) -> tuple[dict[str, Any], bytes, bytes]:
    """``(JSON document, BIN chunk, the file as one GLB)``, bounded and self-contained."""
    folder: Path | None = None
    if isinstance(source, bytes | bytearray | memoryview):
        data = bytes(source)
    else:
        path = Path(source)
        try:
            if path.stat().st_size > MAX_CHARACTER_BYTES:
                raise ExampleSetError(
                    f"{label}: larger than {MAX_CHARACTER_BYTES} bytes", code="too_large"
                )
            data = path.read_bytes()
        except OSError:
            raise ExampleSetError(f"{label}: file not found", code="missing_file") from None
        if path.suffix.lower() == ".gltf":
            folder = path.parent
    if len(data) > MAX_CHARACTER_BYTES:
        raise ExampleSetError(f"{label}: larger than {MAX_CHARACTER_BYTES} bytes", code="too_large")
    if data[:4] == b"glTF":
        text, blob = _split_glb(data, label)
        doc = _parse_json(text, label)
        for buffer in (doc.get("buffers") or [])[1 if blob is not None else 0 :]:
            uri = buffer.get("uri") if isinstance(buffer, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                _read_uri(uri, None, label, [0])  # raises external_uri
        _check_textures(doc, blob or b"", label)
        return doc, blob or b"", data
    if data.lstrip()[:1] != b"{":
        raise ExampleSetError(
            f"{label}: not a glTF, GLB or VRM file (a character is a .glb, .vrm or .gltf)",
            code="bad_gltf",
        )
    doc = _parse_json(data, label)
    glb = _pack_gltf(doc, folder, label, [MAX_CHARACTER_BYTES - len(data)])
    text, blob = _split_glb(glb, label)
    doc = json.loads(text)
    _check_textures(doc, blob or b"", label)
    return doc, blob or b"", glb


# -- expressions ------------------------------------------------------------------------


@dataclass
class _Found:
    """An expression being gathered: its bindings and the authored names behind it."""

    bindings: list[Binding]
    origin: str


def _mesh_targets(doc: dict[str, Any], gltf: Any, label: str) -> tuple[list[int], list[list[str]]]:
    """Per mesh: its number of morph targets and their names, every target's vertex count
    checked against its primitive's (``morph_vertex_mismatch``)."""
    accessors = doc.get("accessors") or []

    def count(index: object) -> int:
        try:
            return int(accessors[index]["count"])  # type: ignore[call-overload]
        except (TypeError, IndexError, KeyError, ValueError):
            raise ExampleSetError(
                f"{label}: an attribute names no accessor", code="bad_gltf"
            ) from None

    counts: list[int] = []
    names: list[list[str]] = []
    for number, mesh in enumerate(doc.get("meshes") or []):
        primitives = mesh.get("primitives") if isinstance(mesh, dict) else None
        if not isinstance(primitives, list) or not primitives:
            raise ExampleSetError(f"{label}: mesh {number} has no primitives", code="bad_gltf")
        sizes = set()
        for prim in primitives:
            targets = (prim.get("targets") or []) if isinstance(prim, dict) else None
            attributes = prim.get("attributes") if isinstance(prim, dict) else None
            if not isinstance(targets, list) or not isinstance(attributes, dict):
                raise ExampleSetError(
                    f"{label}: mesh {number} has a malformed primitive", code="bad_gltf"
                )
            sizes.add(len(targets))
            vertices = count(attributes.get("POSITION"))
            for t, target in enumerate(targets):
                if (
                    isinstance(target, dict)
                    and "POSITION" in target
                    and count(target["POSITION"]) != vertices
                ):
                    raise ExampleSetError(
                        f"{label}: mesh {_mesh_name(doc, number)!r} morph target {t} has "
                        f"{count(target['POSITION'])} vertices, the mesh has {vertices}: "
                        "re-export it with the morph targets of this mesh",
                        code="morph_vertex_mismatch",
                    )
        if len(sizes) != 1:
            raise ExampleSetError(
                f"{label}: the primitives of mesh {_mesh_name(doc, number)!r} have different "
                "numbers of morph targets",
                code="bad_gltf",
            )
        m = sizes.pop()
        counts.append(m)
        names.append(target_names(gltf.meshes[number], m))
    return counts, names


def _mesh_name(doc: dict[str, Any], index: int) -> str:
    mesh = (doc.get("meshes") or [])[index]
    name = mesh.get("name") if isinstance(mesh, dict) else None
    return str(name)[:200] if isinstance(name, str) and name else f"mesh {index}"


def _morph_expressions(
    names: list[list[str]], mesh_names: tuple[str, ...]
) -> tuple[dict[str, _Found], list[PairingEntry]]:
    """Expressions from morph target names: one name on several meshes binds them all."""
    found: dict[str, _Found] = {}
    entries: dict[str, tuple[str | None, str, list[str]]] = {}
    halves: dict[tuple[str, str], list[Binding]] = {}
    for mesh, targets in enumerate(names):
        taken: set[str] = set()
        for morph, authored in enumerate(targets):
            match = normalise_name(authored)
            expression = match.name
            how = match.how
            if expression is None and (half := half_of(authored)) is not None:
                halves.setdefault(half, []).append(Binding(mesh, morph, 1.0))
            elif expression == "neutral" or authored == "neutral":
                expression, how = None, "the neutral is the rest pose, not an expression"
            elif expression is None and not authored.startswith("target_"):
                expression = authored  # kept under its own name: a source folder may pair it
            if expression is not None:
                if expression in taken:
                    how = f"another morph target of this mesh already gives {expression}"
                    expression = None
                else:
                    taken.add(expression)
                    found.setdefault(expression, _Found([], "morph")).bindings.append(
                        Binding(mesh, morph, 1.0)
                    )
            entry = entries.setdefault(authored, (expression, how, []))
            entry[2].append(mesh_names[mesh])
    for arkit in ("browInnerUp", "cheekPuff"):
        left, right = halves.get((arkit, "left"), []), halves.get((arkit, "right"), [])
        if arkit not in found and left and right:
            found[arkit] = _Found(left + right, "morph")
    report = []
    for authored, (expression, how, meshes) in entries.items():
        half = half_of(authored)
        if expression is None and half is not None and half[0] in found:
            expression, how = half[0], f"one side of {half[0]}, joined with the other"
        report.append(PairingEntry(authored, "morph target", tuple(meshes), expression, False, how))
    return found, report


def _vrm_entries(
    expressions: Iterable[VrmExpression], mesh_names: tuple[str, ...], found: dict[str, _Found]
) -> list[PairingEntry]:
    """VRM expressions into ``found`` (they replace morph-named ones); their report entries."""
    report = []
    for vrm in expressions:
        origin = "VRM 1.0 expression" if vrm.version == "vrm1" else "VRM 0.x expression"
        meshes = tuple(dict.fromkeys(mesh_names[m] for m, _, _ in vrm.binds))
        if vrm.preset is not None:
            name = vrm.preset if vrm.version == "vrm1" else vrm0_preset(vrm.preset)
            how = f"VRM {'1.0' if vrm.version == 'vrm1' else '0.x'} preset {vrm.preset!r}"
            if name is None or (vrm.version == "vrm1" and name not in VRM_PRESETS):
                name, how = normalise_name(vrm.name).name, "unknown preset, read by its name"
        else:
            match = normalise_name(vrm.name)
            name, how = match.name or vrm.name, match.how if match.name else "custom, own name"
        binds = [Binding(m, t, w) for m, t, w in vrm.binds if w > 0]
        if name is None or name == "neutral":
            report.append(
                PairingEntry(vrm.name, origin, meshes, None, False, "the neutral is the rest pose")
            )
            continue
        if not binds:
            report.append(
                PairingEntry(
                    vrm.name,
                    origin,
                    meshes,
                    None,
                    False,
                    "binds no morph target (material changes only)",
                )
            )
            continue
        found[name] = _Found(binds, "vrm")
        report.append(PairingEntry(vrm.name, origin, meshes, name, False, how))
    return report


def _face_mesh(found: dict[str, _Found], doc: dict[str, Any], gltf: Any, label: str) -> int:
    """The mesh with the most expressions bound; ties: more vertices, then the earlier."""
    meshes = doc.get("meshes") or []
    if not meshes:
        raise ExampleSetError(f"{label}: holds no mesh", code="no_mesh")
    bound = [0] * len(meshes)
    for expression in found.values():
        for mesh in {b.mesh for b in expression.bindings}:
            bound[mesh] += 1
    accessors = doc.get("accessors") or []
    vertices = [
        sum(int(accessors[p["attributes"]["POSITION"]]["count"]) for p in mesh["primitives"])
        for mesh in meshes
    ]
    return min(range(len(meshes)), key=lambda i: (-bound[i], -vertices[i], i))


def pair_report(
    entries: Iterable[PairingEntry],
    paired: dict[str, str],
    unpaired: dict[str, str],
    *,
    source: str,
    face_mesh: str,
) -> PairingReport:
    """The entries with ``paired``/``reason`` set from ``{expression: why}`` tables: an entry
    whose expression is in ``paired`` is paired; one in ``unpaired`` gets that reason."""
    out = []
    for entry in entries:
        name = entry.expression
        if name is not None and name in paired:
            out.append(
                PairingEntry(
                    entry.authored,
                    entry.origin,
                    entry.meshes,
                    name,
                    True,
                    f"{entry.reason}; {paired[name]}",
                )
            )
        elif name is not None and name in unpaired:
            out.append(
                PairingEntry(
                    entry.authored,
                    entry.origin,
                    entry.meshes,
                    name,
                    False,
                    f"{entry.reason}; {unpaired[name]}",
                )
            )
        else:
            out.append(entry)
    return PairingReport(tuple(out), source, face_mesh)


def load_character(source: Path | bytes, *, label: str = "character") -> Character:
    """Read a .glb, .vrm (VRM 0.x or 1.0) or .gltf (with its files beside it) as authored.

    Parameters
    ----------
    source : Path or bytes
        The file, or its bytes (a .gltf given as bytes must embed its buffers and images).
    label : str
        What errors call the file; never a path is put in a message.

    Returns
    -------
    Character
        Expressions from every mesh's morph targets (one name on several meshes is one
        expression binding them all) and from the VRM expressions' morph binds (which
        replace a morph-named expression of the same normalised name), names normalised by
        ``expression_names.normalise_name``; the report pairs them with the generic set.

    Raises
    ------
    ExampleSetError
        ``truncated_file``, ``bad_gltf``, ``external_uri`` (a URI outside the .gltf's
        folder, or any external URI in a GLB or bytes), ``texture_too_large`` (a header
        declaring more than ``MAX_TEXTURE_SIDE`` a side or ``MAX_TEXTURE_PIXELS`` in all),
        ``bad_image``, ``bad_vrm_bind``, ``morph_vertex_mismatch``, ``too_large``,
        ``unsupported_extension``, ``no_mesh``, ``missing_file``.
    """
    doc, _, glb = _read_source(source, label)
    gltf = load_document(glb, label)
    try:
        counts, names = _mesh_targets(doc, gltf, label)
        mesh_names = tuple(_mesh_name(doc, i) for i in range(len(counts)))
        found, entries = _morph_expressions(names, mesh_names)
        vrm_entries = _vrm_entries(vrm_expressions(doc, counts, label), mesh_names, found)
        from_vrm = {e.expression for e in vrm_entries if e.expression}
        entries = [
            PairingEntry(
                e.authored,
                e.origin,
                e.meshes,
                e.expression,
                False,
                e.reason + " (bound through the VRM expression of that name)",
            )
            if e.expression in from_vrm
            else e
            for e in entries
        ] + vrm_entries
        face = _face_mesh(found, doc, gltf, label)
        reader = BufferReader(gltf, None, label)
        vertices, faces, deltas, _ = read_mesh(gltf.meshes[face], reader, label)
    except ExampleSetError:
        raise
    except (AttributeError, TypeError, KeyError, IndexError, ValueError) as exc:
        raise ExampleSetError(
            f"{label}: malformed glTF ({type(exc).__name__})", code="bad_gltf"
        ) from None
    expressions = {}
    for name in sorted(found, key=lambda n: _ORDER.get(n, len(_ORDER))):
        bindings = tuple(found[name].bindings)
        displacement = np.zeros_like(vertices)
        for b in bindings:
            if b.mesh == face:
                displacement += b.weight * deltas[b.morph]
        displacement.flags.writeable = False
        expressions[name] = Expression(name, bindings, displacement, found[name].origin)
    generic = generic_sources()
    paired = {
        n: "paired with the generic set"
        for n in expressions
        if generic.source_points(n) is not None
    }
    unpaired = {
        n: "no source points in the generic ARKit set" for n in expressions if n not in paired
    }
    vertices.flags.writeable = False
    return Character(
        glb=glb,
        format=vrm_format(doc),
        meta=vrm_meta(doc),
        mesh_names=mesh_names,
        face_mesh=face,
        face_vertices=vertices,
        face_faces=faces,
        expressions=expressions,
        names=tuple(entries),
        report=pair_report(
            entries, paired, unpaired, source=GENERIC_ATTRIBUTION, face_mesh=mesh_names[face]
        ),
    )


# The contract with the server names character_example_set here; it lives in
# character_examples (which imports this module), so it is re-exported once both exist.
from .character_examples import character_example_set  # noqa: E402

"""A character as its author made it: a .glb, .vrm or .gltf read into its expressions.

Reads the file once, bounded (truncated files, external URIs, texture bombs, broken VRM
binds are named errors), keeps it byte for byte as one GLB and finds its expressions on
every mesh and in its VRM binds, names normalised (``expression_names``). It does not fit,
pair with source points (``character_examples``, whose ``character_example_set`` is
re-exported here) or render; docs/characters.md explains it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ExampleSetError
from ..io.gltf import BufferReader, GltfLimits, read_mesh, target_names
from .character_examples import character_example_set, generic_pairing
from .character_file import (
    MAX_CHARACTER_BYTES,
    MAX_TEXTURE_PIXELS,
    MAX_TEXTURE_SIDE,
    read_character_file,
)
from .character_model import (
    Binding,
    Character,
    Expression,
    PairingEntry,
    PairingReport,
    pair_report,
)
from .expression_names import ARKIT_NAMES, VRM_PRESETS, half_of, normalise_name, vrm0_preset
from .generic import GENERIC_ATTRIBUTION
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

#: What ``gltf.read_mesh`` gives: vertices, faces, morph deltas, target names.
MeshData = tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]

# Expression order: ARKit's, then VRM's presets, then the rest as found.
_ORDER = {name: i for i, name in enumerate((*ARKIT_NAMES, *VRM_PRESETS))}

#: An expression moves nothing visible when no bound morph target (times its bind weight)
#: moves a vertex by more than this fraction of its mesh's bounding-box diagonal: 30 µm on
#: a 30 cm head, a tenth of a pixel with the face 1000 px tall. Exported files carry such
#: targets (VRoid's Perfect Sync ``jawOpen`` and ``tongueOut`` written as zeros): paired,
#: a rig would give them the weight of a motion the character never shows.
STILL_RELATIVE = 1e-4
#: Vertices of a morph target measured at a time by that check (1.5 MB of float64).
_STILL_CHUNK = 1 << 16


# -- expressions ------------------------------------------------------------------------


@dataclass
class _Found:
    """An expression being gathered: its bindings and the authored names behind it."""

    bindings: list[Binding]
    origin: str


def _mesh_targets(doc: dict[str, Any], label: str) -> tuple[list[int], list[list[str]]]:
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
        names.append(target_names(mesh, m))
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
            if vrm.binds:
                why = "its morph binds all have weight 0: it moves nothing"
            elif vrm.materials:
                why = "binds no morph target (material changes only)"
            else:
                why = "binds nothing (no morph target, no material): an empty expression"
            report.append(PairingEntry(vrm.name, origin, meshes, None, False, why))
            continue
        found[name] = _Found(binds, "vrm")
        report.append(PairingEntry(vrm.name, origin, meshes, name, False, how))
    return report


def _face_mesh(found: dict[str, _Found], doc: dict[str, Any], label: str) -> int:
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


def _still_expressions(found: dict[str, _Found], read: Callable[[int], MeshData]) -> dict[str, str]:
    """``{name: why}`` of the expressions no bound morph target moves visibly
    (``STILL_RELATIVE``); ``read(mesh)`` gives a mesh's vertices, faces and deltas."""
    largest: dict[int, tuple[np.ndarray, float]] = {}

    def moves(binding: Binding) -> float:
        if binding.mesh not in largest:
            vertices, _, deltas, _ = read(binding.mesh)
            extent = float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
            # One morph and _STILL_CHUNK vertices at a time, in float64: a temporary of
            # all (M, V) squared lengths was the peak of a large upload's read
            # (norm(axis=2) made one of (M, V, 3)), then the float64 copy of a morph of a
            # 1 M-vertex face and its squares (46 MB).
            offsets = np.zeros(len(deltas) if deltas.size else 0)
            for t in range(len(offsets)):
                most = 0.0
                for at in range(0, deltas.shape[1], _STILL_CHUNK):
                    one = deltas[t : t + 1, at : at + _STILL_CHUNK].astype(np.float64)
                    most = max(most, float(np.einsum("mvk,mvk->mv", one, one).max()))
                offsets[t] = np.sqrt(most)
            largest[binding.mesh] = (offsets, extent)
        offsets, extent = largest[binding.mesh]
        if binding.morph >= offsets.size:
            return 0.0
        return float(binding.weight * offsets[binding.morph]) / max(extent, 1e-30)

    still = {}
    for name, expression in found.items():
        share = max((moves(b) for b in expression.bindings), default=0.0)
        if share <= STILL_RELATIVE:
            still[name] = (
                f"moves no vertex visibly (its largest offset is {share:.1g} of its mesh's "
                f"size, at most {STILL_RELATIVE:g}): not paired, a rig would drive nothing"
            )
    return still


def load_character(
    source: Path | bytes, *, label: str = "character", limits: GltfLimits | None = None
) -> Character:
    """Read a .glb, .vrm (VRM 0.x or 1.0) or .gltf (with its files beside it) as authored.

    Parameters
    ----------
    source : Path or bytes
        The file, or its bytes (a .gltf given as bytes must embed its buffers and images).
    label : str
        What errors call the file; never a path is put in a message.
    limits : GltfLimits, optional
        The most the file may declare (``gltf_check``; its defaults without).

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
        ``gltf_exceeds_limits`` (a count over ``limits``, checked before anything is read),
        ``bad_compression`` (meshopt or Draco data that does not decode to what its
        accessors declare), ``no_mesh``, ``missing_file``.
    """
    try:
        return _load(source, label, limits)
    except ExampleSetError:
        raise
    except (AttributeError, TypeError, KeyError, IndexError, ValueError, RecursionError) as exc:
        # A wrongly typed JSON field anywhere (dataclasses-json and our own reads take
        # what they are given): say the file is malformed, never crash.
        raise ExampleSetError(
            f"{label}: malformed glTF ({type(exc).__name__})", code="bad_gltf"
        ) from None


def _driven_through_vrm(
    entries: list[PairingEntry],
    names: list[list[str]],
    found: dict[str, _Found],
    paired: dict[str, str],
) -> list[PairingEntry]:
    """Morph-target entries whose own name pairs with nothing but whose morph a paired VRM
    expression binds (a VRM ``A`` binding ``vrc.v_aa``) say so: their motion is live,
    driven by that expression's weight, though the name itself has no source points."""
    through: dict[str, list[str]] = {}
    for name, expression in found.items():
        if expression.origin != "vrm" or name not in paired:
            continue
        for b in expression.bindings:
            authored = names[b.mesh][b.morph]
            if name not in through.setdefault(authored, []):
                through[authored].append(name)
    out = []
    for e in entries:
        via = through.get(e.authored, [])
        if e.origin == "morph target" and e.expression not in paired and via:
            listed = ", ".join(repr(v) for v in via)
            e = replace(e, reason=f"{e.reason}; moved through the paired VRM expression {listed}")
        out.append(e)
    return out


def _load(source: Path | bytes, label: str, limits: GltfLimits | None) -> Character:
    """``load_character`` but for turning stray exceptions into ``bad_gltf``."""
    document, glb = read_character_file(source, label, limits)
    doc = document.json
    counts, names = _mesh_targets(doc, label)
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
    reader = BufferReader(document, label, limits)
    reader.decode_all()  # a compressed part that does not decode is refused now (bounded)
    meshes: dict[int, MeshData] = {}

    def read(index: int) -> MeshData:
        """Each mesh read once: the still check and the face share the face's read."""
        if index not in meshes:
            meshes[index] = read_mesh(doc["meshes"][index], reader, label)
        return meshes[index]

    still = _still_expressions(found, read)
    entries = [
        dataclasses.replace(e, reason=f"{e.reason}; {still[e.expression]}")
        if e.expression in still
        else e
        for e in entries
    ]
    found = {name: f for name, f in found.items() if name not in still}
    face = _face_mesh(found, doc, label)
    vertices, faces, deltas, _ = read(face)
    meshes.clear()
    on_face = {name: [b for b in e.bindings if b.mesh == face] for name, e in found.items()}
    # An expression of one morph at weight 1 is a view of it; a VRM expression mixing
    # morphs or weighting one needs an array of its own: bounded as the morphs are, or
    # a thousand binds at weight 0.5 would each allocate the whole face.
    mixed = sum(1 for b in on_face.values() if len(b) > 1 or (b and b[0].weight != 1.0))
    limit = (limits or GltfLimits()).morph_values
    order = sorted(found, key=lambda n: _ORDER.get(n, len(_ORDER)))
    paired, unpaired = generic_pairing(order)
    # The fit's example set holds the face once per paired expression (float64 rows,
    # character_example_set): bounded as morph targets are, or VRM expressions binding
    # one morph under fifty names would each cost the whole face (a 1 M-vertex face: GBs).
    if len(paired) * len(vertices) > limit:
        raise ExampleSetError(
            f"{label}: {len(paired)} expressions paired on a {len(vertices)}-vertex face "
            f"declare more than {limit} values to fit, each a copy of the face (limit "
            "max_gltf_morph_values)",
            code="gltf_exceeds_limits",
        )
    # Each mixed expression is a float64 array of the face (24 bytes a vertex, a morph
    # value's twice), held with the face's morph targets (float32, or float64 when
    # quantised): together bounded as the file's morph targets are.
    held = deltas.size // 3 * deltas.itemsize // 4 + 2 * mixed * len(vertices)
    if mixed and held > limit:
        raise ExampleSetError(
            f"{label}: {mixed} expressions mixing morph targets of a {len(vertices)}-vertex "
            f"face, each a float64 copy of it, with its {len(deltas)} morph targets declare "
            f"more than {limit} values (limit max_gltf_morph_values; a float64 value counts "
            "twice)",
            code="gltf_exceeds_limits",
        )
    unmoved = np.zeros_like(vertices)
    unmoved.flags.writeable = False
    expressions = {}
    for name in order:
        bindings = tuple(found[name].bindings)
        mine = on_face[name]
        if not mine:
            displacement = unmoved  # moves other meshes only: one shared array of zeros
        elif len(mine) == 1 and mine[0].weight == 1.0:
            displacement = deltas[mine[0].morph]  # a view: most expressions are one morph
        else:
            displacement = np.zeros_like(vertices)
            for b in mine:  # in float64 whatever the deltas' dtype (read_mesh)
                displacement += b.weight * deltas[b.morph].astype(np.float64)
        displacement.flags.writeable = False
        expressions[name] = Expression(name, bindings, displacement, found[name].origin)
    reported = _driven_through_vrm(entries, names, found, paired)
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
            reported, paired, unpaired, source=GENERIC_ATTRIBUTION, face_mesh=mesh_names[face]
        ),
    )

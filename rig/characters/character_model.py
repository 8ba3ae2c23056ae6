"""The types a loaded character is made of: its bindings, expressions and pairing report.

Plain frozen values shared by ``character`` (which builds them from a file) and
``character_examples`` (which pairs them with source points); no file I/O, no pairing rule.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

__all__ = ["Binding", "Character", "Expression", "PairingEntry", "PairingReport", "pair_report"]


@dataclass(frozen=True)
class Binding:
    """Morph target ``morph`` of glTF mesh ``mesh`` (its index in ``meshes``) at ``weight``."""

    mesh: int
    morph: int
    weight: float


@dataclass(frozen=True, eq=False)
class Expression:
    """One expression of the character: the morphs it sets, and what it does to the face.

    ``face_displacement`` (V, 3) is the face mesh's vertex offsets at weight 1: float32 for
    one float32 morph target at weight 1 (a view of the deltas as stored), else float64.
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
    (V, 3) float64 and ``face_faces`` (F, 3) int32 its neutral in mesh space;
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
        for table, paired_ in ((paired, True), (unpaired, False)):
            if name is not None and name in table:
                reason = f"{entry.reason}; {table[name]}"
                entry = dataclasses.replace(entry, paired=paired_, reason=reason)
                break
        out.append(entry)
    return PairingReport(tuple(out), source, face_mesh)

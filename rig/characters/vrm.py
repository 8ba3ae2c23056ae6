"""VRM 0.x and 1.0 extensions of a glTF document: expression binds and the licence meta.

Reads the ``VRM`` (0.x) and ``VRMC_vrm`` (1.0) blocks of an already-parsed glTF JSON
document into plain values, checking every bind against the document's meshes; it does
not read buffers, normalise names against ARKit or decide pairing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

from ..errors import ExampleSetError

__all__ = [
    "MAX_VRM_BINDS",
    "MAX_VRM_EXPRESSIONS",
    "VrmExpression",
    "vrm_expressions",
    "vrm_format",
    "vrm_meta",
]

#: Expressions a VRM may declare, and morph binds in all of them: far above VRoid's ~60
#: clips, so only a hostile file meets them.
MAX_VRM_EXPRESSIONS = 1000
MAX_VRM_BINDS = 20_000
# Meta strings are shown in viewers: longer ones are cut, lists shortened.
_MAX_TEXT = 2000
_MAX_ITEMS = 50


@dataclass(frozen=True)
class VrmExpression:
    """One VRM expression: ``name`` as authored, ``preset`` (VRM 1.0 name) or None for a
    custom one, and its morph binds as ``(mesh index, morph index, weight in [0, 1])``;
    ``materials``: whether it changes materials too (VRM 1.0 ``materialColorBinds`` or
    ``textureTransformBinds``, VRM 0.x ``materialValues``), for the pairing report."""

    name: str
    preset: str | None
    binds: tuple[tuple[int, int, float], ...]
    version: Literal["vrm0", "vrm1"]
    materials: bool = False


def _has_items(expression: object, *keys: str) -> bool:
    return isinstance(expression, dict) and any(
        isinstance(expression.get(k), list) and expression.get(k) for k in keys
    )


def vrm_format(doc: dict[str, Any]) -> Literal["gltf", "vrm0", "vrm1"]:
    """Which VRM the document is, from its top-level extensions (plain glTF otherwise)."""
    extensions = doc.get("extensions")
    if isinstance(extensions, dict):
        if isinstance(extensions.get("VRMC_vrm"), dict):
            return "vrm1"
        if isinstance(extensions.get("VRM"), dict):
            return "vrm0"
    return "gltf"


def _bad(label: str, message: str) -> ExampleSetError:
    return ExampleSetError(f"{label}: {message}", code="bad_vrm_bind")


def _int(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _check_bind(
    label: str,
    where: str,
    mesh: int | None,
    index: object,
    weight: object,
    targets: list[int],
    full: float,
) -> tuple[int, int, float]:
    """``(mesh, morph, weight / full)`` of a bind whose weight runs from 0 to ``full``."""
    morph = _int(index)
    if mesh is None or not 0 <= mesh < len(targets):
        raise _bad(label, f"{where} binds mesh {mesh!r}, the file has {len(targets)} meshes")
    if morph is None or not 0 <= morph < targets[mesh]:
        raise _bad(
            label,
            f"{where} binds morph target {index!r} of mesh {mesh}, which has {targets[mesh]}",
        )
    if not isinstance(weight, int | float) or isinstance(weight, bool) or not math.isfinite(weight):
        raise _bad(label, f"{where} has weight {weight!r}, not a number")
    if not 0.0 <= weight <= full:
        raise _bad(label, f"{where} has weight {weight!r} outside [0, {full:g}]")
    return mesh, morph, float(weight) / full


def vrm_expressions(
    doc: dict[str, Any], targets: list[int], label: str
) -> tuple[VrmExpression, ...]:
    """The document's VRM expressions with their morph binds, checked.

    Parameters
    ----------
    doc : dict
        The glTF JSON document.
    targets : list of int
        Number of morph targets of each mesh (``meshes[i]``).
    label : str
        Names the file in errors (never a path on the server).

    Raises
    ------
    ExampleSetError
        ``bad_vrm_bind``: a bind naming a node without a mesh, a mesh or morph target out of
        range, a weight that is not a number in [0, 1] (VRM 1.0) or [0, 100] (VRM 0.x), or
        more expressions or binds than the limits.
    """
    kind = vrm_format(doc)
    if kind == "vrm1":
        found = _vrm1(doc["extensions"]["VRMC_vrm"], doc, targets, label)
    elif kind == "vrm0":
        found = _vrm0(doc["extensions"]["VRM"], targets, label)
    else:
        return ()
    if sum(len(e.binds) for e in found) > MAX_VRM_BINDS:
        raise _bad(label, f"more than {MAX_VRM_BINDS} morph binds in its VRM expressions")
    return found


def _vrm1(
    block: dict[str, Any], doc: dict[str, Any], targets: list[int], label: str
) -> tuple[VrmExpression, ...]:
    expressions = block.get("expressions") or {}
    nodes = doc.get("nodes") or []
    if not isinstance(expressions, dict) or not isinstance(nodes, list):
        raise _bad(label, "VRMC_vrm.expressions is not an object")
    found: list[VrmExpression] = []
    for group in ("preset", "custom"):
        table = expressions.get(group) or {}
        if not isinstance(table, dict):
            raise _bad(label, f"VRMC_vrm.expressions.{group} is not an object")
        if len(found) + len(table) > MAX_VRM_EXPRESSIONS:
            raise _bad(label, f"more than {MAX_VRM_EXPRESSIONS} VRM expressions")
        for name, expression in table.items():
            where = f"VRM expression {group}.{name}"
            binds = (
                expression.get("morphTargetBinds") or [] if isinstance(expression, dict) else None
            )
            if not isinstance(binds, list):
                raise _bad(label, f"{where}: morphTargetBinds is not a list")
            checked = []
            for number, bind in enumerate(binds):
                at = f"{where} bind {number}"
                if not isinstance(bind, dict):
                    raise _bad(label, f"{at} is not an object")
                node = _int(bind.get("node"))
                if node is None or not 0 <= node < len(nodes) or not isinstance(nodes[node], dict):
                    raise _bad(
                        label, f"{at} names node {bind.get('node')!r}, the file has {len(nodes)}"
                    )
                mesh = _int(nodes[node].get("mesh"))
                if mesh is None:
                    raise _bad(label, f"{at} names node {node}, which holds no mesh")
                weight = bind.get("weight", 1.0)
                checked.append(
                    _check_bind(label, at, mesh, bind.get("index"), weight, targets, 1.0)
                )
            found.append(
                VrmExpression(
                    str(name),
                    str(name) if group == "preset" else None,
                    tuple(checked),
                    "vrm1",
                    _has_items(expression, "materialColorBinds", "textureTransformBinds"),
                )
            )
    return tuple(found)


def _vrm0(block: dict[str, Any], targets: list[int], label: str) -> tuple[VrmExpression, ...]:
    master = block.get("blendShapeMaster") or {}
    groups = master.get("blendShapeGroups") or [] if isinstance(master, dict) else None
    if not isinstance(groups, list):
        raise _bad(label, "VRM.blendShapeMaster.blendShapeGroups is not a list")
    if len(groups) > MAX_VRM_EXPRESSIONS:
        raise _bad(label, f"more than {MAX_VRM_EXPRESSIONS} VRM blend shape groups")
    found: list[VrmExpression] = []
    for number, group in enumerate(groups):
        if not isinstance(group, dict):
            raise _bad(label, f"VRM blend shape group {number} is not an object")
        name = str(group.get("name") or f"group {number}")
        where = f"VRM blend shape group {name!r}"
        binds = group.get("binds") or []
        if not isinstance(binds, list):
            raise _bad(label, f"{where}: binds is not a list")
        checked = []
        for index, bind in enumerate(binds):
            at = f"{where} bind {index}"
            if not isinstance(bind, dict):
                raise _bad(label, f"{at} is not an object")
            weight = bind.get("weight", 100.0)
            # VRM 0.x weights are percent.
            checked.append(
                _check_bind(
                    label, at, _int(bind.get("mesh")), bind.get("index"), weight, targets, 100.0
                )
            )
        preset = group.get("presetName")
        found.append(
            VrmExpression(
                name,
                str(preset) if isinstance(preset, str) and preset.lower() != "unknown" else None,
                tuple(checked),
                "vrm0",
                _has_items(group, "materialValues"),
            )
        )
    return tuple(found)


def _text(value: object) -> str | None:
    if isinstance(value, str) and value:
        return value[:_MAX_TEXT]
    return None


def vrm_meta(doc: dict[str, Any]) -> dict[str, Any]:
    """The VRM licence meta, normalised across 0.x and 1.0 (``{}`` for plain glTF).

    Keys: ``name``, ``version``, ``authors`` (list), ``contact``, ``licence`` (VRM 1.0: its
    licence URL's name, VRM 0.x: ``licenseName``), ``licence_url``, ``redistribution``
    (True, False, or None when the licence does not say: a VRM 0.x "Other" licence),
    ``commercial`` (VRM 1.0 ``commercialUsage``, VRM 0.x ``commercialUssageName``),
    ``avatar_permission``, ``modification``, ``credit``, ``vrm`` ("0.x" or "1.0"). Strings
    are cut at 2000 characters, lists at 50 items; missing values are None.
    """
    kind = vrm_format(doc)
    if kind == "gltf":
        return {}
    if kind == "vrm1":
        meta = doc["extensions"]["VRMC_vrm"].get("meta")
        meta = meta if isinstance(meta, dict) else {}
        authors = meta.get("authors")
        redistribution = meta.get("allowRedistribution")
        url = _text(meta.get("licenseUrl"))
        return {
            "vrm": "1.0",
            "name": _text(meta.get("name")),
            "version": _text(meta.get("version")),
            "authors": [a[:_MAX_TEXT] for a in authors[:_MAX_ITEMS] if isinstance(a, str)]
            if isinstance(authors, list)
            else [],
            "contact": _text(meta.get("contactInformation")),
            "licence": "VRM Public License 1.0" if url and "vrm.dev/licenses/1.0" in url else url,
            "licence_url": url,
            "redistribution": redistribution if isinstance(redistribution, bool) else False,
            "commercial": _text(meta.get("commercialUsage")),
            "avatar_permission": _text(meta.get("avatarPermission")),
            "modification": _text(meta.get("modification")),
            "credit": _text(meta.get("creditNotation")),
        }
    meta = doc["extensions"]["VRM"].get("meta")
    meta = meta if isinstance(meta, dict) else {}
    licence = _text(meta.get("licenseName"))
    author = _text(meta.get("author"))
    return {
        "vrm": "0.x",
        "name": _text(meta.get("title")),
        "version": _text(meta.get("version")),
        "authors": [author] if author else [],
        "contact": _text(meta.get("contactInformation")),
        "licence": licence,
        "licence_url": _text(meta.get("otherLicenseUrl")),
        # Every VRM 0.x licence but these two lets the file be passed on (CC ones with terms).
        "redistribution": None
        if licence in (None, "Other")
        else licence != "Redistribution_Prohibited",
        "commercial": _text(meta.get("commercialUssageName")),
        "avatar_permission": _text(meta.get("allowedUserName")),
        "modification": None,
        "credit": None,
    }

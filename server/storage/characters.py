"""A rig's character file as stored beside it: the uploaded glTF/VRM and what the pages need.

``<id>.character`` holds a short header, a JSON record (format, VRM meta, bindings by
expression name) and the GLB as uploaded (a .gltf upload packed into one GLB). Written in
one atomic write by ``RigStore.put_rig``; no HTTP here.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

from ..names import PERFORMER_SEPARATOR

__all__ = [
    "CHARACTER_SUFFIX",
    "PackedCharacter",
    "StoredCharacter",
    "audience",
    "base_id",
    "character_not_served",
    "character_view",
    "looks_like_character",
    "pack_character",
    "unpack_character",
]

#: The character file beside ``<id>.rig``; deleted with the rig and by a rig stored without one.
CHARACTER_SUFFIX = ".character"
_MAGIC = b"FCCH"
_VERSION = 1
_HEADER = struct.Struct("<4sII")  # magic, version, JSON byte length


@dataclass(frozen=True)
class StoredCharacter:
    """A stored character: ``glb`` as uploaded and its record.

    ``record``: ``{"format": "gltf"|"vrm0"|"vrm1", "meta": {...}, "rights_holder": bool,
    "bindings": {name: [[mesh, morph, weight], ...]}}`` — bindings by the rig's example
    (expression) names, ``mesh`` the index in the glTF ``meshes`` array, ``morph`` the
    morph target's index; ``rights_holder`` (absent in older records: false) the
    uploader's declaration that they may show it to everyone.
    """

    glb: bytes
    record: dict[str, Any]

    @property
    def format(self) -> str:
        return str(self.record.get("format", "gltf"))

    @property
    def meta(self) -> dict[str, Any]:
        meta = self.record.get("meta") or {}
        return dict(meta)

    @property
    def rights_holder(self) -> bool:
        """Whether the uploader declared they hold the rights to show it (``rights_holder``)."""
        return self.record.get("rights_holder") is True

    def bindings_for(self, names: Sequence[str]) -> list[list[dict[str, Any]]]:
        """One list of ``{"mesh", "morph", "weight"}`` per weight, in ``names``' order.

        A name the record does not bind (the neutral) gets an empty list.
        """
        bound: dict[str, list[list[Any]]] = self.record.get("bindings", {})
        return [
            [{"mesh": int(m), "morph": int(t), "weight": float(w)} for m, t, w in bound.get(n, [])]
            for n in names
        ]


def base_id(rig_id: str) -> str:
    """The rig whose character ``rig_id`` shows: ``ann-face@bo`` shows ``ann-face``'s."""
    return rig_id.split(PERFORMER_SEPARATOR, 1)[0]


def character_view(
    rig_id: str, names: Sequence[str], stored: StoredCharacter | None
) -> dict[str, Any] | None:
    """The ``character`` of ``GET /v1/rigs/{id}`` (format, url, meta, bindings per weight
    in ``names``' order); ``None`` for a rig without one."""
    if stored is None:
        return None
    return {
        "format": stored.format,
        "url": f"/v1/rigs/{rig_id}/character.glb",
        "meta": stored.meta,
        **audience(stored.meta, rights_holder=stored.rights_holder),
        "bindings": stored.bindings_for(names),
    }


def audience(meta: dict[str, Any], *, rights_holder: bool) -> dict[str, Any]:
    """Who is shown the character file under its licence, for the uploader and the pages.

    ``{"rights_holder": bool, "shown_to": "everyone" | "token_holders", "licence_note":
    str}``: ``token_holders`` when ``character_not_served`` withholds it from anonymous
    callers (the rule is that function's), the note saying why and what to do.
    """
    withheld = character_not_served(meta, anonymous=True, rights_holder=rights_holder)
    if withheld:
        note = (
            "shown only to viewers with a token: its VRM licence forbids redistribution "
            "(viewers without a token see the rig's plain mesh). If you hold the rights to "
            "show it, upload it again with --rights-holder (?rights_holder=true)"
        )
    elif meta.get("redistribution") is False:
        note = (
            "shown to everyone: its VRM licence forbids redistribution, and the uploader "
            "declared they hold the rights to show it (rights_holder)"
        )
    elif meta.get("redistribution") is True:
        note = "shown to everyone: its VRM licence allows redistribution"
    elif meta.get("vrm"):
        note = "shown to everyone: its VRM licence does not forbid redistribution"
    else:
        note = "shown to everyone: a glTF file carries no licence to hold it back"
    return {
        "rights_holder": rights_holder,
        "shown_to": "token_holders" if withheld else "everyone",
        "licence_note": note,
    }


#: ``pack_character``'s parts: the header with the record, then the GLB.
PackedCharacter = tuple[bytes, bytes]


def pack_character(glb: bytes, record: dict[str, Any]) -> PackedCharacter:
    """The bytes of ``<id>.character`` for ``glb`` and its JSON-able ``record``: the header
    with the record, then ``glb`` itself, to be written one after the other
    (``write_atomically`` takes both): joined, they would copy the GLB, most of a 64 MiB
    upload, while the fitted rig is held (SERVER.md "What an upload can cost")."""
    text = json.dumps(record, separators=(",", ":"), allow_nan=False).encode()
    return _HEADER.pack(_MAGIC, _VERSION, len(text)) + text, glb


def unpack_character(source: BinaryIO, *, with_glb: bool = True) -> StoredCharacter:
    """Read ``pack_character``'s bytes from ``source``; ``ValueError`` for anything else.

    ``with_glb=False`` reads the record alone (``glb`` is then empty): a rig's description
    needs no megabytes of mesh and texture.
    """
    header = source.read(_HEADER.size)
    if len(header) < _HEADER.size:
        raise ValueError("character file is truncated")
    magic, version, length = _HEADER.unpack(header)
    if magic != _MAGIC or version != _VERSION:
        raise ValueError("not a facecast character file (or a newer version)")
    text = source.read(length)
    if len(text) < length:
        raise ValueError("character file is truncated")
    try:
        record = json.loads(text)
    except ValueError:
        raise ValueError("character record is not JSON") from None
    if not isinstance(record, dict):
        raise ValueError("character record is not a JSON object")
    return StoredCharacter(source.read() if with_glb else b"", record)


def character_not_served(
    meta: dict[str, Any], *, anonymous: bool, rights_holder: bool = False
) -> bool:
    """Whether the file is withheld: a VRM whose meta forbids redistribution, to an anonymous caller.

    ``redistribution`` False (VRM 1.0 ``allowRedistribution: false``, VRM 0.x licence
    ``Redistribution_Prohibited``) withholds the file from callers without a token (a
    server with auth off has only those); a token holding a read role gets it. Unknown
    (``None``) or plain glTF: served. ``rights_holder``: the uploader (admin) declared
    they hold the rights to show it (``?rights_holder=true``): served to everyone.
    """
    return anonymous and not rights_holder and meta.get("redistribution") is False


def looks_like_character(data: bytes) -> bool:
    """Whether an upload is a glTF binary (.glb, .vrm) or a .gltf JSON, not a rig or archive."""
    if data[:4] == b"glTF":
        return True
    head = data[:4096].lstrip()
    return head[:1] == b"{" and b'"asset"' in head

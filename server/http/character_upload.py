"""A character upload's body read into a ``Character`` (a .glb/.vrm as it is, or an archive
holding one, with a transfer's ``markers.txt`` beside it), and what is kept and told of it.

Runs in a worker thread (parsing and unpacking are CPU and disk work); errors are
``ArchiveError``s and the engine's ``RigError``s with the upload's paths hidden.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from facecast.rig.characters.character import Character, PairingReport, load_character
from facecast.rig.io.gltf import GltfLimits
from facecast.rig.transfer import read_markers

from ..errors import ApiError, upload_paths_hidden
from ..settings import Settings
from ..storage.archive import ArchiveError, ArchiveLimits, extract_archive

__all__ = [
    "CHARACTER_SUFFIXES",
    "MARKERS_FILE",
    "character_record",
    "check_character_size",
    "gltf_limits",
    "pairing_view",
    "read_character_upload",
]

#: What an archive may hold as its character (the one such file in it).
CHARACTER_SUFFIXES = (".gltf", ".glb", ".vrm")
#: A transfer's markers in an archive, beside the character file: ``source_vertex
#: target_vertex`` a line (``facecast expressions --markers``' format).
MARKERS_FILE = "markers.txt"


def gltf_limits(settings: Settings) -> GltfLimits:
    """The ``max_gltf_*`` settings: the most an uploaded character may declare."""
    return GltfLimits(
        json_values=settings.max_gltf_json_values,
        nodes=settings.max_gltf_nodes,
        depth=settings.max_gltf_depth,
        meshes=settings.max_gltf_meshes,
        primitives=settings.max_gltf_primitives,
        vertices=settings.max_gltf_vertices,
        faces=settings.max_gltf_faces,
        morph_targets=settings.max_gltf_morph_targets,
        morph_values=settings.max_gltf_morph_values,
        accessor_values=settings.max_gltf_accessor_values,
    )


def read_character_upload(
    data: bytes, limits: ArchiveLimits, scratch: Path, gltf: GltfLimits
) -> tuple[Character, np.ndarray | None]:
    """The uploaded character and the markers beside it in an archive (None without).

    Both upload paths (a character with expressions, and a transfer job's) read it here:
    every size the file declares is checked against ``gltf`` before anything is read.
    """
    if data[:4] == b"glTF":
        return load_character(data, label="the uploaded file", limits=gltf), None
    if data.lstrip()[:1] == b"{":
        raise ApiError(
            415,
            "gltf_needs_archive",
            "a .gltf refers to its buffers and images by file name: send it in a zip or "
            "tar with its files (`facecast rigs put URL ID avatar.gltf` does), or as a .glb",
        )
    with tempfile.TemporaryDirectory(prefix="upload-", dir=scratch) as tmp:
        dest = Path(tmp)
        try:
            extract_archive(data, dest, limits)
        except ArchiveError as exc:
            if exc.code == "unsupported_archive":
                raise ArchiveError(
                    415,
                    "unsupported_character",
                    "the body is neither a glTF binary (.glb, .vrm) nor a zip/tar of a "
                    ".gltf folder",
                ) from None
            raise
        found = _find_character(dest)
        with upload_paths_hidden(dest):
            character = load_character(found, label=found.relative_to(dest).as_posix(), limits=gltf)
            beside = found.parent / MARKERS_FILE
            markers = read_markers(beside) if beside.is_file() else None
    return character, markers


def check_character_size(character: Character, max_bytes: int, *, adding: int = 0) -> None:
    """422 ``character_too_large`` for a character file larger than the store keeps
    (``adding``: bytes a transfer job will add to it)."""
    size = len(character.glb) + adding
    if size > max_bytes:
        raise ApiError(
            422,
            "character_too_large",
            f"the character file is {size} bytes as stored (a .gltf folder "
            f"packed into one GLB), over the limit of {max_bytes} (setting "
            "max_character_bytes): shrink its textures or meshes",
        )


def _find_character(dest: Path) -> Path:
    """The one .gltf/.glb/.vrm in an unpacked upload (at its top or one folder down)."""
    found = [
        p
        for pattern in ("*", "*/*")
        for p in dest.glob(pattern)
        if p.is_file() and p.suffix.lower() in CHARACTER_SUFFIXES
    ]
    if not found:
        raise ArchiveError(
            422,
            "no_character_in_archive",
            "the archive holds no .gltf, .glb or .vrm at its top level or one folder down",
        )
    if len(found) > 1:
        names = ", ".join(sorted(str(p.relative_to(dest)) for p in found)[:4])
        raise ArchiveError(
            422, "several_characters", f"the archive holds more than one character file ({names})"
        )
    return found[0]


def character_record(character: Character, *, rights_holder: bool = False) -> dict[str, Any]:
    """What ``<id>.character`` keeps beside the GLB: format, VRM meta, the uploader's
    ``rights_holder`` declaration, bindings by name."""
    return {
        "format": character.format,
        "meta": character.meta,
        "rights_holder": rights_holder,
        "bindings": {
            name: [[b.mesh, b.morph, b.weight] for b in expression.bindings]
            for name, expression in character.expressions.items()
        },
    }


def pairing_view(report: PairingReport) -> dict[str, Any]:
    """The pairing report as JSON, with its lines as ``facecast fit`` prints them."""
    return {**report.to_dict(), "text": report.lines()}

"""Reading a character file, bounded: GLB chunks, a .gltf packed with its files, textures.

Checks what a hostile file could abuse before anything decodes it (chunk lengths, URIs
leaving the upload, image headers declaring huge textures) and returns the file as one
self-contained GLB; it does not read meshes, morph targets or VRM blocks.
"""

from __future__ import annotations

import urllib.parse
from pathlib import Path
from typing import Any

from ..errors import ExampleSetError
from ..io.gltf import pack_glb
from ..io.gltf_check import (
    GltfLimits,
    check_document,
    decode_data_uri,
    external_uri_error,
    parse_json,
    split_glb,
)
from ..io.gltf_compression import MESHOPT
from ..io.gltf_read import GltfDocument
from ..io.image_headers import image_size, sniff_mime

__all__ = ["MAX_CHARACTER_BYTES", "MAX_TEXTURE_PIXELS", "MAX_TEXTURE_SIDE", "read_character_file"]

#: Largest character file (a .glb/.vrm, or a .gltf with all its files) read.
MAX_CHARACTER_BYTES = 256 * 2**20
#: Largest texture side a header may declare (WebGL 2 guarantees 2048, desktops 16384).
MAX_TEXTURE_SIDE = 8192
#: All textures together, in pixels: 2^27 is 512 MiB decoded as RGBA in a viewer.
MAX_TEXTURE_PIXELS = 2**27


#: Required extensions refused, and why: ones the pages' three.js (0.170) cannot read, so
#: a viewer would get a file it cannot show (meshopt's Khronos successor to EXT_).
_UNREADABLE = {
    "KHR_meshopt_compression": "the viewer's three.js cannot decode yet: export with "
    "EXT_meshopt_compression (gltfpack -cc, gltf-transform meshopt) instead",
}


def _refuse_unreadable(doc: dict[str, Any], label: str) -> None:
    """``unsupported_extension`` for a required extension of ``_UNREADABLE``."""
    required = doc.get("extensionsRequired") or []
    blocked = [e for e in required if e in _UNREADABLE] if isinstance(required, list) else []
    if blocked:
        raise ExampleSetError(
            f"{label}: requires {blocked[0]}, which {_UNREADABLE[blocked[0]]}",
            code="unsupported_extension",
        )


def _read_uri(uri: str, folder: Path | None, label: str, budget: list[int]) -> bytes:
    """A buffer's or image's bytes: a data URI, or a file inside the .gltf's folder."""
    if uri.startswith("data:"):
        return decode_data_uri(uri, label)
    relative = urllib.parse.unquote(uri)
    outside = (
        folder is None
        or urllib.parse.urlsplit(uri).scheme != ""
        or relative.startswith(("/", "\\"))
        or not (folder / relative).resolve().is_relative_to(folder.resolve())
    )
    if outside:
        where = "outside the .gltf's folder" if folder is not None else "outside the file"
        raise external_uri_error(uri, label, where)
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


def _is_fallback(buffer: object) -> bool:
    """An ``EXT_meshopt_compression`` fallback buffer: no bytes, only a size to stand for."""
    if not isinstance(buffer, dict) or "uri" in buffer:
        return False
    extensions = buffer.get("extensions")
    ext = extensions.get(MESHOPT) if isinstance(extensions, dict) else None
    return isinstance(ext, dict) and ext.get("fallback") is True


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _pack_gltf(doc: dict[str, Any], folder: Path | None, label: str, budget: list[int]) -> bytes:
    """The .gltf as one GLB: its buffers concatenated in one BIN chunk, images embedded;
    meshopt's fallback buffers (no bytes) stay buffers of their own after it."""
    buffers = doc.get("buffers") or []
    if not isinstance(buffers, list):
        raise ExampleSetError(f"{label}: buffers is not a list", code="bad_gltf")
    parts: list[bytes] = []
    starts: dict[int, int] = {}
    lengths: dict[int, int] = {}
    fallbacks: dict[int, int] = {}  # old index -> its place among the fallback buffers
    size = 0
    for number, buffer in enumerate(buffers):
        if _is_fallback(buffer):
            fallbacks[number] = len(fallbacks)
            continue
        uri = buffer.get("uri") if isinstance(buffer, dict) else None
        if not isinstance(uri, str):
            raise ExampleSetError(f"{label}: a .gltf buffer without a uri", code="bad_gltf")
        data = _read_uri(uri, folder, label, budget)
        starts[number] = size
        lengths[number] = len(data)
        pad = (-len(data)) % 4  # keeps every buffer's views aligned as they were
        parts.append(data + b"\0" * pad)
        size += len(data) + pad
    views = doc.setdefault("bufferViews", [])
    moved: list[dict[str, Any]] = []  # views in fallback buffers: renumbered once known
    for view in views:
        if (
            not isinstance(view, dict)
            or not isinstance(view.get("buffer"), int)
            or not 0 <= view["buffer"] < len(buffers)
        ):
            raise ExampleSetError(f"{label}: a bufferView names no buffer", code="bad_gltf")
        extensions = view.get("extensions")
        ext = extensions.get(MESHOPT) if isinstance(extensions, dict) else None
        if isinstance(ext, dict):  # its compressed bytes move with their buffer
            if ext.get("buffer") not in starts:
                raise ExampleSetError(
                    f"{label}: a meshopt view names no buffer with bytes", code="bad_gltf"
                )
            ext["byteOffset"] = int(ext.get("byteOffset", 0)) + starts[ext["buffer"]]
            ext["buffer"] = 0
        if view["buffer"] in fallbacks:
            moved.append(view)
            continue
        offset, length = view.get("byteOffset", 0), view.get("byteLength")
        if not _is_int(offset) or not _is_int(length):
            raise ExampleSetError(f"{label}: a bufferView's offset or length", code="bad_gltf")
        if offset + length > lengths[view["buffer"]]:
            # Packed, it would reach into the next buffer: refuse it as it stands.
            raise ExampleSetError(
                f"{label}: a bufferView runs past the end of buffer {view['buffer']}",
                code="bad_gltf",
            )
        view["byteOffset"] = offset + starts[view["buffer"]]
        view["buffer"] = 0
    for image in doc.get("images") or []:
        if isinstance(image, dict) and isinstance(image.get("uri"), str):
            data = _read_uri(image.pop("uri"), folder, label, budget)
            image["mimeType"] = sniff_mime(data) or image.get("mimeType") or "image/png"
            views.append({"buffer": 0, "byteOffset": size, "byteLength": len(data)})
            image["bufferView"] = len(views) - 1
            parts.append(data + b"\0" * ((-len(data)) % 4))
            size += len(data) + (-len(data)) % 4
    first = [{"byteLength": size}] if parts else []
    for view in moved:
        view["buffer"] = len(first) + fallbacks[view["buffer"]]
    doc["buffers"] = first + [buffers[number] for number in fallbacks]
    if not doc["buffers"]:
        doc.pop("buffers")
    return pack_glb(doc, b"".join(parts))


def _check_textures(document: GltfDocument, label: str) -> None:
    """Refuse images whose headers declare more pixels than a viewer should decode (the
    document is checked: every image is a data URI or a bufferView inside its buffer)."""
    doc = document.json
    views = doc.get("bufferViews", [])
    total = 0
    for number, image in enumerate(doc.get("images", [])):
        where = f"{label}: image {number}"
        data: bytes | memoryview
        if image.get("bufferView") is None:
            data = decode_data_uri(image["uri"], label)
        else:
            view = views[image["bufferView"]]
            start = view.get("byteOffset", 0)
            data = document.buffers[view["buffer"]][start : start + view["byteLength"]]
        width, height = image_size(bytes(data[: 1 << 20]), where)
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


def read_character_file(
    source: Path | bytes, label: str, limits: GltfLimits | None = None
) -> tuple[GltfDocument, bytes]:
    """``(the checked document, the file as one GLB)``, bounded and self-contained.

    A GLB (.glb, .vrm) is returned as it is, after its chunks, every size it declares
    (``gltf_check.check_document`` with ``limits``, defaults without), URIs (``data:``
    only, anywhere) and textures are checked; a .gltf's buffers and images are read from
    its folder (never outside it) and packed into one GLB, nothing else changed, and that
    GLB is checked as one uploaded.

    Raises
    ------
    ExampleSetError
        ``truncated_file``, ``bad_gltf``, ``external_uri``, ``gltf_exceeds_limits``,
        ``texture_too_large``, ``bad_image``, ``too_large``, ``missing_file``,
        ``unsupported_extension`` (``KHR_meshopt_compression``: the pages cannot show it). Compressed
        geometry (meshopt, Draco) is not decoded here: ``gltf_read`` decodes it, bounded.
    """
    limits = GltfLimits() if limits is None else limits
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
    if data[:4] != b"glTF":
        if data.lstrip()[:1] != b"{":
            raise ExampleSetError(
                f"{label}: not a glTF, GLB or VRM file (a character is a .glb, .vrm or .gltf)",
                code="bad_gltf",
            )
        doc = parse_json(data, limits, label)
        data = _pack_gltf(doc, folder, label, [MAX_CHARACTER_BYTES - len(data)])
    text, blob = split_glb(data, label)
    doc = parse_json(text, limits, label)
    _refuse_unreadable(doc, label)
    document = GltfDocument(doc, check_document(doc, blob, limits, label))
    _check_textures(document, label)
    return document, data

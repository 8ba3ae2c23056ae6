"""Reading a character file, bounded: GLB chunks, a .gltf packed with its files, textures.

Checks what a hostile file could abuse before anything decodes it (chunk lengths, URIs
leaving the upload, image headers declaring huge textures) and returns the file as one
self-contained GLB; it does not read meshes, morph targets or VRM blocks.
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
import urllib.parse
from pathlib import Path
from typing import Any

from ..errors import ExampleSetError
from ..io.gltf import pack_glb
from ..io.gltf_compression import MESHOPT
from ..io.image_headers import image_size, sniff_mime

__all__ = ["MAX_CHARACTER_BYTES", "MAX_TEXTURE_PIXELS", "MAX_TEXTURE_SIDE", "read_character_file"]

#: Largest character file (a .glb/.vrm, or a .gltf with all its files) read.
MAX_CHARACTER_BYTES = 256 * 2**20
#: Largest texture side a header may declare (WebGL 2 guarantees 2048, desktops 16384).
MAX_TEXTURE_SIDE = 8192
#: All textures together, in pixels: 2^27 is 512 MiB decoded as RGBA in a viewer.
MAX_TEXTURE_PIXELS = 2**27

_GLB_HEADER = struct.Struct("<4sII")
_CHUNK = struct.Struct("<I4s")


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
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ExampleSetError(
            f"{label}: glTF JSON is not readable ({type(exc).__name__})", code="bad_gltf"
        ) from None
    asset = doc.get("asset") if isinstance(doc, dict) else None
    if not isinstance(asset, dict) or not str(asset.get("version", "")).startswith("2"):
        raise ExampleSetError(f"{label}: not a glTF 2.0 document", code="bad_gltf")
    checked: dict[str, Any] = doc
    return checked


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


def _is_fallback(buffer: object) -> bool:
    """An ``EXT_meshopt_compression`` fallback buffer: no bytes, only a size to stand for."""
    if not isinstance(buffer, dict) or "uri" in buffer:
        return False
    extensions = buffer.get("extensions")
    ext = extensions.get(MESHOPT) if isinstance(extensions, dict) else None
    return isinstance(ext, dict) and ext.get("fallback") is True


def _pack_gltf(doc: dict[str, Any], folder: Path | None, label: str, budget: list[int]) -> bytes:
    """The .gltf as one GLB: its buffers concatenated in one BIN chunk, images embedded;
    meshopt's fallback buffers (no bytes) stay buffers of their own after it."""
    buffers = doc.get("buffers") or []
    if not isinstance(buffers, list):
        raise ExampleSetError(f"{label}: buffers is not a list", code="bad_gltf")
    parts: list[bytes] = []
    starts: dict[int, int] = {}
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
    first = [{"byteLength": size}] if parts else []
    for view in moved:
        view["buffer"] = len(first) + fallbacks[view["buffer"]]
    doc["buffers"] = first + [buffers[number] for number in fallbacks]
    if not doc["buffers"]:
        doc.pop("buffers")
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


def read_character_file(source: Path | bytes, label: str) -> tuple[dict[str, Any], bytes, bytes]:
    """``(JSON document, BIN chunk, the file as one GLB)``, bounded and self-contained.

    A GLB (.glb, .vrm) is returned as it is, after its chunks, external URIs (none
    allowed) and textures are checked; a .gltf's buffers and images are read from its
    folder (never outside it) and packed into one GLB, nothing else changed.

    Raises
    ------
    ExampleSetError
        ``truncated_file``, ``bad_gltf``, ``external_uri``, ``texture_too_large``,
        ``bad_image``, ``too_large``, ``missing_file``. Compressed geometry (meshopt,
        Draco) is not decoded here: ``gltf_read`` decodes it, bounded.
    """
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

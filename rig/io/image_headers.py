"""Image dimensions from PNG, JPEG and WebP headers, without decoding a pixel.

Lets a character's textures be bounded before any viewer decodes them (a "texture bomb"
declares 60000 x 60000 pixels in a few hundred bytes); it must not decode or allocate
in proportion to what a header declares.
"""

from __future__ import annotations

import struct

from ..errors import ExampleSetError

__all__ = ["MAX_JPEG_SEGMENTS", "image_size", "sniff_mime"]

#: JPEG markers the scan walks past before giving up on finding the frame header.
MAX_JPEG_SEGMENTS = 1000

_PNG = b"\x89PNG\r\n\x1a\n"
# Start-of-frame markers: every SOFn except DHT (C4), JPG (C8) and DAC (CC).
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def sniff_mime(data: bytes) -> str | None:
    """``image/png``, ``image/jpeg`` or ``image/webp`` from the magic bytes; None otherwise."""
    if data.startswith(_PNG):
        return "image/png"
    if data.startswith(b"\xff\xd8"):
        return "image/jpeg"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return None


def image_size(data: bytes, label: str) -> tuple[int, int]:
    """``(width, height)`` the image's header declares.

    Raises
    ------
    ExampleSetError
        ``bad_image``: not PNG, JPEG or WebP, or a header cut short or malformed.
    """
    mime = sniff_mime(data)
    try:
        if mime == "image/png":
            return _png(data, label)
        if mime == "image/jpeg":
            return _jpeg(data, label)
        if mime == "image/webp":
            return _webp(data, label)
    except struct.error:
        raise ExampleSetError(f"{label}: image header is cut short", code="bad_image") from None
    raise ExampleSetError(
        f"{label}: not a PNG, JPEG or WebP image (the formats a glTF texture may use here)",
        code="bad_image",
    )


def _png(data: bytes, label: str) -> tuple[int, int]:
    # The IHDR chunk must come first (PNG spec 5.6): length, "IHDR", width, height.
    length, kind, width, height = struct.unpack_from(">I4sII", data, 8)
    if kind != b"IHDR" or length < 8:
        raise ExampleSetError(f"{label}: PNG without IHDR header", code="bad_image")
    return int(width), int(height)


def _jpeg(data: bytes, label: str) -> tuple[int, int]:
    pos = 2
    for _ in range(MAX_JPEG_SEGMENTS):
        while (
            pos < len(data) and data[pos] == 0xFF and pos + 1 < len(data) and data[pos + 1] == 0xFF
        ):
            pos += 1  # fill bytes
        if pos + 4 > len(data) or data[pos] != 0xFF:
            break
        marker = data[pos + 1]
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers carry no length
            pos += 2
            continue
        (length,) = struct.unpack_from(">H", data, pos + 2)
        if marker in _SOF:
            height, width = struct.unpack_from(">HH", data, pos + 5)
            return int(width), int(height)
        if length < 2:
            break
        pos += 2 + length
    raise ExampleSetError(f"{label}: JPEG without a readable frame header", code="bad_image")


def _webp(data: bytes, label: str) -> tuple[int, int]:
    chunk = data[12:16]
    if chunk == b"VP8 ":
        width, height = struct.unpack_from("<HH", data, 26)
        return int(width & 0x3FFF), int(height & 0x3FFF)
    if chunk == b"VP8L":
        (bits,) = struct.unpack_from("<I", data, 21)
        return int((bits & 0x3FFF) + 1), int(((bits >> 14) & 0x3FFF) + 1)
    if chunk == b"VP8X":
        w = int.from_bytes(data[24:27], "little") + 1
        h = int.from_bytes(data[27:30], "little") + 1
        if len(data) < 30:
            raise struct.error
        return w, h
    raise ExampleSetError(f"{label}: WebP of unknown kind", code="bad_image")

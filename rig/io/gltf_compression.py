"""Compressed glTF geometry decoded for reading: ``EXT_meshopt_compression`` buffer views and
``KHR_draco_mesh_compression`` primitives, through meshoptimizer's and Draco's own decoders.

Every decoded size is bounded from the counts the file declares before a decoder runs, and
what a decoder gives back is checked against those counts; errors are ``ExampleSetError``
``bad_compression``. It reads no accessor (gltf_read.py) and never changes the file: what is
stored and served stays compressed. ``KHR_mesh_quantization`` needs no decoder (its integer
attributes are plain accessors, which gltf_read.py reads).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

# DracoPy: Google's Draco decoder (C++) as built by its maintainers, pinned in pyproject.toml.
import DracoPy
import meshopt
import numpy as np

from ..errors import ExampleSetError

__all__ = [
    "DRACO",
    "MESHOPT",
    "QUANTIZATION",
    "DracoGeometry",
    "decode_draco",
    "decode_meshopt_view",
    "draco_extension",
    "meshopt_extension",
]

MESHOPT = "EXT_meshopt_compression"
DRACO = "KHR_draco_mesh_compression"
QUANTIZATION = "KHR_mesh_quantization"

_MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
# EXT_meshopt_compression's filters and vertex codec (header 0xa0): the COLOR filter and
# codec version 1 are KHR_meshopt_compression's, which the pages' decoder cannot read.
_FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL")
_VERTEX_HEADER = 0xA0

#: A Draco primitive's decoded geometry: positions (V, 3) float64 and, for a mesh, the
#: triangle corners (3F,) int64 (None for a point cloud).
DracoGeometry = tuple[np.ndarray, np.ndarray | None]


def _int(value: object, where: str, label: str, low: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ExampleSetError(
            f"{label}: {where} is {value!r}, not an integer of at least {low}",
            code="bad_compression",
        )
    return value


def _extension(item: Any, name: str) -> Mapping[str, Any] | None:
    """Extension ``name``'s object on a glTF item (a JSON dict or a pygltflib object)."""
    extensions = item.get("extensions") if isinstance(item, dict) else getattr(item, "extensions", None)  # fmt: skip
    found = extensions.get(name) if isinstance(extensions, dict) else None
    return found if isinstance(found, dict) else None


def meshopt_extension(view: Any) -> Mapping[str, Any] | None:
    """A buffer view's ``EXT_meshopt_compression`` object, or None if it has none."""
    return _extension(view, MESHOPT)


def draco_extension(primitive: Any) -> Mapping[str, Any] | None:
    """A primitive's ``KHR_draco_mesh_compression`` object, or None if it has none."""
    return _extension(primitive, DRACO)


def decode_meshopt_view(
    ext: Mapping[str, Any],
    view_length: int,
    buffer: Callable[[int], bytes | memoryview],
    max_bytes: int,
    label: str,
) -> memoryview:
    """The bytes of a buffer view that ``EXT_meshopt_compression`` stores compressed.

    Parameters
    ----------
    ext : mapping
        The view's extension object: ``buffer``, ``byteOffset``, ``byteLength``,
        ``byteStride``, ``count``, ``mode`` and ``filter`` as the extension defines them.
    view_length : int
        The view's own ``byteLength``, which the extension requires to be ``byteStride``
        times ``count``.
    buffer : callable
        A buffer's bytes by its index.
    max_bytes : int
        Most bytes the decoded view may hold (``count * byteStride`` is checked against it
        before the decoder runs).

    Returns
    -------
    memoryview
        ``count * byteStride`` bytes, the view as it would be uncompressed (the decoder's
        array, not a copy of it).
    """
    index = _int(ext.get("buffer"), "the meshopt view's buffer", label)
    offset = _int(ext.get("byteOffset", 0), "the meshopt view's byteOffset", label)
    length = _int(ext.get("byteLength"), "the meshopt view's byteLength", label)
    stride = _int(ext.get("byteStride"), "the meshopt view's byteStride", label, 1)
    count = _int(ext.get("count"), "the meshopt view's count", label, 1)
    mode = ext.get("mode")
    chosen = ext.get("filter", "NONE")
    if mode not in _MODES or chosen not in _FILTERS:
        raise ExampleSetError(
            f"{label}: a meshopt view has mode {str(mode)[:40]!r} and filter "
            f"{str(chosen)[:40]!r} (modes {', '.join(_MODES)}; filters {', '.join(_FILTERS)})",
            code="bad_compression",
        )
    if count * stride > max_bytes:
        raise ExampleSetError(
            f"{label}: a meshopt view declares {count} x {stride} bytes, more than the "
            f"reader's limit of {max_bytes} decoded bytes",
            code="too_large",
        )
    problem = _meshopt_rule(mode, chosen, stride, count, view_length)
    if problem is not None:
        raise ExampleSetError(f"{label}: a meshopt view {problem}", code="bad_compression")
    data = buffer(index)
    if offset + length > len(data):
        raise ExampleSetError(
            f"{label}: a meshopt view runs past its buffer ({offset} + {length} > {len(data)})",
            code="bad_compression",
        )
    if mode == "ATTRIBUTES" and length and data[offset] != _VERTEX_HEADER:
        raise ExampleSetError(
            f"{label}: a meshopt view's vertex stream starts with {data[offset]:#x}, not "
            f"{_VERTEX_HEADER:#x} (EXT_meshopt_compression's codec; version 1 is "
            "KHR_meshopt_compression's, which the pages cannot decode)",
            code="bad_compression",
        )
    try:
        rows = meshopt.decode_gltf_buffer(
            bytes(data[offset : offset + length]),
            count,
            stride,
            mode,
            None if chosen == "NONE" else chosen,
        )
    except (ValueError, RuntimeError) as exc:
        raise ExampleSetError(
            f"{label}: a meshopt view does not decode ({exc})", code="bad_compression"
        ) from None
    # The decoder's array itself, as bytes: a copy (tobytes) held it twice.
    decoded = np.ascontiguousarray(rows).reshape(-1).view(np.uint8).data
    if len(decoded) != count * stride:  # the decoder's promise, checked rather than trusted
        raise ExampleSetError(
            f"{label}: a meshopt view decoded to {len(decoded)} bytes, not {count * stride}",
            code="bad_compression",
        )
    return decoded


def _meshopt_rule(mode: str, chosen: str, stride: int, count: int, view_length: int) -> str | None:
    """What breaks the extension's validity rules (its "JSON schema updates"), or None."""
    if stride * count != view_length:
        return f"decodes to {count} x {stride} bytes, its bufferView holds {view_length}"
    if mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
        return f"of ATTRIBUTES has byteStride {stride} (4 to 256, in fours)"
    if mode != "ATTRIBUTES" and (stride not in (2, 4) or chosen != "NONE"):
        return f"of {mode} has byteStride {stride} and filter {chosen} (2 or 4, NONE)"
    if mode == "TRIANGLES" and count % 3:
        return f"of TRIANGLES has {count} indices, not triangles"
    if (chosen == "OCTAHEDRAL" and stride not in (4, 8)) or (
        chosen == "QUATERNION" and stride != 8
    ):
        return f"filtered {chosen} has byteStride {stride}"
    return None


def decode_draco(
    data: bytes | memoryview, position_id: int, vertices: int, corners: int | None, label: str
) -> DracoGeometry:
    """A Draco primitive's positions and triangle corners, checked against its accessors.

    Parameters
    ----------
    data : bytes
        The primitive's Draco bitstream (its extension's buffer view).
    position_id : int
        The Draco attribute holding POSITION (the extension's ``attributes.POSITION``).
    vertices, corners : int
        What the POSITION and indices accessors declare (``corners`` None without
        indices); the caller has bounded both. Decoded counts must equal them.
    """
    try:
        geometry = DracoPy.decode(bytes(data))
    except Exception as exc:  # DracoPy raises its own types and RuntimeError on bad input
        raise ExampleSetError(
            f"{label}: a Draco primitive does not decode ({type(exc).__name__}: {exc})",
            code="bad_compression",
        ) from None
    attribute = geometry.get_attribute_by_unique_id(position_id)
    if attribute is None:
        raise ExampleSetError(
            f"{label}: a Draco primitive has no attribute {position_id} for POSITION",
            code="bad_compression",
        )
    positions = np.asarray(attribute["data"], dtype=np.float64)
    if positions.ndim != 2 or positions.shape != (vertices, 3):
        raise ExampleSetError(
            f"{label}: a Draco primitive decoded {positions.shape[0]} positions of "
            f"{positions.shape[1:]}, its accessor declares {vertices} VEC3",
            code="bad_compression",
        )
    if corners is None:
        return positions, None
    faces = getattr(geometry, "faces", None)
    flat = np.asarray(faces if faces is not None else [], dtype=np.int64).reshape(-1)
    if flat.size != corners:
        raise ExampleSetError(
            f"{label}: a Draco primitive decoded {flat.size} triangle corners, its indices "
            f"accessor declares {corners}",
            code="bad_compression",
        )
    return positions, flat

"""A ``frame`` message in its canonical layout, decoded without msgpack's generic path.

A shortcut only, for the server's per-frame path: bytes laid out exactly as `encode`
writes a `Frame` (PROTOCOL.md §5.1.2: keys in the spec's order, ``ts`` a float64) become
a `Frame`; anything else gives None and the generic decoder decides, so the two never
disagree. It never raises.
"""

from __future__ import annotations

import math
import struct
from typing import Final

import numpy as np

from facecast.protocol.arrays import WIRE_DTYPES, all_finite
from facecast.protocol.limits import Limits
from facecast.protocol.messages import Frame, _checked

__all__ = ["decode_frame"]

# The fixed parts of the layout, in msgpack bytes: a 5-key map {"v": 1, "type": "frame",
# "seq": <uint>, "ts": <float64>, "points": {"dtype": "f..", "shape": [K, 3], "data": <bin>}}.
_HEAD: Final = b"\x85\xa1v\x01\xa4type\xa5frame\xa3seq"
_TS: Final = b"\xa2ts\xcb"
_POINTS: Final = b"\xa6points\x83\xa5dtype\xa3f"
_SHAPE: Final = b"\xa5shape\x92"
_DATA: Final = b"\x03\xa4data"
_F64: Final = struct.Struct(">d")
_DTYPES: Final = {name[1:].encode(): dtype for name, dtype in WIRE_DTYPES.items()}
#: msgpack's uint8/16/32/64 markers and their payload sizes.
_UINT: Final = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}
#: bin8/16/32 markers and the sizes of their length fields.
_BIN: Final = {0xC4: 1, 0xC5: 2, 0xC6: 4}


def _uint(data: bytes, i: int, sizes: dict[int, int]) -> tuple[int, int]:
    """The unsigned int whose marker is at ``data[i]`` and the index after it; (-1, i) if none."""
    marker = data[i]
    if marker < 0x80 and sizes is _UINT:
        return marker, i + 1
    size = sizes.get(marker)
    if size is None or i + 1 + size > len(data):
        return -1, i
    return int.from_bytes(data[i + 1 : i + 1 + size], "big"), i + 1 + size


def decode_frame(data: bytes, limits: Limits) -> Frame | None:
    """The `Frame` in ``data`` if it is one in the canonical layout and valid, else None.

    None means "not decided here", never "invalid": the caller then runs the generic
    decoder, which accepts or rejects the bytes with the right error. The points are a
    read-only view of ``data``, as the generic decoder's are of their bin value.
    """
    if type(data) is not bytes or not data.startswith(_HEAD):
        return None
    end = len(data)
    if end > limits.max_message_bytes:
        return None
    try:
        seq, i = _uint(data, len(_HEAD), _UINT)
        if seq < 0 or data[i : i + 4] != _TS:
            return None
        (ts,) = _F64.unpack_from(data, i + 4)
        i += 12
        if not math.isfinite(ts) or data[i : i + len(_POINTS)] != _POINTS:
            return None
        i += len(_POINTS)
        dtype = _DTYPES.get(data[i : i + 2])
        i += 2
        if dtype is None or data[i : i + len(_SHAPE)] != _SHAPE:
            return None
        rows, i = _uint(data, i + len(_SHAPE), _UINT)
        if data[i : i + len(_DATA)] != _DATA:
            return None
        size, i = _uint(data, i + len(_DATA), _BIN)
    except (IndexError, struct.error):
        return None
    if not 0 < rows <= limits.max_points or size != rows * 3 * dtype.itemsize or i + size != end:
        return None
    points = np.ndarray((rows, 3), dtype, data, offset=i)
    if not all_finite(points):
        return None
    return _checked(Frame, seq=seq, ts=ts, points=points, head=None)

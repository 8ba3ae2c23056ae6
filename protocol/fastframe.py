"""A ``frame`` message in its canonical layout, decoded without msgpack's generic path.

A shortcut only, for the server's per-frame path: bytes laid out exactly as `encode`
writes a `Frame` (PROTOCOL.md §5.1.2: keys in the spec's order, ``ts`` a float64) become
a `Frame`; anything else gives None and the generic decoder decides, so the two never
disagree. It never raises.
"""

from __future__ import annotations

import math
import re
import struct
from typing import Final

import numpy as np

from facecast.protocol.arrays import WIRE_DTYPES, all_finite
from facecast.protocol.frames import Frame
from facecast.protocol.limits import Limits
from facecast.protocol.message import _checked

__all__ = ["decode_frame"]

# The layout, in msgpack bytes: a 5-key map {"v": 1, "type": "frame", "seq": <uint>,
# "ts": <float64>, "points": {"dtype": "f..", "shape": [K, 3], "data": <bin>}}. One
# regular expression reads it (~0.4 µs; slicing and comparing each part cost 2 µs more).
# Groups: seq as fixint/uint8/16/32/64, ts, the dtype's digits, K as fixint/uint8/16 (a
# larger K is past any limit), the bin8/16/32 length; the array's bytes follow the match.
_LAYOUT: Final = re.compile(
    rb"\x85\xa1v\x01\xa4type\xa5frame\xa3seq"
    rb"(?:([\x00-\x7f])|\xcc(.)|\xcd(..)|\xce(.{4})|\xcf(.{8}))"
    rb"\xa2ts\xcb(.{8})"
    rb"\xa6points\x83\xa5dtype\xa3f(16|32|64)\xa5shape\x92"
    rb"(?:([\x00-\x7f])|\xcc(.)|\xcd(..))\x03\xa4data"
    rb"(?:\xc4(.)|\xc5(..)|\xc6(.{4}))",
    re.DOTALL,
)
_F64: Final = struct.Struct(">d")
_DTYPES: Final = {name[1:].encode(): dtype for name, dtype in WIRE_DTYPES.items()}


def decode_frame(data: bytes, limits: Limits) -> Frame | None:
    """The `Frame` in ``data`` if it is one in the canonical layout and valid, else None.

    None means "not decided here", never "invalid": the caller then runs the generic
    decoder, which accepts or rejects the bytes with the right error. The points are a
    read-only view of ``data``, as the generic decoder's are of their bin value.
    """
    if type(data) is not bytes or len(data) > limits.max_message_bytes:
        return None
    match = _LAYOUT.match(data)
    if match is None:
        return None
    seq8, seq16, seq32, seq64, seq_fix, ts, digits, rows8, rows16, rows_fix, n8, n16, n32 = (
        match.group(2, 3, 4, 5, 1, 6, 7, 9, 10, 8, 11, 12, 13)
    )
    seq = int.from_bytes(seq_fix or seq8 or seq16 or seq32 or seq64, "big")
    rows = int.from_bytes(rows_fix or rows8 or rows16, "big")
    size = int.from_bytes(n8 or n16 or n32, "big")
    dtype = _DTYPES.get(digits)
    (stamp,) = _F64.unpack(ts)
    start = match.end()
    if (
        dtype is None
        or not math.isfinite(stamp)
        or not 0 < rows <= limits.max_points
        or size != rows * 3 * dtype.itemsize
        or start + size != len(data)
    ):
        return None
    points = np.ndarray((rows, 3), dtype, data, offset=start)
    if not all_finite(points):
        return None
    return _checked(Frame, seq=seq, ts=stamp, points=points, head=None, stamps=None)

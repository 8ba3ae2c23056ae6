"""The streaming messages (PROTOCOL.md §5.1.2, §5.2.2): a `Frame` in, its `Result` out.

The per-frame path: checks are type checks, never array scans; fastframe.py decodes the
common frame without ``parse``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final

import numpy as np

from facecast.protocol.arrays import array_from_wire, array_to_wire, wire_dtype_name
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import (
    check_float,
    check_uint,
    read_float,
    read_uint,
)
from facecast.protocol.head import Head
from facecast.protocol.limits import Limits
from facecast.protocol.message import (
    _DEFAULT_LIMITS,
    _ArrayMessage,
    _check_array,
    _check_head,
    _check_stamps,
    _checked,
    _header,
    _read_head,
    _read_stamps,
)
from facecast.protocol.stamps import Stamps


@dataclass(frozen=True, kw_only=True, eq=False)
class Frame(_ArrayMessage):
    """One frame of tracked feature points (§5.1.2).

    Attributes
    ----------
    seq : int
        Sender's sequence number, echoed in the result.
    ts : float
        Source timestamp (seconds, sender's clock), echoed in the result.
    points : (K, 3) float16/32/64
        Feature points; decoded frames hold a read-only view of the message bytes.
    head : Head or None
        The performer's head pose (§5.3), relayed to a channel's watchers; None: not sent.
    stamps : Stamps or None
        The frame's times along the path so far (§5.4: captured, tracked, sent), on the
        server's clock as the sender estimates it; None: not sent.
    """

    TYPE: ClassVar[str] = "frame"
    seq: int
    ts: float
    points: np.ndarray
    head: Head | None = None
    stamps: Stamps | None = None

    def __post_init__(self) -> None:
        check_uint(self.seq, "frame.seq")
        object.__setattr__(self, "ts", check_float(self.ts, "frame.ts"))
        _check_array(self.points, "frame.points", (3,))
        _check_head(self.head, "frame.head")
        _check_stamps(self.stamps, "frame.stamps")

    def serialize(self) -> dict[str, Any]:
        out = {
            **_header(self.TYPE),
            "seq": self.seq,
            "ts": self.ts,
            "points": array_to_wire(self.points),
        }
        if self.head is not None:  # absent otherwise: a frame without one keeps its bytes
            out["head"] = self.head.serialize()
        if self.stamps is not None:  # likewise
            out["stamps"] = self.stamps.serialize()
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Frame:
        return _checked(
            cls,
            seq=read_uint(obj, "seq", "frame.seq"),
            ts=read_float(obj, "ts", "frame.ts"),
            points=array_from_wire(
                obj.get("points"), "frame.points", trailing=(3,), max_rows=limits.max_points
            ),
            head=_read_head(obj, "frame.head"),
            stamps=_read_stamps(obj, "frame.stamps"),
        )


_RESULT_ARRAYS: Final = ("weights", "vertices", "points")
_ONE_ARRAY: Final = "a result carries exactly one of weights, vertices and points"


@dataclass(frozen=True, kw_only=True, eq=False)
class Result(_ArrayMessage):
    """The clone of one frame (§5.2.2); exactly one of the three arrays is set.

    Attributes
    ----------
    seq : int
        The frame's sequence number.
    ts : float
        The frame's source timestamp, echoed unchanged.
    weights : (M,) float16/32 or None
        Example weights, when the session's output is "weights".
    vertices : (V, 3) float16/32 or None
        Target mesh vertices, when the session's output is "vertices".
    points : (K, 3) float32/64 or None
        The frame's feature points as published, for a channel watcher whose output is
        "points" (§2.4); nothing is cloned for it.
    proc_us : int
        Server processing time for this frame, microseconds.
    dropped : int
        Frames this session has discarded unprocessed so far (§8).
    server_ts : float or None
        The server's wall clock when encoded (channel endpoints, §2.4).
    head : Head or None
        The frame's head pose as published, on channel endpoints (§5.3).
    stamps : Stamps or None
        The frame's times along the path (§5.4): the publisher's plausible ones and the
        server's ``server_in``, on channel endpoints when the frame had stamps.
    """

    TYPE: ClassVar[str] = "result"
    seq: int
    ts: float
    weights: np.ndarray | None = None
    vertices: np.ndarray | None = None
    points: np.ndarray | None = None
    proc_us: int = 0
    dropped: int = 0
    server_ts: float | None = None
    head: Head | None = None
    stamps: Stamps | None = None

    def __post_init__(self) -> None:
        # On the server's per-frame path: a handful of type checks, no array scans.
        check_uint(self.seq, "result.seq")
        object.__setattr__(self, "ts", check_float(self.ts, "result.ts"))
        check_uint(self.proc_us, "result.proc_us")
        check_uint(self.dropped, "result.dropped")
        _check_head(self.head, "result.head")
        _check_stamps(self.stamps, "result.stamps")
        if self.server_ts is not None:
            object.__setattr__(self, "server_ts", check_float(self.server_ts, "result.server_ts"))
        present = [name for name in _RESULT_ARRAYS if getattr(self, name) is not None]
        if len(present) != 1:
            raise ProtocolError(ErrorCode.INVALID_FIELD, _ONE_ARRAY)
        name = present[0]
        _check_array(getattr(self, name), f"result.{name}", () if name == "weights" else (3,))

    @property
    def output(self) -> str:
        """ "weights", "vertices" or "points": which one this result carries."""
        if self.weights is not None:
            return "weights"
        return "vertices" if self.vertices is not None else "points"

    @property
    def values(self) -> np.ndarray:
        """The array this result carries: (M,) weights, (V, 3) vertices or (K, 3) points."""
        values: np.ndarray = getattr(self, self.output)
        return values

    @property
    def dtype(self) -> str:
        """Wire dtype name of `values`."""
        return wire_dtype_name(self.values.dtype)

    def serialize(self) -> dict[str, Any]:
        out = {**_header(self.TYPE), "seq": self.seq, "ts": self.ts}
        output = self.output
        out[output] = array_to_wire(self.values)
        out["proc_us"] = self.proc_us
        out["dropped"] = self.dropped
        if self.server_ts is not None:
            out["server_ts"] = self.server_ts
        if self.head is not None:
            out["head"] = self.head.serialize()
        if self.stamps is not None:
            out["stamps"] = self.stamps.serialize()
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Result:
        seq = read_uint(obj, "seq", "result.seq")
        ts = read_float(obj, "ts", "result.ts")
        present = [name for name in _RESULT_ARRAYS if obj.get(name) is not None]
        if len(present) != 1:
            raise ProtocolError(ErrorCode.INVALID_FIELD, _ONE_ARRAY)
        name = present[0]
        trailing, max_rows = {
            "weights": ((), limits.max_names),
            "vertices": ((3,), limits.max_vertices),
            "points": ((3,), limits.max_points),
        }[name]
        values = array_from_wire(obj[name], f"result.{name}", trailing=trailing, max_rows=max_rows)
        arrays: dict[str, np.ndarray | None] = dict.fromkeys(_RESULT_ARRAYS)
        arrays[name] = values
        return _checked(
            cls,
            seq=seq,
            ts=ts,
            **arrays,
            proc_us=read_uint(obj, "proc_us", "result.proc_us"),
            dropped=read_uint(obj, "dropped", "result.dropped"),
            server_ts=read_float(obj, "server_ts", "result.server_ts", None),
            head=_read_head(obj, "result.head"),
            stamps=_read_stamps(obj, "result.stamps"),
        )

"""The optional head pose a ``frame`` may carry and a channel ``result`` relays (PROTOCOL.md §5.3).

One small value type with its checks and its wire map; it knows nothing of messages,
sessions or VMC (the bridges convert angles to and from it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from facecast.protocol.arrays import array_from_wire, array_to_wire
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import check_map

__all__ = ["HEAD_NORM_TOLERANCE", "MAX_HEAD_POSITION", "Head"]

#: Largest | ||rotation|| - 1 | accepted: a unit quaternion rounded to f16 stays within it.
HEAD_NORM_TOLERANCE: Final = 1e-3
#: Largest |position| component accepted, metres (float32-safe for a VMC receiver).
MAX_HEAD_POSITION: Final = 1000.0
#: No row limit of its own: the data, whose length must match the shape, is bounded by
#: the message size, so a longer array is a bad shape (INVALID_ARRAY), not a limit.
_ANY_ROWS: Final = 1 << 62


def _vector(value: Any, where: str, length: int) -> np.ndarray:
    """``value`` as a float (length,) array: checked if an ndarray, decoded if a wire map."""
    if isinstance(value, np.ndarray):
        if value.ndim != 1 or value.dtype.kind != "f" or value.dtype.itemsize not in (2, 4, 8):
            raise ProtocolError(
                ErrorCode.INVALID_ARRAY,
                f"{where} must be a float ({length},) array, got {value.dtype} {value.shape}",
            )
        if not np.isfinite(value).all():
            raise ProtocolError(ErrorCode.NON_FINITE, f"{where} contains NaN or infinity")
        array = value
    else:
        array = array_from_wire(value, where, trailing=(), max_rows=_ANY_ROWS)
    if array.shape != (length,):
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY, f"{where}.shape must be [{length}], got {list(array.shape)}"
        )
    return array


@dataclass(frozen=True, kw_only=True, eq=False)
class Head:
    """A head pose: the VMC ``Head`` bone's local rotation, and optionally its position.

    The frame is Unity's as the VMC protocol's ``/VMC/Ext/Bone/Pos`` uses it: left-handed,
    +x the performer's right, +y up, +z where the face looks; the identity rotation is
    the head looking straight ahead.

    Attributes
    ----------
    rotation : (4,) float16/32/64
        Unit quaternion (x, y, z, w), norm within `HEAD_NORM_TOLERANCE` of 1.
    position : (3,) float16/32/64 or None
        Local position in metres, each component within ±`MAX_HEAD_POSITION`.

    Arrays keep their dtype and values, so a relayed head is bit for bit the one sent.
    """

    rotation: np.ndarray
    position: np.ndarray | None = None

    def __post_init__(self) -> None:
        rotation, position = _check(self.rotation, self.position, "head")
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "position", position)

    def serialize(self) -> dict[str, Any]:
        out: dict[str, Any] = {"rotation": array_to_wire(self.rotation)}
        if self.position is not None:
            out["position"] = array_to_wire(self.position)
        return out

    @classmethod
    def parse(cls, obj: Any, where: str) -> Head:
        """The head in a decoded wire map; ProtocolError (with ``where`` in it) otherwise."""
        check_map(obj, where)
        assert isinstance(obj, Mapping)
        if obj.get("rotation") is None:
            raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where}.rotation is required")
        rotation, position = _check(obj["rotation"], obj.get("position"), where)
        head = object.__new__(cls)  # checked above: skip __post_init__'s second pass
        head.__dict__.update(rotation=rotation, position=position)
        return head

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Head):
            return NotImplemented
        return _same(self.rotation, other.rotation) and _same(self.position, other.position)

    __hash__ = None  # type: ignore[assignment]


def _check(rotation: Any, position: Any, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A head's rotation and position (arrays or wire maps), checked as §5.3 asks."""
    rotation = _vector(rotation, f"{where}.rotation", 4)
    norm = float(np.linalg.norm(rotation.astype(np.float64)))
    if abs(norm - 1.0) > HEAD_NORM_TOLERANCE:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            f"{where}.rotation must be a unit quaternion (x, y, z, w), norm within "
            f"{HEAD_NORM_TOLERANCE:g} of 1, got norm {norm:.6g}",
        )
    if position is None:
        return rotation, None
    position = _vector(position, f"{where}.position", 3)
    largest = float(np.abs(position.astype(np.float64)).max())
    if largest > MAX_HEAD_POSITION:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            f"{where}.position components must be within ±{MAX_HEAD_POSITION:g} m, "
            f"got {largest:.6g}",
        )
    return rotation, position


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b))

"""The calibration messages (PROTOCOL.md §5.1.3, §5.2.5): `Calibrate` and its answer `Calibrated`.

Capturing or clearing the performer's neutral pose; the re-basing itself is the rig's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from facecast.protocol.arrays import array_from_wire, array_to_wire
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import (
    check_bool,
    check_float,
    check_str,
    check_uint,
    read_bool,
    read_float,
    read_str,
    read_uint,
)
from facecast.protocol.limits import Limits
from facecast.protocol.message import (
    _DEFAULT_LIMITS,
    Message,
    _ArrayMessage,
    _check_array,
    _header,
)

#: The names ``calibrate.blinks`` takes: ARKit's two blinks (the eyes' closures).
BLINK_NAMES = ("eyeBlinkLeft", "eyeBlinkRight")


@dataclass(frozen=True, kw_only=True, eq=False)
class Calibrate(_ArrayMessage):
    """Capture (or clear) the performer's neutral pose (§5.1.3).

    Attributes
    ----------
    points : (K, 3) float array or None
        The neutral explicitly; None means "use the next frame received".
    reset : bool
        Clear the captured neutral instead; excludes ``points``.
    noise : float or None
        The performer's landmark noise (standard deviation per coordinate, in the points'
        units), e.g. measured over the frames the neutral was held; >= 0. Given, the server
        re-bases the rig noise-aware and bounded; None: exactly, as before the field.
    blinks : {name: (K, 3) float array} or None
        The performer's captured closed eyes, under ``BLINK_NAMES`` (one or both), each with
        as many points as ``points``; needs ``points`` and ``noise``. The server maps each
        blink weight so that the re-based rig reads the performer's closed eye as 1.
    blink_contrast : (low, high) floats or None
        The performer's own curve for those blinks, 0 <= low < high <= 1: a mapped blink
        below low reads open, above high closed (the server's own when None: 0.4, 0.8 for a
        rig with eye-look examples, 0.4, 0.7 for one without); needs ``blinks``.
    """

    TYPE: ClassVar[str] = "calibrate"
    points: np.ndarray | None = None
    reset: bool = False
    noise: float | None = None
    blinks: Mapping[str, np.ndarray] | None = None
    blink_contrast: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        check_bool(self.reset, "calibrate.reset")
        if self.points is not None:
            _check_array(self.points, "calibrate.points", (3,))
            if self.reset:
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD,
                    "calibrate.points and calibrate.reset exclude each other",
                )
        if self.noise is not None:
            noise = check_float(self.noise, "calibrate.noise")
            if noise < 0:
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD, f"calibrate.noise must be >= 0, got {noise!r}"
                )
            if self.reset:
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD,
                    "calibrate.noise and calibrate.reset exclude each other",
                )
            object.__setattr__(self, "noise", noise)
        if self.blinks is not None:
            self._check_blinks(self.blinks)
        if self.blink_contrast is not None:
            object.__setattr__(self, "blink_contrast", self._checked_contrast(self.blink_contrast))

    def _checked_contrast(self, value: Any) -> tuple[float, float]:
        where = "calibrate.blink_contrast"
        if self.blinks is None:
            raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where} needs calibrate.blinks")
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ProtocolError(ErrorCode.INVALID_FIELD, f"{where} must be [low, high]")
        low, high = check_float(value[0], f"{where}[0]"), check_float(value[1], f"{where}[1]")
        if not 0.0 <= low < high <= 1.0:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"{where} must be 0 <= low < high <= 1, got [{low!r}, {high!r}]",
            )
        return low, high

    def _check_blinks(self, blinks: Any) -> None:
        if not isinstance(blinks, Mapping) or not blinks:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, "calibrate.blinks must be a non-empty map of arrays"
            )
        unknown = [name for name in blinks if name not in BLINK_NAMES]
        if unknown:
            raise _not_a_blink(unknown[0])
        if self.points is None or self.noise is None:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, "calibrate.blinks needs calibrate.points and .noise"
            )
        for name, array in blinks.items():
            _check_array(array, f"calibrate.blinks.{name}", (3,))
            if array.shape != self.points.shape:
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD,
                    f"calibrate.blinks.{name} has {array.shape[0]} points, calibrate.points "
                    f"{self.points.shape[0]}",
                )

    def serialize(self) -> dict[str, Any]:
        out = {
            **_header(self.TYPE),
            "points": None if self.points is None else array_to_wire(self.points),
            "reset": self.reset,
        }
        # Absent unless given: a calibrate without it keeps its bytes (§10.4).
        if self.noise is not None:
            out["noise"] = self.noise
        if self.blinks is not None:  # absent unless given, as noise
            out["blinks"] = {name: array_to_wire(a) for name, a in self.blinks.items()}
        if self.blink_contrast is not None:  # absent unless given, as blinks
            out["blink_contrast"] = list(self.blink_contrast)
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Calibrate:
        points = obj.get("points")
        return cls(
            points=None
            if points is None
            else array_from_wire(
                points, "calibrate.points", trailing=(3,), max_rows=limits.max_points
            ),
            reset=read_bool(obj, "reset", "calibrate.reset", False),
            noise=read_float(obj, "noise", "calibrate.noise", None),
            blinks=_read_blinks(obj.get("blinks"), limits),
            blink_contrast=obj.get("blink_contrast"),  # checked as the message is built
        )


def _not_a_blink(name: Any) -> ProtocolError:
    return ProtocolError(
        ErrorCode.INVALID_FIELD,
        f"calibrate.blinks: {str(name)[:64]!r} is not one of {', '.join(BLINK_NAMES)}",
    )


def _read_blinks(value: Any, limits: Limits) -> dict[str, np.ndarray] | None:
    """``calibrate.blinks`` from the wire: a map of at most ``BLINK_NAMES`` to arrays."""
    if value is None:
        return None
    if not isinstance(value, Mapping) or len(value) > len(BLINK_NAMES):
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            f"calibrate.blinks must be a map of at most {len(BLINK_NAMES)} arrays",
        )
    blinks = {}
    for name, array in value.items():
        if name not in BLINK_NAMES:  # before the key names anything in an error
            raise _not_a_blink(name)
        blinks[name] = array_from_wire(
            array, f"calibrate.blinks.{name}", trailing=(3,), max_rows=limits.max_points
        )
    return blinks


@dataclass(frozen=True, kw_only=True)
class Calibrated(Message):
    """Acknowledges a `Calibrate` (§5.2.5).

    Attributes
    ----------
    active : bool
        True when a neutral is now captured, False after a reset.
    seq : int or None
        The frame whose points became the neutral, or None (explicit points, reset).
    smoothing : str or None
        The filter the session's ``hello.smoothing`` runs from here on, as
        ``ready.smoothing``: a calibrate's ``noise`` turns an auto smoothing that had no
        noise into the Kalman filter (§5.2.5). None (absent) without smoothing.
    """

    TYPE: ClassVar[str] = "calibrated"
    active: bool
    seq: int | None = None
    smoothing: str | None = None

    def __post_init__(self) -> None:
        check_bool(self.active, "calibrated.active")
        if self.seq is not None:
            check_uint(self.seq, "calibrated.seq")
        if self.smoothing is not None:
            check_str(self.smoothing, "calibrated.smoothing", None)

    def serialize(self) -> dict[str, Any]:
        out = {**_header(self.TYPE), "active": self.active, "seq": self.seq}
        if self.smoothing is not None:  # absent without smoothing: §10's bytes stay
            out["smoothing"] = self.smoothing
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Calibrated:
        return cls(
            active=read_bool(obj, "active", "calibrated.active"),
            seq=read_uint(obj, "seq", "calibrated.seq", None),
            smoothing=read_str(obj, "smoothing", "calibrated.smoothing", limits, None),
        )

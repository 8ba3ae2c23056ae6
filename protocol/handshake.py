"""The handshake messages (PROTOCOL.md §5.1.1, §5.2.1): `Hello`, its `Smoothing`, `Ready`.

What a session asks for and what the server grants; also the vocabulary they negotiate
(outputs, dtypes, smoothing filters). Framing and dispatch live in codec.py.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final

import numpy as np

from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fields import (
    check_bool,
    check_float,
    check_str,
    check_str_length,
    check_uint,
    read_bool,
    read_float,
    read_map,
    read_str,
    read_uint,
)
from facecast.protocol.limits import Limits
from facecast.protocol.message import (
    _DEFAULT_LIMITS,
    Message,
    _ArrayMessage,
    _check_choice,
    _fail,
    _header,
)

#: What a channel clones for its watchers (§2.4): weights (M,) or target vertices (V, 3).
CHANNEL_OUTPUTS: Final = ("weights", "vertices")
#: What a ``/v1/stream`` session streams back: a channel's outputs, or only the N vertices
#: the rig's examples move (``moving``, §5.2.1; their indices come once, in ``ready``).
OUTPUTS: Final = (*CHANNEL_OUTPUTS, "moving")
#: Dtypes a client may negotiate for results.
RESULT_DTYPES: Final = ("f32", "f16")
#: What a channel watcher may ask for (§2.4): the channel outputs, or the published points.
WATCH_OUTPUTS: Final = (*CHANNEL_OUTPUTS, "points")
#: All that ``ready.output`` may say.
READY_OUTPUTS: Final = (*OUTPUTS, "points")
#: ``ready.rig.moving``: the moving vertices' indices as little-endian uint32 (§5.2.1).
MOVING_DTYPE: Final = np.dtype("<u4")
#: Dtypes of ``points`` results: f16 would blur feature points, f64 keeps f64 frames exact.
POINTS_DTYPES: Final = ("f32", "f64")
#: What the one-euro filter smooths: the incoming points or the outgoing weights.
SMOOTHING_TARGETS: Final = ("points", "weights")
#: The smoothing filters (§5.1.1): one-euro or a constant-velocity Kalman; a smoothing that
#: names neither is "auto" (the Kalman where it can run, else the one-euro).
SMOOTHING_FILTERS: Final = ("one-euro", "kalman")
#: The Kalman filter's default acceleration, landmark-noise units per s^2 (§5.1.1; the same
#: figure as ``facecast.rig.filters.KALMAN_ACCELERATION``, which protocol/ cannot import).
KALMAN_ACCELERATION: Final = 480.0
#: Longest error message a server sends; longer ones are cut, so they always decode.
MAX_ERROR_MESSAGE: Final = 256


def _result_dtypes(output: str) -> tuple[str, ...]:
    return POINTS_DTYPES if output == "points" else RESULT_DTYPES


def _checked_moving(moving: Any, num_vertices: int) -> np.ndarray:
    """``ready.rig.moving`` as a read-only (N,) uint32 array, or INVALID_FIELD."""
    if not isinstance(moving, np.ndarray) or moving.ndim != 1 or moving.dtype.kind not in "iu":
        raise _fail("ready.rig.moving", "a 1-d integer array", moving)
    if moving.size == 0:
        raise ProtocolError(ErrorCode.INVALID_FIELD, "ready.rig.moving must not be empty")
    values = moving.astype(np.int64)
    if values[0] < 0 or values[-1] >= num_vertices or np.any(np.diff(values) <= 0):
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            f"ready.rig.moving must be strictly increasing vertex indices below {num_vertices}",
        )
    out = np.array(moving, dtype=MOVING_DTYPE)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, kw_only=True)
class Smoothing:
    """Smoothing filter parameters, §5.1.1: one-euro (Casiez et al. 2012) or Kalman.

    Attributes
    ----------
    filter : {"one-euro", "kalman"} or None
        The filter; the keys below it say which apply. None (the default, "auto") leaves
        it to the server: the Kalman filter where it can run (target "points" and a noise
        known, from ``noise`` or the rig's fit), else the one-euro filter.
    min_cutoff : float
        Minimum cutoff frequency in Hz, > 0; lower means smoother at rest.
    beta : float
        Speed coefficient, >= 0; higher means less lag on fast motion.
    d_cutoff : float
        Cutoff frequency in Hz for the derivative, > 0.
    target : {"points", "weights"}
        Smooth the incoming feature points or the outgoing weights (Kalman: points only).
    acceleration : float
        Kalman: how hard the face may accelerate, in landmark-noise units per s^2 (the
        filter's process noise is acceleration * noise), > 0.
    noise : float or None
        Kalman: the landmark noise std in source units, > 0; None (the default) is the
        noise the session's rig was fitted with (the server refuses a rig without one).
    """

    # Defaults: the one-euro setting with the least jitter at under a frame of lag on real
    # Live Link takes (README "Temporal coherence"; beta per source unit, centimetres there).
    min_cutoff: float = 2.0
    beta: float = 2.0
    d_cutoff: float = 1.0
    target: str = "points"
    # Kalman: acceleration 480 noise units / s^2, less jitter and less lag than the
    # one-euro defaults on both real takes at 0.1-0.5 mm of noise (README "Temporal
    # coherence"), hence the auto default (None) runs it wherever it can.
    filter: str | None = None
    acceleration: float = KALMAN_ACCELERATION
    noise: float | None = None

    def __post_init__(self) -> None:
        checks = [("min_cutoff", 0.0, True), ("beta", 0.0, False), ("d_cutoff", 0.0, True)]
        checks.append(("acceleration", 0.0, True))
        if self.noise is not None:
            checks.append(("noise", 0.0, True))
        for name, low, strict in checks:
            where = f"hello.options.smoothing.{name}"
            value = check_float(getattr(self, name), where)
            if value < low or (strict and value == low):
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD,
                    f"{where} must be {'>' if strict else '>='} {low}, got {value!r}",
                )
            object.__setattr__(self, name, value)
        _check_choice(self.target, "hello.options.smoothing.target", SMOOTHING_TARGETS)
        if self.filter is not None:
            _check_choice(self.filter, "hello.options.smoothing.filter", SMOOTHING_FILTERS)
        if self.filter == "kalman" and self.target != "points":
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                "hello.options.smoothing.target must be 'points' with filter 'kalman' (its "
                "noise model is the landmarks')",
            )

    def serialize(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "min_cutoff": self.min_cutoff,
            "beta": self.beta,
            "d_cutoff": self.d_cutoff,
            "target": self.target,
        }
        # Default smoothing keeps its four keys (and bytes, §10.1): "filter" travels only
        # when named, "acceleration" with a Kalman (§10.14) or when not the default.
        if self.filter is not None:
            out["filter"] = self.filter
        if self.filter == "kalman" or self.acceleration != KALMAN_ACCELERATION:
            out["acceleration"] = self.acceleration
        if self.noise is not None:
            out["noise"] = self.noise
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Smoothing:
        w = "hello.options.smoothing."
        return cls(
            min_cutoff=read_float(obj, "min_cutoff", w + "min_cutoff", cls.min_cutoff),
            beta=read_float(obj, "beta", w + "beta", cls.beta),
            d_cutoff=read_float(obj, "d_cutoff", w + "d_cutoff", cls.d_cutoff),
            target=read_str(
                obj, "target", w + "target", limits, cls.target, choices=SMOOTHING_TARGETS
            ),
            filter=read_str(obj, "filter", w + "filter", limits, None, choices=SMOOTHING_FILTERS),
            acceleration=read_float(obj, "acceleration", w + "acceleration", cls.acceleration),
            noise=read_float(obj, "noise", w + "noise", None),
        )


@dataclass(frozen=True, kw_only=True)
class Hello(Message):
    """Opens a session (§5.1.1): which rig, what to stream back, and how.

    On the wire the five options travel in a nested ``options`` map.
    """

    TYPE: ClassVar[str] = "hello"
    rig: str
    output: str = "weights"
    dtype: str = "f32"
    align: bool = False
    align_scale: bool = False
    calibration: bool = False
    smoothing: Smoothing | None = None

    def __post_init__(self) -> None:
        check_str(self.rig, "hello.rig", None)
        _check_choice(self.output, "hello.output", OUTPUTS)
        _check_choice(self.dtype, "hello.dtype", RESULT_DTYPES)
        check_bool(self.align, "hello.options.align")
        check_bool(self.align_scale, "hello.options.scale")
        check_bool(self.calibration, "hello.options.calibration")
        if self.align_scale and not self.align:
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, "hello.options.scale needs hello.options.align"
            )
        if self.smoothing is not None and not isinstance(self.smoothing, Smoothing):
            raise _fail("hello.options.smoothing", "nil or a map", self.smoothing)

    def serialize(self) -> dict[str, Any]:
        return {
            **_header(self.TYPE),
            "rig": self.rig,
            "output": self.output,
            "dtype": self.dtype,
            "options": {
                "align": self.align,
                "scale": self.align_scale,
                "calibration": self.calibration,
                "smoothing": None if self.smoothing is None else self.smoothing.serialize(),
            },
        }

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Hello:
        options = read_map(obj, "options", "hello.options", {})
        smoothing = read_map(options, "smoothing", "hello.options.smoothing", None)
        rig = read_str(obj, "rig", "hello.rig", limits)
        return cls(
            rig=rig,
            output=read_str(obj, "output", "hello.output", limits, "weights", choices=OUTPUTS),
            dtype=read_str(obj, "dtype", "hello.dtype", limits, "f32", choices=RESULT_DTYPES),
            align=read_bool(options, "align", "hello.options.align", False),
            align_scale=read_bool(options, "scale", "hello.options.scale", False),
            calibration=read_bool(options, "calibration", "hello.options.calibration", False),
            smoothing=None if smoothing is None else Smoothing.parse(smoothing, limits),
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class Ready(_ArrayMessage):
    """The session is open (§5.2.1): what the rig is, what will stream, and the limits.

    Attributes
    ----------
    session : str
        Server-chosen session id (for logs and support).
    rig : str
        Rig id.
    names : tuple of str, length M
        Blendshape/example names; ``names[0]`` is the neutral.
    num_points : int
        K, feature points every frame must carry.
    num_vertices : int
        V, vertices of the target mesh.
    output, dtype : str
        What each ``result`` carries, as negotiated; "points" only for a channel
        watcher that asked for the published frames (§2.4), with dtype "f32" or "f64".
    limits : mapping of str to number
        Limits the server enforces (§7); unknown keys are informational.
    moving : (N,) uint32 or None
        With output "moving" (and only then): the indices, strictly increasing and
        below V, of the vertices each result carries, in that order.
    smoothing : str or None
        The filter the session's ``hello.smoothing`` runs ("kalman" or "one-euro"; a
        client accepts any other name), None when it smooths nothing or the server does
        not say.
    """

    TYPE: ClassVar[str] = "ready"
    session: str
    rig: str
    names: tuple[str, ...]
    num_points: int
    num_vertices: int
    output: str
    dtype: str
    limits: Mapping[str, int | float] = field(default_factory=dict)
    moving: np.ndarray | None = None
    smoothing: str | None = None

    def __post_init__(self) -> None:
        check_str(self.session, "ready.session", None)
        if self.smoothing is not None:
            check_str(self.smoothing, "ready.smoothing", None)
        check_str(self.rig, "ready.rig.id", None)
        object.__setattr__(self, "names", tuple(self.names))
        for name in self.names:
            if type(name) is not str:
                raise _fail("ready.rig.names[]", "a string", name)
        if not self.names:
            raise ProtocolError(ErrorCode.INVALID_FIELD, "ready.rig.names must not be empty")
        check_uint(self.num_points, "ready.rig.k")
        check_uint(self.num_vertices, "ready.rig.v")
        _check_choice(self.output, "ready.output", READY_OUTPUTS)
        _check_choice(self.dtype, "ready.dtype", _result_dtypes(self.output))
        if (self.moving is None) != (self.output != "moving"):
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, "ready.rig.moving is present exactly when output is moving"
            )
        if self.moving is not None:
            object.__setattr__(self, "moving", _checked_moving(self.moving, self.num_vertices))
        if not isinstance(self.limits, Mapping):
            raise _fail("ready.limits", "a map", self.limits)
        for key, value in self.limits.items():
            if type(key) is not str:
                raise _fail("ready.limits key", "a string", key)
            if type(value) is int:
                continue
            if type(value) is not float or not math.isfinite(value):
                raise _fail(f"ready.limits.{key}", "a finite number", value)

    @property
    def num_examples(self) -> int:
        """M, the number of examples (and of weights per result)."""
        return len(self.names)

    @property
    def result_vertices(self) -> int:
        """Rows of a vertices result: N with output "moving", else V."""
        return self.num_vertices if self.moving is None else int(self.moving.size)

    def serialize(self) -> dict[str, Any]:
        rig: dict[str, Any] = {
            "id": self.rig,
            "m": len(self.names),
            "names": list(self.names),
            "k": self.num_points,
            "v": self.num_vertices,
        }
        if self.moving is not None:
            rig["moving"] = self.moving.data  # stored as MOVING_DTYPE by __post_init__
        out: dict[str, Any] = {
            **_header(self.TYPE),
            "session": self.session,
            "rig": rig,
            "output": self.output,
            "dtype": self.dtype,
            "limits": dict(self.limits),
        }
        if self.smoothing is not None:  # absent without smoothing: §10.6's bytes stay
            out["smoothing"] = self.smoothing
        return out

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Ready:
        rig = read_map(obj, "rig", "ready.rig")
        names = rig.get("names")
        if type(names) is not list:
            raise _fail("ready.rig.names", "an array", names)
        for name in names:
            if type(name) is not str:
                raise _fail("ready.rig.names[]", "a string", name)
            check_str_length(name, "ready.rig.names[]", limits)
        m = read_uint(rig, "m", "ready.rig.m")
        if m != len(names):
            raise ProtocolError(
                ErrorCode.INVALID_FIELD, f"ready.rig.m is {m} but there are {len(names)} names"
            )
        num_vertices = read_uint(rig, "v", "ready.rig.v")
        if num_vertices > limits.max_vertices:
            raise ProtocolError(
                ErrorCode.MESSAGE_TOO_LARGE,
                f"ready.rig.v is {num_vertices}, more than the limit {limits.max_vertices}",
            )
        num_points = read_uint(rig, "k", "ready.rig.k")
        if num_points > limits.max_points:
            raise ProtocolError(
                ErrorCode.MESSAGE_TOO_LARGE,
                f"ready.rig.k is {num_points}, more than the limit {limits.max_points}",
            )
        output = read_str(obj, "output", "ready.output", limits, choices=READY_OUTPUTS)
        moving = rig.get("moving")
        if moving is not None:
            if type(moving) is not bytes:
                raise _fail("ready.rig.moving", "bin", moving)
            if len(moving) % MOVING_DTYPE.itemsize:
                raise ProtocolError(
                    ErrorCode.INVALID_FIELD,
                    f"ready.rig.moving holds {len(moving)} bytes, not a whole number of uint32",
                )
            if len(moving) // MOVING_DTYPE.itemsize > limits.max_vertices:
                raise ProtocolError(
                    ErrorCode.MESSAGE_TOO_LARGE,
                    f"ready.rig.moving has more than the limit of {limits.max_vertices} vertices",
                )
            moving = np.frombuffer(moving, dtype=MOVING_DTYPE)
        server_limits = read_map(obj, "limits", "ready.limits", {})
        for key, value in server_limits.items():
            if type(key) is not str:
                raise _fail("ready.limits key", "a string", key)
            check_str_length(key, "ready.limits key", limits)
            check_float(value, f"ready.limits.{key}")
        return cls(
            session=read_str(obj, "session", "ready.session", limits),
            rig=read_str(rig, "id", "ready.rig.id", limits),
            names=tuple(names),
            num_points=num_points,
            num_vertices=num_vertices,
            output=output,
            dtype=read_str(obj, "dtype", "ready.dtype", limits, choices=_result_dtypes(output)),
            limits=server_limits,
            moving=moving,
            smoothing=read_str(obj, "smoothing", "ready.smoothing", limits, None),
        )

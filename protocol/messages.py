"""The twelve protocol messages as frozen dataclasses with serialize/parse (PROTOCOL.md §5).

Each class checks its own fields and converts to and from a msgpack-ready dict; framing,
version and type dispatch live in codec.py, session order in connection.py.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Final, Self, TypeVar

import numpy as np

from facecast.protocol.arrays import WIRE_DTYPES, array_from_wire, array_to_wire, wire_dtype_name
from facecast.protocol.errors import ErrorCode, ProtocolError, error_code
from facecast.protocol.fields import (
    check_bool,
    check_float,
    check_str,
    check_str_length,
    check_uint,
    invalid,
    read_bool,
    read_float,
    read_int,
    read_map,
    read_str,
    read_uint,
)
from facecast.protocol.head import Head
from facecast.protocol.limits import Limits

PROTOCOL_VERSION: Final = 1

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

_DEFAULT_LIMITS: Final = Limits()


def _fail(where: str, expected: str, value: Any) -> ProtocolError:
    return invalid(where, expected, value)


def _check_choice(value: Any, where: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD, f"{where} must be one of {list(choices)}, got {value!r}"
        )


def _check_array(value: Any, where: str, trailing: tuple[int, ...]) -> None:
    if (
        not isinstance(value, np.ndarray)
        or value.ndim != 1 + len(trailing)
        or value.shape[1:] != trailing
        or value.shape[0] == 0
        or value.dtype.kind != "f"
        or value.dtype.itemsize not in (2, 4, 8)
    ):
        shape = f"(N, {', '.join(map(str, trailing))})" if trailing else "(N,)"
        got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value)
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY, f"{where} must be a non-empty float {shape} array, got {got}"
        )


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


def _result_dtypes(output: str) -> tuple[str, ...]:
    return POINTS_DTYPES if output == "points" else RESULT_DTYPES


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and bool(np.array_equal(a, b))
        )
    return bool(a == b)


class Message:
    """Base of all messages: ``TYPE`` is the wire ``type``; ``serialize`` gives the map."""

    TYPE: ClassVar[str]

    def serialize(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        raise NotImplementedError


class _ArrayMessage(Message):
    """Equality for messages holding arrays: same dtype, shape and values."""

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))  # type: ignore[arg-type]

    __hash__ = None  # type: ignore[assignment]


_M = TypeVar("_M", bound=Message)


def _checked(cls: type[_M], **values: Any) -> _M:
    """A message of ``cls`` from field values its ``parse`` has already validated.

    Skips ``__post_init__``, which would check the same fields again (a third of a frame's
    decode). Every field must be given, each exactly as ``__post_init__`` would store it.
    """
    message = object.__new__(cls)
    message.__dict__.update(values)
    return message


def _header(kind: str) -> dict[str, Any]:
    return {"v": PROTOCOL_VERSION, "type": kind}


def _check_head(value: Any, where: str) -> None:
    if value is not None and not isinstance(value, Head):
        raise _fail(where, "nil or a Head", value)


def _read_head(obj: Mapping[str, Any], where: str) -> Head | None:
    value = obj.get("head")
    return None if value is None else Head.parse(value, where)


# --- client -> server -------------------------------------------------------------------


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
    """

    TYPE: ClassVar[str] = "frame"
    seq: int
    ts: float
    points: np.ndarray
    head: Head | None = None

    def __post_init__(self) -> None:
        check_uint(self.seq, "frame.seq")
        object.__setattr__(self, "ts", check_float(self.ts, "frame.ts"))
        _check_array(self.points, "frame.points", (3,))
        _check_head(self.head, "frame.head")

    def serialize(self) -> dict[str, Any]:
        out = {
            **_header(self.TYPE),
            "seq": self.seq,
            "ts": self.ts,
            "points": array_to_wire(self.points),
        }
        if self.head is not None:  # absent otherwise: a frame without one keeps its bytes
            out["head"] = self.head.serialize()
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
        )


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
    """

    TYPE: ClassVar[str] = "calibrate"
    points: np.ndarray | None = None
    reset: bool = False
    noise: float | None = None

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

    def serialize(self) -> dict[str, Any]:
        out = {
            **_header(self.TYPE),
            "points": None if self.points is None else array_to_wire(self.points),
            "reset": self.reset,
        }
        # Absent unless given: a calibrate without it keeps its bytes (§10.4).
        if self.noise is not None:
            out["noise"] = self.noise
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
        )


@dataclass(frozen=True, kw_only=True)
class _Probe(Message):
    """Fields shared by `Ping` and `Pong`."""

    id: int
    ts: float

    def __post_init__(self) -> None:
        check_uint(self.id, f"{self.TYPE}.id")
        object.__setattr__(self, "ts", check_float(self.ts, f"{self.TYPE}.ts"))

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "id": self.id, "ts": self.ts}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        return cls(
            id=read_uint(obj, "id", f"{cls.TYPE}.id"), ts=read_float(obj, "ts", f"{cls.TYPE}.ts")
        )


@dataclass(frozen=True, kw_only=True)
class Ping(_Probe):
    """Liveness and round-trip probe (§5.1.4); answered by a `Pong` with the same fields.

    Attributes
    ----------
    id : int
        Sender-chosen probe id.
    ts : float
        Sender's clock when sent, seconds.
    """

    TYPE: ClassVar[str] = "ping"


# --- server -> client -------------------------------------------------------------------


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

    def __post_init__(self) -> None:
        # On the server's per-frame path: a handful of type checks, no array scans.
        check_uint(self.seq, "result.seq")
        object.__setattr__(self, "ts", check_float(self.ts, "result.ts"))
        check_uint(self.proc_us, "result.proc_us")
        check_uint(self.dropped, "result.dropped")
        _check_head(self.head, "result.head")
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
        )


@dataclass(frozen=True, kw_only=True)
class Error(Message):
    """Something went wrong (§5.2.3, codes in §6).

    ``code`` is an `ErrorCode`, or a bare int for a code newer than this library.
    ``message`` is cut to `MAX_ERROR_MESSAGE` characters. ``dropped``: on RATE_LIMITED,
    the session's total of discarded frames so far, like ``result.dropped`` (§8); None
    (not sent) on other errors.
    """

    TYPE: ClassVar[str] = "error"
    code: ErrorCode | int
    message: str
    seq: int | None = None
    fatal: bool = False
    dropped: int | None = None

    def __post_init__(self) -> None:
        if type(self.code) is not int and not isinstance(self.code, ErrorCode):
            raise _fail("error.code", "an integer", self.code)
        object.__setattr__(self, "code", error_code(int(self.code)))
        if type(self.message) is not str:
            raise _fail("error.message", "a string", self.message)
        if len(self.message) > MAX_ERROR_MESSAGE:
            object.__setattr__(self, "message", self.message[: MAX_ERROR_MESSAGE - 1] + "…")
        if self.seq is not None:
            check_uint(self.seq, "error.seq")
        check_bool(self.fatal, "error.fatal")
        if self.dropped is not None:
            check_uint(self.dropped, "error.dropped")

    def serialize(self) -> dict[str, Any]:
        fields = {
            **_header(self.TYPE),
            "code": int(self.code),
            "message": self.message,
            "seq": self.seq,
            "fatal": self.fatal,
        }
        if self.dropped is not None:
            fields["dropped"] = self.dropped
        return fields

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Error:
        message = obj.get("message")
        if type(message) is not str:
            raise _fail("error.message", "a string", message)
        check_str_length(message, "error.message", limits)
        return cls(
            code=read_int(obj, "code", "error.code"),
            message=message,
            seq=read_uint(obj, "seq", "error.seq", None),
            fatal=read_bool(obj, "fatal", "error.fatal", False),
            dropped=read_uint(obj, "dropped", "error.dropped", None),
        )

    def to_exception(self) -> ProtocolError:
        """This error as a `ProtocolError` a client can raise."""
        return ProtocolError(self.code, self.message, seq=self.seq, fatal=self.fatal)

    @classmethod
    def of(cls, error: ProtocolError) -> Error:
        """The `Error` message that reports ``error`` to the peer."""
        return cls(code=error.code, message=error.message, seq=error.seq, fatal=error.fatal)


@dataclass(frozen=True, kw_only=True)
class Pong(_Probe):
    """Answer to a `Ping` (§5.2.4): ``id`` and ``ts`` echoed unchanged."""

    TYPE: ClassVar[str] = "pong"


@dataclass(frozen=True, kw_only=True)
class Calibrated(Message):
    """Acknowledges a `Calibrate` (§5.2.5).

    Attributes
    ----------
    active : bool
        True when a neutral is now captured, False after a reset.
    seq : int or None
        The frame whose points became the neutral, or None (explicit points, reset).
    """

    TYPE: ClassVar[str] = "calibrated"
    active: bool
    seq: int | None = None

    def __post_init__(self) -> None:
        check_bool(self.active, "calibrated.active")
        if self.seq is not None:
            check_uint(self.seq, "calibrated.seq")

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "active": self.active, "seq": self.seq}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Calibrated:
        return cls(
            active=read_bool(obj, "active", "calibrated.active"),
            seq=read_uint(obj, "seq", "calibrated.seq", None),
        )


@dataclass(frozen=True, kw_only=True)
class _ChannelEvent(Message):
    """Fields shared by `ChannelIdle` and `ChannelLive`."""

    channel: str

    def __post_init__(self) -> None:
        check_str(self.channel, f"{self.TYPE}.channel", None)

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "channel": self.channel}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> Self:
        return cls(channel=read_str(obj, "channel", f"{cls.TYPE}.channel", limits))


@dataclass(frozen=True, kw_only=True)
class ChannelIdle(_ChannelEvent):
    """The watched channel has no publisher (§5.2.6)."""

    TYPE: ClassVar[str] = "channel_idle"


@dataclass(frozen=True, kw_only=True)
class ChannelLive(_ChannelEvent):
    """The watched channel has a publisher again (§5.2.6)."""

    TYPE: ClassVar[str] = "channel_live"


@dataclass(frozen=True, kw_only=True)
class FaceLost(Message):
    """The publisher's tracker lost the face (§5.2.7); ``since`` is the last frame's ``ts``."""

    TYPE: ClassVar[str] = "face_lost"
    since: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "since", check_float(self.since, "face_lost.since"))

    def serialize(self) -> dict[str, Any]:
        return {**_header(self.TYPE), "since": self.since}

    @classmethod
    def parse(cls, obj: Mapping[str, Any], limits: Limits = _DEFAULT_LIMITS) -> FaceLost:
        return cls(since=read_float(obj, "since", "face_lost.since"))


ClientMessage = Hello | Frame | Calibrate | Ping
ServerMessage = Ready | Result | Error | Pong | Calibrated | ChannelIdle | ChannelLive | FaceLost

CLIENT_MESSAGES: Final[dict[str, type[Message]]] = {
    cls.TYPE: cls for cls in (Hello, Frame, Calibrate, Ping)
}
SERVER_MESSAGES: Final[dict[str, type[Message]]] = {
    cls.TYPE: cls
    for cls in (Ready, Result, Error, Pong, Calibrated, ChannelIdle, ChannelLive, FaceLost)
}

__all__ = [
    "CHANNEL_OUTPUTS",
    "CLIENT_MESSAGES",
    "MOVING_DTYPE",
    "OUTPUTS",
    "POINTS_DTYPES",
    "PROTOCOL_VERSION",
    "READY_OUTPUTS",
    "RESULT_DTYPES",
    "SERVER_MESSAGES",
    "SMOOTHING_TARGETS",
    "WATCH_OUTPUTS",
    "WIRE_DTYPES",
    "Calibrate",
    "Calibrated",
    "ChannelIdle",
    "ChannelLive",
    "ClientMessage",
    "Error",
    "FaceLost",
    "Frame",
    "Hello",
    "Message",
    "Ping",
    "Pong",
    "Ready",
    "Result",
    "ServerMessage",
    "Smoothing",
]

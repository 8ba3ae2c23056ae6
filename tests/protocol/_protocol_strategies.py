"""Hypothesis strategies for valid protocol messages and for hostile msgpack input.

Test data only; shared by the round-trip and fuzz tests.
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from facecast.protocol import (
    Calibrate,
    Calibrated,
    ChannelIdle,
    ChannelLive,
    Error,
    ErrorCode,
    FaceLost,
    Frame,
    Hello,
    Ping,
    Pong,
    Ready,
    Result,
    Smoothing,
)

uint64 = st.integers(0, 2**64 - 1)
finite = st.floats(allow_nan=False, allow_infinity=False)
text = st.text(min_size=1, max_size=40)
positive = st.floats(min_value=1e-6, max_value=1e6)


def float_arrays(dtype: str, shape) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(
        np.dtype(dtype), shape, elements={"allow_nan": False, "allow_infinity": False}
    )


def points() -> st.SearchStrategy[np.ndarray]:
    return st.sampled_from(["<f2", "<f4", "<f8"]).flatmap(
        lambda dt: float_arrays(dt, st.tuples(st.integers(1, 20), st.just(3)))
    )


smoothing = st.builds(
    Smoothing,
    min_cutoff=positive,
    beta=st.floats(min_value=0.0, max_value=1e6),
    d_cutoff=positive,
    target=st.sampled_from(["points", "weights"]),
    filter=st.sampled_from([None, "one-euro"]),  # auto or named ("kalman": points only)
    acceleration=positive,
    noise=st.none() | positive,
)


@st.composite
def hellos(draw) -> Hello:
    align = draw(st.booleans())
    return Hello(
        rig=draw(text),
        output=draw(st.sampled_from(["weights", "vertices"])),
        dtype=draw(st.sampled_from(["f32", "f16"])),
        align=align,
        align_scale=align and draw(st.booleans()),
        calibration=draw(st.booleans()),
        smoothing=draw(st.none() | smoothing),
    )


@st.composite
def results(draw) -> Result:
    dtype = draw(st.sampled_from(["<f2", "<f4"]))
    if draw(st.booleans()):
        values = {"weights": draw(float_arrays(dtype, st.tuples(st.integers(1, 50))))}
    else:
        values = {"vertices": draw(float_arrays(dtype, st.tuples(st.integers(1, 50), st.just(3))))}
    return Result(
        seq=draw(uint64), ts=draw(finite), proc_us=draw(uint64), dropped=draw(uint64),
        server_ts=draw(st.none() | finite), **values,
    )  # fmt: skip


client_messages = st.one_of(
    hellos(),
    st.builds(Frame, seq=uint64, ts=finite, points=points()),
    st.builds(
        Calibrate,
        points=st.none() | points(),
        noise=st.none() | st.floats(0.0, 1e300, allow_nan=False, allow_infinity=False),
    ),
    st.builds(Calibrate, reset=st.booleans()),
    st.builds(Ping, id=uint64, ts=finite),
)

server_messages = st.one_of(
    st.builds(
        Ready,
        session=text,
        rig=text,
        names=st.lists(text, min_size=1, max_size=10).map(tuple),
        num_points=st.integers(0, 4096),
        num_vertices=st.integers(0, 2_000_000),
        output=st.sampled_from(["weights", "vertices"]),
        dtype=st.sampled_from(["f32", "f16"]),
        limits=st.dictionaries(text, st.integers(-(2**63), 2**64 - 1) | finite, max_size=5),
    ),
    results(),
    st.builds(
        Error,
        code=st.sampled_from(list(ErrorCode)) | st.integers(0, 9999),
        message=st.text(max_size=200),
        seq=st.none() | uint64,
        fatal=st.booleans(),
    ),
    st.builds(Pong, id=uint64, ts=finite),
    st.builds(Calibrated, active=st.booleans(), seq=st.none() | uint64),
    st.builds(ChannelIdle, channel=text),
    st.builds(ChannelLive, channel=text),
    st.builds(FaceLost, since=finite),
)

# Any value msgpack can carry (no ext types), nested a few levels.
msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=64),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=10,
)

_KEYS = [
    "v", "type", "rig", "output", "dtype", "options", "align", "scale", "calibration",
    "smoothing", "min_cutoff", "beta", "d_cutoff", "target", "seq", "ts", "points", "shape",
    "data", "reset", "id", "session", "names", "m", "k", "limits", "weights", "vertices",
    "proc_us", "dropped", "code", "message", "fatal", "active", "channel", "since",
    "head", "rotation", "position", "moving", "filter", "acceleration", "noise", "server_ts",
]  # fmt: skip
_TYPES = [
    "hello", "frame", "calibrate", "ping", "ready", "result", "error", "pong", "calibrated",
    "channel_idle", "channel_live", "face_lost",
]  # fmt: skip


leaves = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=12)
    | st.binary(max_size=48)
)
# Cheap to generate: hypothesis spends far longer building deep trees than the decoder
# spends rejecting them, and the deep cases are covered by `msgpack_values`.
shallow_values = (
    leaves | st.lists(leaves, max_size=4) | st.dictionaries(st.text(max_size=8), leaves, max_size=4)
)

array_maps = st.fixed_dictionaries(
    {
        "dtype": st.sampled_from(["f16", "f32", "f64", "i32", ""]) | leaves,
        "shape": st.lists(st.integers(-2, 2**40), max_size=3) | leaves,
        "data": st.binary(max_size=96) | leaves,
    }
)
"""Array maps with plausible but often inconsistent dtype, shape and data."""

nested_maps = st.dictionaries(st.sampled_from(_KEYS), leaves | array_maps, max_size=5)


@st.composite
def near_messages(draw) -> dict:
    """Maps that look like messages: mostly version 1 and a real type, fields of any value."""
    obj = {
        "v": draw(st.just(1) | leaves),
        "type": draw(st.sampled_from(_TYPES) | leaves),
    }
    for key in draw(st.lists(st.sampled_from(_KEYS), max_size=6, unique=True)):
        obj[key] = draw(st.one_of(leaves, array_maps, nested_maps, shallow_values))
    return obj


# -- maps shaped like each message: valid, one field broken, or loosely alike ------------------

uints = st.integers(0, 2**64 - 1)
floats = finite | st.floats()


def valid_arrays(*trailing: int, elements=None) -> st.SearchStrategy[dict]:
    """Wire array maps a decoder takes: agreeing dtype, shape and data, finite values."""

    @st.composite
    def build(draw) -> dict:
        name = draw(st.sampled_from(["f16", "f32", "f64"]))
        dtype = {"f16": "<f2", "f32": "<f4", "f64": "<f8"}[name]
        shape = (draw(st.integers(1, 5)), *trailing) if elements is None else trailing
        finite_values = {"allow_nan": False, "allow_infinity": False}
        values = draw(
            hnp.arrays(
                np.dtype(dtype), shape, elements=finite_values if elements is None else elements
            )
        )
        return {"dtype": name, "shape": list(values.shape), "data": values.tobytes()}

    return build()


@st.composite
def near_arrays(draw) -> dict:
    """Array maps whose dtype, shape and data nearly agree: a byte off, a row off, NaN."""
    dtype = draw(st.sampled_from(["f16", "f32", "f64"]))
    columns = draw(st.sampled_from([[], [3], [4], [1]]))
    rows = draw(st.integers(0, 6))
    itemsize = {"f16": 2, "f32": 4, "f64": 8}[dtype]
    size = rows * (columns[0] if columns else 1) * itemsize + draw(st.sampled_from([0, -1, 1]))
    data = draw(st.binary(min_size=max(size, 0), max_size=max(size, 0)))
    return {"dtype": dtype, "shape": [rows, *columns], "data": data}


def _unit_quaternion(values: np.ndarray) -> dict:
    norm = float(np.linalg.norm(values))
    q = values / norm if norm > 1e-3 else np.array([0.0, 0.0, 0.0, 1.0])
    return {"dtype": "f32", "shape": [4], "data": q.astype("<f4").tobytes()}


_quaternions = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).map(_unit_quaternion)
_positions = valid_arrays(3, elements=st.floats(-0.5, 0.5, width=16))


class Field:
    """A field of a message: the values its decoder takes, and values it must refuse."""

    def __init__(self, valid: st.SearchStrategy, *, optional: bool = False,
                 broken: st.SearchStrategy | None = None) -> None:  # fmt: skip
        self.valid = valid
        self.optional = optional
        self.broken = leaves | near_arrays() if broken is None else broken | leaves


def shaped(fields: dict[str, Field]) -> st.SearchStrategy[dict]:
    """Maps laid out as ``fields`` say: all valid (half of them), one field broken or
    missing, or every field loosely alike (present or not, valid or any leaf), now and then
    with a stranger key."""

    @st.composite
    def build(draw) -> dict:
        mode = draw(st.sampled_from(["valid", "valid", "one broken", "loose"]))
        broken = draw(st.sampled_from(sorted(fields))) if mode == "one broken" else None
        obj = {}
        for key, field in fields.items():
            if key == broken:
                if draw(st.booleans()):
                    obj[key] = draw(field.broken)
            elif mode == "loose":
                if draw(st.integers(0, 5)):
                    obj[key] = draw(field.valid if draw(st.booleans()) else field.broken)
            elif not field.optional or draw(st.booleans()):
                obj[key] = draw(field.valid)
        if mode == "loose" and not draw(st.integers(0, 4)):
            obj[draw(st.sampled_from(_KEYS))] = draw(leaves | near_arrays())
        return obj

    return build()


_head = shaped({"rotation": Field(_quaternions), "position": Field(_positions, optional=True)})
_smoothing = shaped({
    "min_cutoff": Field(positive, optional=True), "beta": Field(positive, optional=True),
    "d_cutoff": Field(positive, optional=True), "acceleration": Field(positive, optional=True),
    "noise": Field(positive, optional=True),
    "target": Field(st.sampled_from(["points", "weights"]), optional=True,
                    broken=st.just("vertices")),
    "filter": Field(st.sampled_from(["one-euro", "kalman"]), optional=True,
                    broken=st.just("box")),
})  # fmt: skip
_blinks = st.dictionaries(st.sampled_from(["eyeBlinkLeft", "eyeBlinkRight"]), valid_arrays(3),
                          min_size=1, max_size=2)  # fmt: skip
_contrasts = st.tuples(st.floats(0.0, 0.5), st.floats(0.5, 1.0, exclude_min=True)).map(list)
_outputs = st.sampled_from(["weights", "vertices", "moving"])
_dtypes = st.sampled_from(["f32", "f16"])
_seq = Field(uints, broken=st.integers(-3, -1) | floats)
_ts = Field(finite, broken=st.floats())
_FIELDS: dict[str, dict[str, Field]] = {
    "hello": {
        "rig": Field(text), "output": Field(_outputs, optional=True, broken=st.just("points")),
        "dtype": Field(_dtypes, optional=True, broken=st.just("f64")),
        "options": Field(shaped({
            "align": Field(st.booleans(), optional=True),
            "scale": Field(st.booleans(), optional=True),
            "calibration": Field(st.booleans(), optional=True),
            "smoothing": Field(st.none() | _smoothing, optional=True),
        }), optional=True),
    },
    "frame": {"seq": _seq, "ts": _ts, "points": Field(valid_arrays(3)),
              "head": Field(_head, optional=True)},
    "calibrate": {"points": Field(valid_arrays(3), optional=True),
                  "reset": Field(st.booleans(), optional=True),
                  "noise": Field(positive | st.just(0.0), optional=True, broken=st.just(-1.0)),
                  "blinks": Field(_blinks, optional=True, broken=st.just({"jawOpen": None})),
                  "blink_contrast": Field(_contrasts, optional=True,
                                          broken=st.just([0.9, 0.1]) | st.lists(floats))},
    "ping": {"id": _seq, "ts": _ts},
    "pong": {"id": _seq, "ts": _ts},
    "ready": {
        "session": Field(text), "output": Field(_outputs), "dtype": Field(_dtypes),
        "smoothing": Field(text, optional=True),
        "rig": Field(shaped({
            "id": Field(text), "m": Field(st.integers(0, 3)),
            "names": Field(st.lists(text, max_size=3)),
            "k": Field(st.integers(0, 5000)), "v": Field(st.integers(0, 3_000_000)),
            "moving": Field(st.binary(max_size=12), optional=True),
        })),
        "limits": Field(st.dictionaries(text, finite | st.integers(0, 100), max_size=3),
                        optional=True),
    },
    "result": {
        "seq": _seq, "ts": _ts, "weights": Field(valid_arrays(), optional=True),
        "vertices": Field(valid_arrays(3), optional=True), "proc_us": Field(uints),
        "dropped": Field(uints), "server_ts": Field(finite, optional=True),
        "head": Field(_head, optional=True),
    },
    "error": {"code": Field(st.integers(0, 10_000)), "message": Field(st.text(max_size=300)),
              "seq": Field(uints, optional=True), "fatal": Field(st.booleans(), optional=True),
              "dropped": Field(uints, optional=True)},
    "calibrated": {"active": Field(st.booleans()), "seq": Field(uints, optional=True)},
    "channel_idle": {"channel": Field(text)},
    "channel_live": {"channel": Field(text)},
    "face_lost": {"since": Field(finite)},
}  # fmt: skip


# Each type's strategy made once: ``shaped`` defines a composite, and Hypothesis reads and
# parses a composite's source when it is defined (~8 ms), which per case was a third of
# the shaped fuzz test's time.
_SHAPED: dict[str, st.SearchStrategy[dict]] = {
    kind: shaped({"v": Field(st.just(1), broken=st.integers(0, 3)), **fields})
    for kind, fields in _FIELDS.items()
}


@st.composite
def shaped_messages(draw) -> dict:
    """Maps laid out as one message type's: every decoder's checks, field by field and in
    its nested maps, are reached in hundreds of cases, where `near_messages` takes
    thousands and reaches half as many."""
    kind = draw(st.sampled_from(sorted(_FIELDS)))
    return {"type": kind, **draw(_SHAPED[kind])}

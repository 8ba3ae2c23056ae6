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

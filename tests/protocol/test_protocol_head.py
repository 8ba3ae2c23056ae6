"""The optional head pose of frames and results (PROTOCOL.md §5.3): bytes, checks, shortcut.

Golden bytes here and in PROTOCOL.md §10.13; bad heads refused with their codes; frames
with a head leave the canonical fast decoder to the generic one, which agrees.
"""

from __future__ import annotations

import re
from importlib import resources

import msgpack
import numpy as np
import pytest
from _protocol_strategies import points, uint64
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from facecast.protocol import (
    HEAD_NORM_TOLERANCE,
    MAX_HEAD_POSITION,
    ErrorCode,
    Frame,
    Head,
    Limits,
    ProtocolError,
    Result,
    array_to_wire,
    decode_client,
    decode_server,
    encode,
)
from facecast.protocol.codec import CLIENT_MESSAGES, _decode
from facecast.protocol.fastframe import decode_frame

_POINTS = np.array([[0.0, 1.0, 2.0], [-0.5, 0.25, 1.5]], dtype=np.float32)
_TURN = np.array([0.0, -0.6, 0.0, 0.8], dtype=np.float32)
SAMPLES = {
    "frame.head": Frame(
        seq=7,
        ts=12.5,
        points=_POINTS,
        head=Head(rotation=_TURN, position=np.array([0.0, 0.0625, 0.0], dtype=np.float32)),
    ),
    "result.head": Result(
        seq=7,
        ts=12.5,
        weights=np.array([0.5, 0.25, 0.25], dtype=np.float32),
        proc_us=180,
        dropped=2,
        server_ts=1700000000.5,
        head=Head(rotation=_TURN),
    ),
}
GOLDEN = {
    "frame.head": "86a17601a474797065a56672616d65a373657107a27473cb4029000000000000"
    "a6706f696e747383a56474797065a3663332a57368617065920203a464617461c418000000000000803f000000"
    "40000000bf0000803e0000c03fa46865616482a8726f746174696f6e83a56474797065a3663332a57368617065"
    "9104a464617461c410000000009a9919bf00000000cdcc4c3fa8706f736974696f6e83a56474797065a3663332"
    "a573686170659103a464617461c40c000000000000803d00000000",
    "result.head": "89a17601a474797065a6726573756c74a373657107a27473cb4029000000000"
    "000a77765696768747383a56474797065a3663332a573686170659103a464617461c40c0000003f0000803e000"
    "0803ea770726f635f7573ccb4a764726f7070656402a97365727665725f7473cb41d954fc40200000a46865616"
    "481a8726f746174696f6e83a56474797065a3663332a573686170659104a464617461c410000000009a9919bf0"
    "0000000cdcc4c3f",
}
_EXAMPLE = re.compile(r"<!-- example: (\w+\.head) -->\s*```[a-z]*\n(.*?)```", re.DOTALL)


def _decode_any(name: str, data: bytes):
    return decode_client(data) if name.startswith("frame") else decode_server(data)


def _spec_examples() -> dict[str, bytes]:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    return {
        name: bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", block))
        for name, block in _EXAMPLE.findall(text)
    }


# -- golden bytes ---------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_message_with_a_head_encodes_to_golden_bytes(name: str) -> None:
    assert encode(SAMPLES[name]).hex() == GOLDEN[name]


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_bytes_with_a_head_decode_to_the_message(name: str) -> None:
    decoded = _decode_any(name, bytes.fromhex(GOLDEN[name]))
    assert decoded == SAMPLES[name] and decoded.head is not None


def test_spec_shows_both_head_examples_as_encoded() -> None:
    assert _spec_examples() == {name: encode(message) for name, message in SAMPLES.items()}


def test_a_frame_without_a_head_has_no_head_key() -> None:
    frame = Frame(seq=7, ts=12.5, points=_POINTS)
    assert b"head" not in encode(frame)
    assert encode(SAMPLES["frame.head"]).startswith(b"\x86") and encode(frame)[0] == 0x85


# -- round trips ----------------------------------------------------------------------


def _unit(values: np.ndarray) -> np.ndarray:
    return values / np.linalg.norm(values)


_DTYPES = st.sampled_from(["<f2", "<f4", "<f8"])
_COMPONENT = st.floats(-1.0, 1.0, allow_nan=False)
heads = st.builds(
    lambda q, dtype, position: Head(
        rotation=_unit(np.asarray(q, dtype=np.float64)).astype(dtype), position=position
    ),
    st.lists(_COMPONENT, min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    _DTYPES,
    st.none()
    | _DTYPES.flatmap(
        lambda dt: hnp.arrays(np.dtype(dt), 3, elements=st.floats(-1000, 1000, width=16))
    ),
)
frames_with_heads = st.builds(
    Frame,
    seq=uint64,
    ts=st.floats(allow_nan=False, allow_infinity=False),
    points=points(),
    head=heads,
)


@settings(max_examples=200, deadline=None)
@given(frames_with_heads)
def test_a_frame_with_a_head_round_trips_bit_for_bit(frame: Frame) -> None:
    decoded = decode_client(encode(frame))
    assert decoded == frame
    assert decoded.head.rotation.dtype == frame.head.rotation.dtype


@settings(max_examples=200, deadline=None)
@given(frames_with_heads)
def test_a_frame_with_a_head_is_left_to_the_generic_decoder(frame: Frame) -> None:
    assert decode_frame(encode(frame), Limits()) is None


def _generic(data: bytes, limits: Limits):
    try:
        return _decode(data, limits.max_message_bytes, limits, CLIENT_MESSAGES, "c->s")
    except ProtocolError as exc:
        return exc.code


@settings(
    max_examples=500,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(frames_with_heads, st.data())
def test_any_change_to_a_frame_with_a_head_is_deferred_or_decoded_alike(
    frame: Frame, data: st.DataObject
) -> None:
    raw = bytearray(encode(frame))
    at = data.draw(st.integers(0, len(raw) - 1))
    edit = data.draw(st.sampled_from(["flip", "cut"]))
    if edit == "flip":
        raw[at] = data.draw(st.integers(0, 255))
    else:
        del raw[at:]
    fast = decode_frame(bytes(raw), Limits())
    generic = _generic(bytes(raw), Limits())
    assert fast is None or fast == generic


# -- refusals -------------------------------------------------------------------------


def _frame_bytes(head) -> bytes:
    """A valid frame's wire map with ``head`` as given, as a sender might write it."""
    wire = Frame(seq=3, ts=1.0, points=_POINTS).serialize()
    wire["head"] = head
    return msgpack.packb(wire, use_bin_type=True)


def _refusal(head) -> ProtocolError:
    with pytest.raises(ProtocolError) as caught:
        decode_client(_frame_bytes(head))
    return caught.value


def _array(values, dtype="<f4") -> dict:
    return array_to_wire(np.asarray(values, dtype=dtype))


@pytest.mark.parametrize(
    ("head", "code", "words"),
    [
        ([0, 0, 0, 1], ErrorCode.INVALID_FIELD, "frame.head must be a map"),
        ({}, ErrorCode.INVALID_FIELD, "frame.head.rotation is required"),
        ({"rotation": [0, 0, 0, 1]}, ErrorCode.INVALID_ARRAY, "frame.head.rotation"),
        ({"rotation": _array([0, 0, 1])}, ErrorCode.INVALID_ARRAY, "must be [4], got [3]"),
        ({"rotation": _array([0, 0, 0, 1, 0])}, ErrorCode.INVALID_ARRAY, "must be [4]"),
        ({"rotation": _array([[0, 0, 0, 1]])}, ErrorCode.INVALID_ARRAY, "shape"),
        ({"rotation": _array([0, 0, np.nan, 1])}, ErrorCode.NON_FINITE, "frame.head.rotation"),
        ({"rotation": _array([0, 0, 0, np.inf])}, ErrorCode.NON_FINITE, "NaN or infinity"),
        ({"rotation": _array([0, 0, 0, 0])}, ErrorCode.INVALID_FIELD, "got norm 0"),
        ({"rotation": _array([0, 0, 0, 2])}, ErrorCode.INVALID_FIELD, "unit quaternion"),
        (
            {"rotation": _array([0, 0, 0, 1]), "position": _array([0, 1])},
            ErrorCode.INVALID_ARRAY,
            "frame.head.position.shape must be [3]",
        ),
        (
            {"rotation": _array([0, 0, 0, 1]), "position": _array([0, np.nan, 0])},
            ErrorCode.NON_FINITE,
            "frame.head.position",
        ),
        (
            {"rotation": _array([0, 0, 0, 1]), "position": _array([0, 0, -1000.5], "<f8")},
            ErrorCode.INVALID_FIELD,
            "within ±1000 m",
        ),
    ],
)
def test_a_bad_head_is_refused_with_its_code(head, code, words) -> None:
    error = _refusal(head)
    assert error.code == code
    assert words in error.message


def test_the_norm_tolerance_is_inclusive_at_the_edge_and_refused_past_it() -> None:
    w_at = 1.0 + HEAD_NORM_TOLERANCE * 0.999
    w_past = 1.0 + HEAD_NORM_TOLERANCE * 1.001
    assert decode_client(_frame_bytes({"rotation": _array([0, 0, 0, w_at], "<f8")})).head
    assert _refusal({"rotation": _array([0, 0, 0, w_past], "<f8")}).code == (
        ErrorCode.INVALID_FIELD
    )


def test_the_position_bound_is_inclusive() -> None:
    head = {"rotation": _array([0, 0, 0, 1]), "position": _array([MAX_HEAD_POSITION, 0, 0])}
    decoded = decode_client(_frame_bytes(head))
    assert decoded.head.position[0] == MAX_HEAD_POSITION


def test_a_unit_quaternion_rounded_to_f16_is_accepted() -> None:
    rng = np.random.default_rng(3)
    for q in rng.normal(size=(200, 4)):
        Head(rotation=_unit(q).astype(np.float16))


def test_a_nil_head_is_no_head() -> None:
    assert decode_client(_frame_bytes(None)).head is None


def test_unknown_keys_in_a_head_are_ignored() -> None:
    decoded = decode_client(_frame_bytes({"rotation": _array([0, 0, 0, 1]), "scale": 2}))
    assert np.array_equal(decoded.head.rotation, [0, 0, 0, 1]) and decoded.head.position is None


def test_constructing_a_bad_head_raises_the_same_error() -> None:
    with pytest.raises(ProtocolError) as caught:
        Head(rotation=np.array([0.0, 0.0, 0.0, 0.5]))
    assert caught.value.code == ErrorCode.INVALID_FIELD
    with pytest.raises(ProtocolError) as caught:
        Frame(seq=0, ts=0.0, points=_POINTS, head=(0, 0, 0, 1))  # type: ignore[arg-type]
    assert caught.value.code == ErrorCode.INVALID_FIELD


def test_a_result_with_a_bad_head_is_refused_by_the_client_decoder() -> None:
    wire = SAMPLES["result.head"].serialize()
    wire["head"] = {"rotation": _array([0.0, 0.0, 0.0, 3.0])}
    with pytest.raises(ProtocolError) as caught:
        decode_server(msgpack.packb(wire, use_bin_type=True))
    assert caught.value.code == ErrorCode.INVALID_FIELD
    assert "result.head.rotation" in caught.value.message

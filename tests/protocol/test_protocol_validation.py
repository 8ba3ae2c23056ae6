"""Decoders refuse every malformed message with the documented error code (PROTOCOL.md §3-6)."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest
from _protocol_samples import SAMPLES
from _protocol_wire import pack, raw

from facecast.protocol import (
    MAX_ERROR_MESSAGE,
    Calibrate,
    Error,
    ErrorCode,
    Frame,
    Hello,
    ProtocolError,
    Result,
    decode_client,
    decode_server,
    encode,
    reject_text,
)
from facecast.protocol.messages import CLIENT_MESSAGES


def _decoder(name: str):
    return decode_client if name in CLIENT_MESSAGES else decode_server


def _code_of(name: str, data: bytes) -> ErrorCode | int:
    with pytest.raises(ProtocolError) as info:
        _decoder(name)(data)
    return info.value.code


def _set(obj: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    *parents, last = path.split(".")
    target = obj
    for key in parents:
        target = target[key]
    if value is _DELETE:
        del target[last]
    else:
        target[last] = value
    return obj


_DELETE = object()


# --- framing ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "code"),
    [
        (b"", ErrorCode.MALFORMED),
        (b"\xc1", ErrorCode.MALFORMED),  # the one byte msgpack never uses
        (bytes.fromhex("d40101"), ErrorCode.MALFORMED),  # ext type
        (bytes.fromhex("81a17601") + b"\x00", ErrorCode.MALFORMED),  # trailing bytes
        (pack({1: 2}), ErrorCode.MALFORMED),  # non-string map key
        (b"\xa2\xff\xfe", ErrorCode.MALFORMED),  # invalid UTF-8
        (pack([1, "hello"]), ErrorCode.INVALID_MESSAGE),
        (pack(1), ErrorCode.INVALID_MESSAGE),
        (pack({"type": "ping", "id": 1, "ts": 0.0}), ErrorCode.INVALID_MESSAGE),
        (pack({"v": "1", "type": "ping", "id": 1, "ts": 0.0}), ErrorCode.INVALID_MESSAGE),
        (pack({"v": True, "type": "ping", "id": 1, "ts": 0.0}), ErrorCode.INVALID_MESSAGE),
        (pack({"v": 1, "id": 1, "ts": 0.0}), ErrorCode.INVALID_MESSAGE),
        (pack({"v": 1, "type": 3, "id": 1, "ts": 0.0}), ErrorCode.INVALID_MESSAGE),
        (pack({"v": 2, "type": "ping", "id": 1, "ts": 0.0}), ErrorCode.UNSUPPORTED_VERSION),
        (pack({"v": 0, "type": "ping", "id": 1, "ts": 0.0}), ErrorCode.UNSUPPORTED_VERSION),
        (pack({"v": 1, "type": "dance"}), ErrorCode.UNKNOWN_TYPE),
        (pack({"v": 1, "type": "ready"}), ErrorCode.UNKNOWN_TYPE),  # server type from client
    ],
)
def test_client_decoder_rejects_bad_framing_with_stable_code(data: bytes, code: ErrorCode) -> None:
    with pytest.raises(ProtocolError) as info:
        decode_client(data)
    assert info.value.code == code


def test_server_decoder_rejects_client_message_type() -> None:
    assert _code_of("ready", encode(SAMPLES["frame"])) == ErrorCode.UNKNOWN_TYPE


def test_repeated_map_key_is_invalid_message() -> None:
    # a map with "v" twice: 0x83 = map of 3 pairs
    data = bytes.fromhex("83a17601a17601a474797065a470696e67")
    assert _code_of("ping", data) == ErrorCode.INVALID_MESSAGE


def test_version_is_checked_before_type() -> None:
    assert _code_of("ping", pack({"v": 9, "type": "dance"})) == ErrorCode.UNSUPPORTED_VERSION


def test_text_message_is_rejected_with_text_not_supported() -> None:
    with pytest.raises(ProtocolError) as info:
        reject_text('{"type": "hello"}')
    assert info.value.code == ErrorCode.TEXT_NOT_SUPPORTED


def test_str_given_to_decoder_is_text_not_supported() -> None:
    assert _code_of("hello", "hello") == ErrorCode.TEXT_NOT_SUPPORTED  # type: ignore[arg-type]


def test_decoder_accepts_bytearray_and_memoryview() -> None:
    data = encode(SAMPLES["frame"])
    assert decode_client(bytearray(data)) == decode_client(memoryview(data)) == SAMPLES["frame"]


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_every_proper_prefix_of_a_valid_message_is_rejected(name: str) -> None:
    data = encode(SAMPLES[name])
    decoder = _decoder(name)
    codes = set()
    for end in range(len(data)):
        with pytest.raises(ProtocolError) as info:
            decoder(data[:end])
        codes.add(info.value.code)
    assert codes == {ErrorCode.MALFORMED}


# --- forward compatibility --------------------------------------------------------------


@pytest.mark.parametrize(
    "path", ["extra", "options.extra", "points.extra", "options.smoothing.extra"]
)
def test_unknown_keys_are_ignored(path: str) -> None:
    obj = raw("hello") if "points" not in path else raw("frame")
    _set(obj, path, {"anything": [1, 2, 3]})
    name = "frame" if "points" in path else "hello"
    assert decode_client(pack(obj)) == SAMPLES[name]


def test_optional_hello_fields_default_when_absent() -> None:
    message = decode_client(pack({"v": 1, "type": "hello", "rig": "demo"}))
    assert message == Hello(rig="demo", output="weights", dtype="f32")


def test_nil_means_absent_for_optional_fields() -> None:
    obj = {"v": 1, "type": "hello", "rig": "demo", "output": None, "options": None}
    assert decode_client(pack(obj)) == Hello(rig="demo")


# --- wrong field types and values -------------------------------------------------------

_BAD_FIELDS = [
    ("hello", "rig", _DELETE, ErrorCode.INVALID_FIELD),
    ("hello", "rig", 5, ErrorCode.INVALID_FIELD),
    ("hello", "rig", "", ErrorCode.INVALID_FIELD),
    ("hello", "rig", b"demo", ErrorCode.INVALID_FIELD),
    ("hello", "output", "mesh", ErrorCode.INVALID_FIELD),
    ("hello", "output", 1, ErrorCode.INVALID_FIELD),
    ("hello", "dtype", "f64", ErrorCode.INVALID_FIELD),
    ("hello", "dtype", True, ErrorCode.INVALID_FIELD),
    ("hello", "options", [], ErrorCode.INVALID_FIELD),
    ("hello", "options.align", 1, ErrorCode.INVALID_FIELD),
    ("hello", "options.scale", "yes", ErrorCode.INVALID_FIELD),
    ("hello", "options.calibration", 0, ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing", 1.0, ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing.min_cutoff", 0.0, ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing.min_cutoff", "1", ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing.min_cutoff", math.nan, ErrorCode.NON_FINITE),
    ("hello", "options.smoothing.beta", -0.1, ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing.beta", math.inf, ErrorCode.NON_FINITE),
    ("hello", "options.smoothing.d_cutoff", -1, ErrorCode.INVALID_FIELD),
    ("hello", "options.smoothing.target", "both", ErrorCode.INVALID_FIELD),
    ("frame", "seq", _DELETE, ErrorCode.INVALID_FIELD),
    ("frame", "seq", -1, ErrorCode.INVALID_FIELD),
    ("frame", "seq", 1.0, ErrorCode.INVALID_FIELD),
    ("frame", "seq", True, ErrorCode.INVALID_FIELD),
    ("frame", "seq", "7", ErrorCode.INVALID_FIELD),
    ("frame", "ts", _DELETE, ErrorCode.INVALID_FIELD),
    ("frame", "ts", "now", ErrorCode.INVALID_FIELD),
    ("frame", "ts", False, ErrorCode.INVALID_FIELD),
    ("frame", "ts", math.nan, ErrorCode.NON_FINITE),
    ("frame", "ts", -math.inf, ErrorCode.NON_FINITE),
    ("frame", "points", _DELETE, ErrorCode.INVALID_ARRAY),
    ("frame", "points", [[0.0, 1.0, 2.0]], ErrorCode.INVALID_ARRAY),
    ("frame", "points", b"\x00" * 12, ErrorCode.INVALID_ARRAY),
    ("calibrate", "reset", 1, ErrorCode.INVALID_FIELD),
    ("calibrate", "points", "next", ErrorCode.INVALID_ARRAY),
    ("ping", "id", -5, ErrorCode.INVALID_FIELD),
    ("ping", "id", "a", ErrorCode.INVALID_FIELD),
    ("ping", "ts", _DELETE, ErrorCode.INVALID_FIELD),
    ("ready", "session", 1, ErrorCode.INVALID_FIELD),
    ("ready", "rig", "demo", ErrorCode.INVALID_FIELD),
    ("ready", "rig.id", _DELETE, ErrorCode.INVALID_FIELD),
    ("ready", "rig.names", "neutral", ErrorCode.INVALID_FIELD),
    ("ready", "rig.names", ["neutral", 2, "x"], ErrorCode.INVALID_FIELD),
    ("ready", "rig.m", 2, ErrorCode.INVALID_FIELD),
    ("ready", "rig.k", -1, ErrorCode.INVALID_FIELD),
    ("ready", "rig.v", 1.5, ErrorCode.INVALID_FIELD),
    ("ready", "output", "both", ErrorCode.INVALID_FIELD),
    ("ready", "dtype", "f64", ErrorCode.INVALID_FIELD),
    ("ready", "limits", [], ErrorCode.INVALID_FIELD),
    ("ready", "limits.max_fps", "fast", ErrorCode.INVALID_FIELD),
    ("ready", "limits.max_fps", math.nan, ErrorCode.NON_FINITE),
    ("result", "seq", None, ErrorCode.INVALID_FIELD),
    ("result", "weights", _DELETE, ErrorCode.INVALID_FIELD),
    (
        "result",
        "vertices",
        {"dtype": "f32", "shape": [1, 3], "data": bytes(12)},
        ErrorCode.INVALID_FIELD,
    ),
    ("result", "proc_us", -1, ErrorCode.INVALID_FIELD),
    ("result", "dropped", "2", ErrorCode.INVALID_FIELD),
    ("error", "code", "1001", ErrorCode.INVALID_FIELD),
    ("error", "message", None, ErrorCode.INVALID_FIELD),
    ("error", "seq", -1, ErrorCode.INVALID_FIELD),
    ("error", "fatal", "no", ErrorCode.INVALID_FIELD),
    ("pong", "id", 1.5, ErrorCode.INVALID_FIELD),
    ("calibrated", "active", _DELETE, ErrorCode.INVALID_FIELD),
    ("calibrated", "seq", "9", ErrorCode.INVALID_FIELD),
    ("channel_idle", "channel", "", ErrorCode.INVALID_FIELD),
    ("channel_live", "channel", 7, ErrorCode.INVALID_FIELD),
    ("face_lost", "since", math.inf, ErrorCode.NON_FINITE),
    ("face_lost", "since", None, ErrorCode.INVALID_FIELD),
]


@pytest.mark.parametrize(
    ("name", "path", "value", "code"),
    _BAD_FIELDS,
    ids=[f"{n}.{p}={v if v is not _DELETE else 'missing'!r}" for n, p, v, _ in _BAD_FIELDS],
)
def test_wrong_field_is_rejected_with_its_code(
    name: str, path: str, value: Any, code: ErrorCode
) -> None:
    data = pack(_set(raw(name), path, value))
    assert _code_of(name, data) == code


def test_scale_without_align_is_invalid() -> None:
    obj = _set(_set(raw("hello"), "options.align", False), "options.scale", True)
    assert _code_of("hello", pack(obj)) == ErrorCode.INVALID_FIELD


def test_calibrate_with_points_and_reset_is_invalid() -> None:
    obj = _set(raw("frame"), "type", "calibrate")
    obj["reset"] = True
    assert _code_of("calibrate", pack(obj)) == ErrorCode.INVALID_FIELD


def test_unknown_error_code_from_a_newer_server_is_kept_as_int() -> None:
    obj = _set(raw("error"), "code", 4242)
    message = decode_server(pack(obj))
    assert isinstance(message, Error)
    assert message.code == 4242


def test_code_name_is_the_name_or_the_number_of_an_unnamed_code() -> None:
    # Metrics labels, close reasons and loadgen's counts all read it.
    assert ProtocolError(ErrorCode.RATE_LIMITED, "slow").code_name == "RATE_LIMITED"
    assert ProtocolError(4242, "newer server").code_name == "4242"


def test_frame_error_carries_the_frame_seq() -> None:
    obj = _set(raw("frame"), "points.dtype", "i32")
    with pytest.raises(ProtocolError) as info:
        decode_client(pack(obj))
    assert info.value.seq == 7


# --- arrays -----------------------------------------------------------------------------

_BAD_ARRAYS = [
    ("dtype", "f128", ErrorCode.INVALID_ARRAY),
    ("dtype", "i32", ErrorCode.INVALID_ARRAY),
    ("dtype", 4, ErrorCode.INVALID_ARRAY),
    ("dtype", _DELETE, ErrorCode.INVALID_ARRAY),
    ("shape", [6], ErrorCode.INVALID_ARRAY),
    ("shape", [3, 2], ErrorCode.INVALID_ARRAY),
    ("shape", [2, 3, 1], ErrorCode.INVALID_ARRAY),
    ("shape", [-2, 3], ErrorCode.INVALID_ARRAY),
    ("shape", [2.0, 3], ErrorCode.INVALID_ARRAY),
    ("shape", [True, 3], ErrorCode.INVALID_ARRAY),
    ("shape", "2x3", ErrorCode.INVALID_ARRAY),
    ("shape", [0, 3], ErrorCode.INVALID_ARRAY),
    ("shape", [1, 3], ErrorCode.INVALID_ARRAY),  # data holds 2 points
    ("data", "0123", ErrorCode.INVALID_ARRAY),
    ("data", bytes(23), ErrorCode.INVALID_ARRAY),
    ("data", bytes(25), ErrorCode.INVALID_ARRAY),
    ("data", _DELETE, ErrorCode.INVALID_ARRAY),
]


@pytest.mark.parametrize(("key", "value", "code"), _BAD_ARRAYS)
def test_bad_array_part_is_rejected(key: str, value: Any, code: ErrorCode) -> None:
    data = pack(_set(raw("frame"), f"points.{key}", value))
    assert _code_of("frame", data) == code


def test_huge_dimension_with_empty_data_is_rejected_without_allocating() -> None:
    data = pack(_set(raw("frame"), "points.shape", [2**62, 3]))
    assert _code_of("frame", data) == ErrorCode.MESSAGE_TOO_LARGE


@pytest.mark.parametrize("wire", ["f16", "f32", "f64"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_point_is_rejected(wire: str, bad: float) -> None:
    dtype = {"f16": "<f2", "f32": "<f4", "f64": "<f8"}[wire]
    points = np.array([[0.0, 1.0, 2.0], [3.0, bad, 5.0]], dtype=dtype)
    obj = _set(raw("frame"), "points", {"dtype": wire, "shape": [2, 3], "data": points.tobytes()})
    assert _code_of("frame", pack(obj)) == ErrorCode.NON_FINITE


def test_non_finite_result_weight_is_rejected() -> None:
    weights = np.array([1.0, math.nan, 0.0], dtype="<f4")
    obj = _set(raw("result"), "weights.data", weights.tobytes())
    assert _code_of("result", pack(obj)) == ErrorCode.NON_FINITE


@pytest.mark.parametrize(("wire", "dtype"), [("f16", "<f2"), ("f32", "<f4"), ("f64", "<f8")])
def test_points_decode_in_their_wire_dtype(wire: str, dtype: str) -> None:
    points = np.array([[0.5, 1.0, 2.0], [3.0, -4.0, 5.0]], dtype=dtype)
    obj = _set(raw("frame"), "points", {"dtype": wire, "shape": [2, 3], "data": points.tobytes()})
    frame = decode_client(pack(obj))
    assert frame.points.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(frame.points, points)


def test_decoded_points_are_read_only() -> None:
    frame = decode_client(encode(SAMPLES["frame"]))
    assert not frame.points.flags.writeable


def test_big_endian_and_strided_arrays_are_sent_little_endian() -> None:
    points = np.arange(12, dtype=">f8").reshape(2, 6)[:, ::2]
    frame = decode_client(encode(Frame(seq=1, ts=0.0, points=points)))
    assert frame.points.dtype == np.dtype("<f8")
    np.testing.assert_array_equal(frame.points, points)


# --- constructing invalid messages in Python --------------------------------------------


@pytest.mark.parametrize(
    "build",
    [
        lambda: Hello(rig=""),
        lambda: Hello(rig="demo", output="mesh"),
        lambda: Frame(seq=-1, ts=0.0, points=np.zeros((1, 3))),
        lambda: Frame(seq=0, ts=math.nan, points=np.zeros((1, 3))),
        lambda: Frame(seq=0, ts=0.0, points=np.zeros((1, 2))),
        lambda: Frame(seq=0, ts=0.0, points=np.zeros((1, 3), dtype=np.int32)),
        lambda: Calibrate(points=np.zeros((1, 3)), reset=True),
        lambda: Result(seq=0, ts=0.0, proc_us=0, dropped=0),
        lambda: Result(seq=0, ts=0.0, weights=np.zeros(2), vertices=np.zeros((2, 3))),
        lambda: Result(seq=0, ts=0.0, weights=np.zeros((2, 3))),
    ],
)
def test_constructing_an_invalid_message_raises_protocol_error(build) -> None:
    with pytest.raises(ProtocolError):
        build()


def test_long_error_message_is_cut_so_it_always_decodes() -> None:
    message = Error(code=ErrorCode.INTERNAL, message="x" * 10_000)
    decoded = decode_server(encode(message))
    assert len(decoded.message) == MAX_ERROR_MESSAGE


def test_protocol_error_round_trips_through_error_message() -> None:
    error = ProtocolError(ErrorCode.NON_FINITE, "bad", seq=3, fatal=True)
    decoded = decode_server(encode(Error.of(error)))
    back = decoded.to_exception()
    assert (back.code, back.message, back.seq, back.fatal) == (ErrorCode.NON_FINITE, "bad", 3, True)


def test_protocol_error_is_a_value_error() -> None:
    assert issubclass(ProtocolError, ValueError)


def test_raw_msgpack_of_sample_matches_encode() -> None:
    # The test helpers must build the same maps the encoder does.
    assert msgpack.packb(raw("frame"), use_bin_type=True) == encode(SAMPLES["frame"])

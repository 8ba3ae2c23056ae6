"""Every decoder limit accepts a message exactly at the limit and refuses one past it (§7)."""

from __future__ import annotations

import numpy as np
import pytest
from _protocol_wire import pack, raw

from facecast.protocol import (
    ErrorCode,
    Frame,
    Hello,
    Limits,
    ProtocolError,
    Ready,
    Result,
    decode_client,
    decode_server,
    encode,
)


def _too_large(decode, data: bytes, limits: Limits) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(data, limits)
    assert info.value.code == ErrorCode.MESSAGE_TOO_LARGE


def _padded(obj: dict, size: int) -> bytes:
    """``obj`` packed with an ignored "pad" bin key so the whole message is ``size`` bytes."""
    obj = dict(obj, pad=b"")
    overhead = len(pack(obj))
    for header_growth in range(0, 8):
        obj["pad"] = bytes(max(0, size - overhead - header_growth))
        data = pack(obj)
        if len(data) == size:
            return data
    raise AssertionError(f"cannot pad to {size} bytes")


@pytest.mark.parametrize("limit", [200, 1 << 20])
def test_client_message_at_byte_limit_is_accepted_one_past_is_refused(limit: int) -> None:
    limits = Limits(max_message_bytes=limit)
    hello = raw("hello")
    assert decode_client(_padded(hello, limit), limits) == decode_client(pack(hello))
    _too_large(decode_client, _padded(hello, limit + 1), limits)


def test_default_client_byte_limit_is_one_mebibyte() -> None:
    assert Limits().max_message_bytes == 1 << 20


def test_server_message_at_byte_limit_is_accepted_one_past_is_refused() -> None:
    limits = Limits(max_server_message_bytes=300)
    result = raw("result")
    assert isinstance(decode_server(_padded(result, 300), limits), Result)
    _too_large(decode_server, _padded(result, 301), limits)


@pytest.mark.parametrize("limits", [Limits(max_points=5), Limits()], ids=["5", "default"])
def test_point_count_limit(limits: Limits) -> None:
    k = limits.max_points
    at = encode(Frame(seq=0, ts=0.0, points=np.zeros((k, 3), np.float32)))
    past = encode(Frame(seq=0, ts=0.0, points=np.zeros((k + 1, 3), np.float32)))
    assert decode_client(at, limits).points.shape == (k, 3)
    _too_large(decode_client, past, limits)


@pytest.mark.parametrize("limits", [Limits(max_vertices=5), Limits()], ids=["5", "default"])
def test_vertex_count_limit(limits: Limits) -> None:
    v = limits.max_vertices
    at = encode(Result(seq=0, ts=0.0, vertices=np.zeros((v, 3), np.float16)))
    past = encode(Result(seq=0, ts=0.0, vertices=np.zeros((v + 1, 3), np.float16)))
    assert decode_server(at, limits).vertices.shape == (v, 3)
    _too_large(decode_server, past, limits)


def test_largest_float64_vertex_result_fits_the_default_server_byte_limit() -> None:
    limits = Limits()
    header = len(encode(Result(seq=2**64 - 1, ts=0.0, vertices=np.zeros((1, 3)))))
    assert header + limits.max_vertices * 3 * 8 <= limits.max_server_message_bytes


@pytest.mark.parametrize("char", ["a", "€", "😀"], ids=["1-byte", "3-byte", "4-byte"])
def test_string_length_limit_counts_characters(char: str) -> None:
    limits = Limits(max_string=256)
    assert decode_client(encode(Hello(rig=char * 256)), limits).rig == char * 256
    _too_large(decode_client, encode(Hello(rig=char * 257)), limits)


def test_error_message_length_limit_on_the_client() -> None:
    limits = Limits(max_string=10)
    obj = raw("error")
    obj["message"] = "x" * 10
    assert decode_server(pack(obj), limits).message == "x" * 10
    obj["message"] = "x" * 11
    _too_large(decode_server, pack(obj), limits)


def _ready(m: int) -> Ready:
    return Ready(
        session="s",
        rig="r",
        names=tuple(f"n{i}" for i in range(m)),
        num_points=1,
        num_vertices=1,
        output="weights",
        dtype="f32",
    )


@pytest.mark.parametrize("limits", [Limits(max_names=4), Limits()], ids=["4", "default"])
def test_name_count_limit(limits: Limits) -> None:
    m = limits.max_names
    assert decode_server(encode(_ready(m)), limits).num_examples == m
    _too_large(decode_server, encode(_ready(m + 1)), limits)


def test_weight_count_limit_is_max_names() -> None:
    limits = Limits(max_names=4)
    at = encode(Result(seq=0, ts=0.0, weights=np.zeros(4, np.float32)))
    past = encode(Result(seq=0, ts=0.0, weights=np.zeros(5, np.float32)))
    assert decode_server(at, limits).weights.shape == (4,)
    _too_large(decode_server, past, limits)


def test_ready_k_and_v_limits() -> None:
    limits = Limits(max_points=3, max_vertices=3)
    obj = raw("ready")
    obj["rig"]["k"], obj["rig"]["v"] = 3, 3
    assert decode_server(pack(obj), limits).num_points == 3
    obj["rig"]["k"] = 4
    _too_large(decode_server, pack(obj), limits)
    obj["rig"]["k"], obj["rig"]["v"] = 3, 4
    _too_large(decode_server, pack(obj), limits)


def test_map_key_count_limit() -> None:
    limits = Limits(max_keys=8)
    obj = raw("hello")  # 6 keys
    obj.update(x1=0, x2=0)
    assert decode_client(pack(obj), limits).rig == "demo"
    obj["x3"] = 0
    _too_large(decode_client, pack(obj), limits)


@pytest.mark.parametrize(
    "field", ["max_message_bytes", "max_points", "max_string", "max_names", "max_keys"]
)
@pytest.mark.parametrize("value", [0, -1, True, 1.5])
def test_limits_must_be_positive_ints(field: str, value: object) -> None:
    with pytest.raises(ValueError):
        Limits(**{field: value})

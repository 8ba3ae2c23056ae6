"""The ``moving`` output (PROTOCOL.md §5.2.1): indices once in ``ready``, N vertices per result."""

from __future__ import annotations

import re
from importlib import resources

import msgpack
import numpy as np
import pytest

from facecast.protocol import (
    ClientProtocol,
    ErrorCode,
    Hello,
    Limits,
    ProtocolError,
    Ready,
    Result,
    decode_server,
    encode,
    watch_hello,
)

READY = Ready(
    session="s1",
    rig="demo",
    names=("neutral", "smile"),
    num_points=2,
    num_vertices=4,
    output="moving",
    dtype="f16",
    limits={},
    moving=np.array([1, 3]),
)
RESULT = Result(
    seq=7,
    ts=12.5,
    vertices=np.array([[0.0, 1.0, 2.0], [-0.5, 0.25, 1.5]], dtype=np.float16),
    proc_us=180,
    dropped=0,
)
GOLDEN = {
    "ready_moving": "87a17601a474797065a57265616479a773657373696f6ea27331a372696786a26964a464656d"
    "6fa16d02a56e616d657392a76e65757472616ca5736d696c65a16b02a17604a66d6f76696e67c4080100000003"
    "000000a66f7574707574a66d6f76696e67a56474797065a3663136a66c696d69747380",
    "result_moving": "87a17601a474797065a6726573756c74a373657107a27473cb4029000000000000a87665"
    "72746963657383a56474797065a3663136a57368617065920203a464617461c40c0000003c004000b800340"
    "03ea770726f635f7573ccb4a764726f7070656400",
}
SAMPLES = {"ready_moving": READY, "result_moving": RESULT}
_EXAMPLE = re.compile(r"<!-- example: (\w+) -->\s*```[a-z]*\n(.*?)```", re.DOTALL)


def _spec_example(name: str) -> bytes:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    blocks = dict(_EXAMPLE.findall(text))
    return bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", blocks[name]))


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_moving_messages_encode_to_golden_bytes(name):
    assert encode(SAMPLES[name]).hex() == GOLDEN[name]


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_spec_hex_example_equals_encoded_bytes(name):
    assert _spec_example(name) == encode(SAMPLES[name])


def test_ready_moving_round_trips_with_its_indices():
    decoded = decode_server(encode(READY))
    assert decoded == READY
    assert decoded.moving.dtype == np.dtype("<u4")
    np.testing.assert_array_equal(decoded.moving, [1, 3])
    assert decoded.result_vertices == 2


def test_hello_accepts_the_moving_output():
    assert Hello(rig="demo", output="moving").output == "moving"


def test_channel_watchers_cannot_ask_for_the_moving_output():
    with pytest.raises(ProtocolError) as caught:
        watch_hello({"rig": "demo", "output": "moving"})
    assert caught.value.code is ErrorCode.INVALID_FIELD


def _ready_bytes(**rig_changes) -> bytes:
    obj = READY.serialize()
    obj["rig"].update(rig_changes)
    obj["rig"] = {k: v for k, v in obj["rig"].items() if v is not None}
    return msgpack.packb(obj)


@pytest.mark.parametrize(
    ("moving", "why"),
    [
        (np.array([3, 1], "<u4").tobytes(), "increasing"),
        (np.array([1, 1], "<u4").tobytes(), "increasing"),
        (np.array([1, 4], "<u4").tobytes(), "below 4"),
        (b"\x01\x00\x00", "whole number"),
        (b"", "empty"),
        ("1,3", "bin"),
        (None, "exactly when"),
    ],
)
def test_ready_refuses_bad_moving_indices(moving, why):
    with pytest.raises(ProtocolError, match=why) as caught:
        decode_server(_ready_bytes(moving=moving))
    assert caught.value.code is ErrorCode.INVALID_FIELD


def test_ready_refuses_moving_indices_for_another_output():
    obj = READY.serialize()
    obj["output"] = "vertices"
    with pytest.raises(ProtocolError, match="exactly when") as caught:
        decode_server(msgpack.packb(obj))
    assert caught.value.code is ErrorCode.INVALID_FIELD


def test_ready_moving_limit_is_inclusive():
    limits = Limits(max_vertices=4)
    at_limit = np.arange(4, dtype="<u4").tobytes()
    assert decode_server(_ready_bytes(moving=at_limit), limits).result_vertices == 4
    over = np.arange(5, dtype="<u4").tobytes()
    with pytest.raises(ProtocolError) as caught:
        decode_server(_ready_bytes(moving=over, v=5), limits)
    assert caught.value.code is ErrorCode.MESSAGE_TOO_LARGE


def _streaming_client() -> ClientProtocol:
    client = ClientProtocol()
    client.send(Hello(rig="demo", output="moving", dtype="f16"))
    client.receive(encode(READY))
    return client


def test_client_accepts_a_result_of_the_moving_vertices():
    result = _streaming_client().receive(encode(RESULT))
    assert result.vertices.shape == (2, 3)


def test_client_refuses_a_result_of_every_vertex_in_a_moving_session():
    full = Result(seq=8, ts=1.0, vertices=np.zeros((4, 3), np.float16))
    with pytest.raises(ProtocolError) as caught:
        _streaming_client().receive(encode(full))
    assert caught.value.code is ErrorCode.INVALID_FIELD

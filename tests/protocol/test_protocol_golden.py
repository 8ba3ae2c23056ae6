"""Golden bytes: every message type encodes to fixed bytes, and PROTOCOL.md shows them."""

from __future__ import annotations

import re
from importlib import resources

import msgpack
import numpy as np
import pytest
from _protocol_samples import SAMPLES

from facecast.protocol import ErrorCode, ProtocolError, decode_client, decode_server, encode
from facecast.protocol.messages import CLIENT_MESSAGES, SERVER_MESSAGES, Calibrate

GOLDEN = {
    "hello": "86a17601a474797065a568656c6c6fa3726967a464656d6fa66f7574707574a777656967687473a564"
    "74797065a3663332a76f7074696f6e7384a5616c69676ec3a57363616c65c2ab63616c6962726174696f6ec2a9"
    "736d6f6f7468696e6784aa6d696e5f6375746f6666cb3ff0000000000000a462657461cb3fe0000000000000a8"
    "645f6375746f6666cb3ff0000000000000a6746172676574a6706f696e7473",
    "frame": "85a17601a474797065a56672616d65a373657107a27473cb4029000000000000a6706f696e747383a5"
    "6474797065a3663332a57368617065920203a464617461c418000000000000803f00000040000000bf0000803e"
    "0000c03f",
    "calibrate": "84a17601a474797065a963616c696272617465a6706f696e7473c0a57265736574c2",
    "ping": "84a17601a474797065a470696e67a2696401a27473cb400a000000000000",
    "ready": "87a17601a474797065a57265616479a773657373696f6ea27331a372696785a26964a464656d6fa16d"
    "03a56e616d657393a76e65757472616ca5736d696c65a86a61775f6f70656ea16b02a17604a66f7574707574a777"
    "656967687473a56474797065a3663332a66c696d69747387aa6d61785f706f696e7473cd1000a76d61785f667073"
    "cb406e000000000000aa726174655f62757273743cae63616c6962726174655f72617465cb3ff0000000000000af"
    "63616c6962726174655f627572737404b16d61785f6d6573736167655f6279746573ce00100000ac69646c655f74"
    "696d656f7574cb404e000000000000",
    "result": "87a17601a474797065a6726573756c74a373657107a27473cb4029000000000000a7776569676874"
    "7383a56474797065a3663332a573686170659103a464617461c40c0000003f0000803e0000803ea770726f635f"
    "7573ccb4a764726f7070656402",
    "error": "86a17601a474797065a56572726f72a4636f6465cd07d2a76d657373616765af6e656564204b3d3220"
    "706f696e7473a373657108a5666174616cc2",
    "pong": "84a17601a474797065a4706f6e67a2696401a27473cb400a000000000000",
    "calibrated": "84a17601a474797065aa63616c69627261746564a6616374697665c3a373657109",
    "channel_idle": "83a17601a474797065ac6368616e6e656c5f69646c65a76368616e6e656ca57374616765",
    "channel_live": "83a17601a474797065ac6368616e6e656c5f6c697665a76368616e6e656ca57374616765",
    "face_lost": "83a17601a474797065a9666163655f6c6f7374a573696e6365cb4029000000000000",
}

#: Further examples in PROTOCOL.md, of message variants (test_protocol_moving checks them).
VARIANTS = (
    "ready_moving",
    "result_moving",
    "calibrate_noise",
    "calibrate_blinks",
    "calibrate_contrast",
)

# Examples in PROTOCOL.md look like: <!-- example: frame --> then a fenced block of hex.
_EXAMPLE = re.compile(r"<!-- example: (\w+) -->\s*```[a-z]*\n(.*?)```", re.DOTALL)


def _decode(name: str, data: bytes):
    return decode_client(data) if name in CLIENT_MESSAGES else decode_server(data)


def _spec_examples() -> dict[str, bytes]:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    return {
        name: bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", block))
        for name, block in _EXAMPLE.findall(text)
    }


def test_every_message_type_has_a_golden_sample() -> None:
    assert set(GOLDEN) == set(CLIENT_MESSAGES) | set(SERVER_MESSAGES)


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_message_encodes_to_golden_bytes(name: str) -> None:
    assert encode(SAMPLES[name]).hex() == GOLDEN[name]


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_bytes_decode_to_the_message(name: str) -> None:
    assert _decode(name, bytes.fromhex(GOLDEN[name])) == SAMPLES[name]


def test_spec_shows_an_example_of_every_message_type() -> None:
    assert set(_spec_examples()) == set(GOLDEN) | set(VARIANTS)


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_spec_hex_example_equals_encoded_bytes(name: str) -> None:
    assert _spec_examples().get(name) == encode(SAMPLES[name])


def test_calibrate_with_noise_is_the_spec_example_and_round_trips() -> None:
    message = Calibrate(noise=0.015625)
    data = encode(message)

    assert _spec_examples()["calibrate_noise"] == data
    assert decode_client(data) == message


def test_calibrate_with_blinks_is_the_spec_example_and_round_trips() -> None:
    message = Calibrate(
        points=np.zeros((1, 3), np.float32),
        noise=0.015625,
        blinks={"eyeBlinkLeft": np.array([[0.0, -0.25, 0.0]], np.float32)},
    )
    data = encode(message)

    assert _spec_examples()["calibrate_blinks"] == data
    assert decode_client(data) == message
    assert b"blinks" not in encode(Calibrate(noise=0.015625))  # absent unless given


def test_calibrate_with_a_blink_contrast_is_the_spec_example_and_round_trips() -> None:
    message = Calibrate(
        points=np.zeros((1, 3), np.float32),
        noise=0.015625,
        blinks={"eyeBlinkLeft": np.array([[0.0, -0.25, 0.0]], np.float32)},
        blink_contrast=(0.5, 0.875),
    )
    data = encode(message)

    assert _spec_examples()["calibrate_contrast"] == data
    assert decode_client(data) == message
    assert decode_client(data).blink_contrast == (0.5, 0.875)
    assert b"blink_contrast" not in encode(Calibrate(noise=0.015625))  # absent unless given


def _calibrate_body(**fields):
    point = {"dtype": "f32", "shape": [1, 3], "data": bytes(12)}
    return {"v": 1, "type": "calibrate", "points": point, "reset": False, "noise": 0.01,
            "blinks": {"eyeBlinkLeft": point}, **fields}  # fmt: skip


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"noise": None}, "needs calibrate.points and .noise"),
        ({"points": None}, "needs calibrate.points and .noise"),
        ({"blinks": {}}, "non-empty map"),
        ({"blinks": {"jawOpen": {"dtype": "f32", "shape": [1, 3], "data": bytes(12)}}}, "not one of"),
        ({"blinks": [1]}, "map of at most 2"),
        ({"blinks": {"eyeBlinkLeft": {"dtype": "f32", "shape": [2, 3], "data": bytes(24)}}},
         "has 2 points"),
    ],
)  # fmt: skip
def test_a_bad_calibrate_blinks_is_refused_with_invalid_field(fields, message) -> None:
    with pytest.raises(ProtocolError) as raised:
        decode_client(msgpack.packb(_calibrate_body(**fields)))

    assert raised.value.code == ErrorCode.INVALID_FIELD
    assert message in str(raised.value)


@pytest.mark.parametrize(
    ("fields", "code", "message"),
    [
        ({"blinks": None, "blink_contrast": [0.5, 0.9]}, ErrorCode.INVALID_FIELD, "needs calibrate.blinks"),
        ({"blink_contrast": [0.5]}, ErrorCode.INVALID_FIELD, "must be [low, high]"),
        ({"blink_contrast": 0.5}, ErrorCode.INVALID_FIELD, "must be [low, high]"),
        ({"blink_contrast": [0.9, 0.5]}, ErrorCode.INVALID_FIELD, "0 <= low < high <= 1"),
        ({"blink_contrast": [0.5, 0.5]}, ErrorCode.INVALID_FIELD, "0 <= low < high <= 1"),
        ({"blink_contrast": [-0.1, 0.5]}, ErrorCode.INVALID_FIELD, "0 <= low < high <= 1"),
        ({"blink_contrast": [0.5, 1.5]}, ErrorCode.INVALID_FIELD, "0 <= low < high <= 1"),
        ({"blink_contrast": [0.5, "0.9"]}, ErrorCode.INVALID_FIELD, "blink_contrast[1]"),
        ({"blink_contrast": [float("nan"), 0.9]}, ErrorCode.NON_FINITE, "blink_contrast[0]"),
    ],
)  # fmt: skip
def test_a_bad_calibrate_blink_contrast_is_refused(fields, code, message) -> None:
    with pytest.raises(ProtocolError) as raised:
        decode_client(msgpack.packb(_calibrate_body(**fields)))

    assert raised.value.code == code
    assert message in str(raised.value)


def test_calibrate_without_noise_keeps_its_bytes_and_reads_none() -> None:
    # An older client's calibrate: no "noise" key on the wire, noise None after decoding.
    assert decode_client(bytes.fromhex(GOLDEN["calibrate"])).noise is None
    assert b"noise" not in encode(Calibrate())


@pytest.mark.parametrize(
    ("fields", "code"),
    [
        ({"noise": -0.01}, ErrorCode.INVALID_FIELD),
        ({"noise": float("nan")}, ErrorCode.NON_FINITE),
        ({"noise": "0.1"}, ErrorCode.INVALID_FIELD),
        ({"noise": 0.01, "reset": True}, ErrorCode.INVALID_FIELD),
    ],
)
def test_a_bad_calibrate_noise_is_refused_with_its_code(fields, code) -> None:
    body = {"v": 1, "type": "calibrate", "points": None, "reset": False, **fields}

    with pytest.raises(ProtocolError) as raised:
        decode_client(msgpack.packb(body))

    assert raised.value.code == code

"""``hello.smoothing`` (PROTOCOL.md §5.1.1): the one-euro filter's keys and the Kalman filter's."""

from __future__ import annotations

import re
from importlib import resources

import pytest

from facecast.protocol import ErrorCode, Hello, ProtocolError, Smoothing, decode_client, encode

KALMAN = Smoothing(
    min_cutoff=2.0, beta=2.0, d_cutoff=1.0, target="points",
    filter="kalman", acceleration=480.0, noise=0.05,
)  # fmt: skip
HELLO = Hello(rig="demo", output="weights", dtype="f32", smoothing=KALMAN)
GOLDEN = (
    "86a17601a474797065a568656c6c6fa3726967a464656d6fa66f7574707574a777656967687473a56474797065"
    "a3663332a76f7074696f6e7384a5616c69676ec2a57363616c65c2ab63616c6962726174696f6ec2a9736d6f6f"
    "7468696e6787aa6d696e5f6375746f6666cb4000000000000000a462657461cb4000000000000000a8645f6375"
    "746f6666cb3ff0000000000000a6746172676574a6706f696e7473a666696c746572a66b616c6d616eac616363"
    "656c65726174696f6ecb407e000000000000a56e6f697365cb3fa999999999999a"
)
_EXAMPLE = re.compile(r"<!-- example: (\w+\.kalman) -->\s*```[a-z]*\n(.*?)```", re.DOTALL)


def _spec_example() -> bytes:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    block = dict(_EXAMPLE.findall(text))["hello.kalman"]
    return bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", block))


def test_kalman_hello_encodes_to_golden_bytes():
    assert encode(HELLO).hex() == GOLDEN


def test_spec_hex_example_of_the_kalman_hello_equals_encoded_bytes():
    assert _spec_example() == encode(HELLO)


def test_kalman_hello_round_trips():
    assert decode_client(encode(HELLO)) == HELLO


def test_one_euro_smoothing_keeps_its_four_keys():
    assert list(Smoothing().serialize()) == ["min_cutoff", "beta", "d_cutoff", "target"]


def test_kalman_without_noise_leaves_it_to_the_rig():
    smoothing = Smoothing.parse({"filter": "kalman"})
    assert (smoothing.filter, smoothing.noise, smoothing.acceleration) == ("kalman", None, 480.0)
    assert "noise" not in smoothing.serialize()


@pytest.mark.parametrize(
    "fields,match",
    [
        ({"filter": "median"}, "filter"),
        ({"filter": "kalman", "target": "weights"}, "target"),
        ({"filter": "kalman", "noise": 0.0}, "noise"),
        ({"filter": "kalman", "noise": -1.0}, "noise"),
        ({"filter": "kalman", "acceleration": 0.0}, "acceleration"),
        ({"filter": 3}, "filter"),
    ],
)
def test_bad_kalman_settings_are_invalid_fields(fields, match):
    with pytest.raises(ProtocolError, match=match) as caught:
        Smoothing.parse(fields)
    assert caught.value.code == ErrorCode.INVALID_FIELD

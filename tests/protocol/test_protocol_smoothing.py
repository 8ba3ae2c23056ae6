"""``hello.smoothing`` (PROTOCOL.md §5.1.1): auto or a named filter, ``ready.smoothing`` and
``calibrated.smoothing``."""

from __future__ import annotations

import dataclasses
import re
from importlib import resources

import msgpack
import pytest
from _protocol_samples import SAMPLES

from facecast.protocol import (
    Calibrated,
    ErrorCode,
    Hello,
    ProtocolError,
    Smoothing,
    decode_client,
    decode_server,
    encode,
)
from facecast.protocol.messages import KALMAN_ACCELERATION
from facecast.rig import filters

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
_EXAMPLE = re.compile(
    r"<!-- example: (\w+\.(?:kalman|smoothing)) -->\s*```[a-z]*\n(.*?)```", re.DOTALL
)


#: §10.1's hello: a four-key smoothing, as sent before "filter" existed.
_SPEC_HELLO = (
    "86a17601a474797065a568656c6c6fa3726967a464656d6fa66f7574707574a777656967687473a56474797065"
    "a3663332a76f7074696f6e7384a5616c69676ec3a57363616c65c2ab63616c6962726174696f6ec2a9736d6f6f"
    "7468696e6784aa6d696e5f6375746f6666cb3ff0000000000000a462657461cb3fe0000000000000a8645f6375"
    "746f6666cb3ff0000000000000a6746172676574a6706f696e7473"
)
#: §10.6's ready of a session whose smoothing runs the Kalman filter (§10.15).
READY = dataclasses.replace(SAMPLES["ready"], smoothing="kalman")


def _spec_example(name: str = "hello.kalman") -> bytes:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    block = dict(_EXAMPLE.findall(text))[name]
    return bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", block))


def test_kalman_hello_encodes_to_golden_bytes():
    assert encode(HELLO).hex() == GOLDEN


def test_spec_hex_example_of_the_kalman_hello_equals_encoded_bytes():
    assert _spec_example() == encode(HELLO)


def test_kalman_hello_round_trips():
    assert decode_client(encode(HELLO)) == HELLO


def test_default_smoothing_is_auto_and_keeps_its_four_keys():
    smoothing = Smoothing()
    assert smoothing.filter is None
    assert list(smoothing.serialize()) == ["min_cutoff", "beta", "d_cutoff", "target"]


def test_an_old_four_key_smoothing_decodes_as_auto():
    hello = decode_client(bytes.fromhex(_SPEC_HELLO))  # §10.1, as every client has sent it
    assert hello.smoothing is not None and hello.smoothing.filter is None
    assert (hello.smoothing.min_cutoff, hello.smoothing.beta) == (1.0, 0.5)


@pytest.mark.parametrize(
    "smoothing",
    [
        Smoothing(),
        Smoothing(noise=0.05),
        Smoothing(acceleration=300.0),
        Smoothing(filter="one-euro"),
        Smoothing(filter="one-euro", min_cutoff=1.0, target="weights"),
        Smoothing(filter="kalman"),
    ],
    ids=["auto", "auto-noise", "auto-acceleration", "one-euro", "one-euro-weights", "kalman"],
)
def test_smoothing_round_trips_auto_or_named(smoothing):
    hello = Hello(rig="demo", smoothing=smoothing)
    assert decode_client(encode(hello)) == hello


def test_a_named_filter_travels_and_auto_sends_only_what_differs():
    assert Smoothing(filter="one-euro").serialize()["filter"] == "one-euro"
    assert "acceleration" not in Smoothing(filter="one-euro").serialize()
    auto = Smoothing(acceleration=300.0, noise=0.05).serialize()
    assert "filter" not in auto and (auto["acceleration"], auto["noise"]) == (300.0, 0.05)


def test_auto_smoothing_of_the_weights_is_valid():
    assert Smoothing.parse({"target": "weights"}).filter is None


def test_protocol_and_rig_agree_on_the_kalman_default():
    assert KALMAN_ACCELERATION == filters.KALMAN_ACCELERATION == Smoothing().acceleration


def test_ready_saying_the_filter_encodes_to_the_spec_example():
    assert encode(READY) == _spec_example("ready.smoothing")


def test_ready_saying_the_filter_round_trips():
    assert decode_server(encode(READY)) == READY
    assert decode_server(encode(READY)).smoothing == "kalman"


def test_ready_without_smoothing_has_no_smoothing_key():
    assert "smoothing" not in dataclasses.replace(READY, smoothing=None).serialize()


def test_ready_accepts_a_filter_name_it_does_not_know():
    # A later server may run another filter; an older client still opens the session.
    ready = decode_server(encode(dataclasses.replace(READY, smoothing="spacetime")))
    assert ready.smoothing == "spacetime"


def test_ready_smoothing_that_is_not_a_string_is_invalid():
    obj = {**READY.serialize(), "smoothing": 3}
    with pytest.raises(ProtocolError) as caught:
        decode_server(msgpack.packb(obj, use_bin_type=True))
    assert caught.value.code == ErrorCode.INVALID_FIELD


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


def test_calibrated_saying_the_filter_encodes_to_the_spec_example_and_round_trips():
    calibrated = Calibrated(active=True, seq=9, smoothing="kalman")
    assert encode(calibrated) == _spec_example("calibrated.smoothing")
    assert decode_server(encode(calibrated)) == calibrated
    # Without smoothing the key is absent (§10.9's bytes stay, tested with the examples).
    assert "smoothing" not in Calibrated(active=True, seq=9).serialize()


def test_calibrated_smoothing_that_is_not_a_string_is_invalid():
    obj = {**Calibrated(active=True).serialize(), "smoothing": 3}
    with pytest.raises(ProtocolError) as caught:
        decode_server(msgpack.packb(obj, use_bin_type=True))
    assert caught.value.code == ErrorCode.INVALID_FIELD

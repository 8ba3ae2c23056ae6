"""Stage stamps (PROTOCOL.md §5.4): golden bytes, the spec's examples, the checks, and the
window a server relays them in; frames and pongs without them keep their bytes."""

from __future__ import annotations

import re
from importlib import resources

import msgpack
import numpy as np
import pytest
from _protocol_samples import SAMPLES as PLAIN

from facecast.protocol import (
    ErrorCode,
    Frame,
    Pong,
    ProtocolError,
    Result,
    Stamps,
    decode_client,
    decode_server,
    encode,
)
from facecast.protocol.stamps import STAMP_FUTURE_SLACK, STAMP_MAX_AGE

T0 = 1_700_000_000.0
PUBLISHED = Stamps(captured=T0 + 0.125, tracked=T0 + 0.25, sent=T0 + 0.3125)
SAMPLES = {
    "frame.stamps": Frame(
        seq=7,
        ts=12.5,
        points=np.array([[0.0, 1.0, 2.0], [-0.5, 0.25, 1.5]], dtype=np.float32),
        stamps=PUBLISHED,
    ),
    "result.stamps": Result(
        seq=7,
        ts=12.5,
        weights=np.array([0.5, 0.25, 0.25], dtype=np.float32),
        proc_us=180,
        dropped=2,
        server_ts=T0 + 0.5,
        stamps=Stamps(
            captured=T0 + 0.125, tracked=T0 + 0.25, sent=T0 + 0.3125, server_in=T0 + 0.375
        ),
    ),
    "pong.clock": Pong(id=1, ts=3.25, server_ts=T0 + 0.5),
}
GOLDEN = {
    "frame.stamps": "86a17601a474797065a56672616d65a373657107a27473cb4029000000000000a6706f696e74"
    "7383a56474797065a3663332a57368617065920203a464617461c418000000000000803f00000040000000bf00"
    "00803e0000c03fa67374616d707383a86361707475726564cb41d954fc40080000a7747261636b6564cb41d954"
    "fc40100000a473656e74cb41d954fc40140000",
    "result.stamps": "89a17601a474797065a6726573756c74a373657107a27473cb4029000000000000a77765"
    "696768747383a56474797065a3663332a573686170659103a464617461c40c0000003f0000803e0000803ea770"
    "726f635f7573ccb4a764726f7070656402a97365727665725f7473cb41d954fc40200000a67374616d707384a8"
    "6361707475726564cb41d954fc40080000a7747261636b6564cb41d954fc40100000a473656e74cb41d954fc40"
    "140000a97365727665725f696ecb41d954fc40180000",
    "pong.clock": "85a17601a474797065a4706f6e67a2696401a27473cb400a000000000000a97365727665725f"
    "7473cb41d954fc40200000",
}
_EXAMPLE = re.compile(r"<!-- example: (\w+\.(?:stamps|clock)) -->\s*```[a-z]*\n(.*?)```", re.DOTALL)


def _spec_examples() -> dict[str, bytes]:
    text = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")
    return {
        name: bytes.fromhex(re.sub(r"[^0-9a-fA-F]", "", block))
        for name, block in _EXAMPLE.findall(text)
    }


def _decode(name: str, data: bytes):
    return decode_client(data) if name.startswith("frame") else decode_server(data)


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_message_with_stamps_encodes_to_golden_bytes(name: str) -> None:
    assert encode(SAMPLES[name]).hex() == GOLDEN[name]


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_bytes_with_stamps_decode_to_the_message(name: str) -> None:
    assert _decode(name, bytes.fromhex(GOLDEN[name])) == SAMPLES[name]


def test_spec_shows_every_stamps_example_as_encoded() -> None:
    assert _spec_examples() == {name: encode(message) for name, message in SAMPLES.items()}


@pytest.mark.parametrize("name", ["frame", "result", "pong"])
def test_a_message_without_stamps_keeps_its_bytes_and_reads_none(name: str) -> None:
    # An older client's frame, an older server's result and pong: no new key, None read.
    data = encode(PLAIN[name])
    decoded = _decode(name, data)
    assert b"stamps" not in data and b"server_ts" not in data
    assert getattr(decoded, "stamps", None) is None and getattr(decoded, "server_ts", None) is None


@pytest.mark.parametrize(
    ("stamps", "code"),
    [
        ([1.0, 2.0], ErrorCode.INVALID_FIELD),
        ({"captured": "now"}, ErrorCode.INVALID_FIELD),
        ({"captured": True}, ErrorCode.INVALID_FIELD),
        ({"sent": float("nan")}, ErrorCode.NON_FINITE),
        ({"tracked": float("inf")}, ErrorCode.NON_FINITE),
    ],
)
def test_bad_frame_stamps_are_refused_with_their_code(stamps, code) -> None:
    body = msgpack.packb({**PLAIN["frame"].serialize(), "stamps": stamps})

    with pytest.raises(ProtocolError) as raised:
        decode_client(body)

    assert raised.value.code == code and "frame.stamps" in raised.value.message


def test_unknown_and_nil_stamp_keys_are_ignored() -> None:
    body = msgpack.packb(
        {**PLAIN["frame"].serialize(), "stamps": {"captured": 5.0, "sent": None, "later": 1}}
    )
    assert decode_client(body).stamps == Stamps(captured=5.0)


def test_the_server_relays_plausible_stamps_and_sets_its_own_arrival() -> None:
    assert PUBLISHED.arrived(T0 + 0.375) == SAMPLES["result.stamps"].stamps


def test_a_publisher_server_in_is_replaced_by_the_servers() -> None:
    claimed = Stamps(sent=T0, server_in=T0 - 5.0)
    assert claimed.arrived(T0 + 0.01) == Stamps(sent=T0, server_in=T0 + 0.01)


@pytest.mark.parametrize(
    "bad",
    [
        T0 + STAMP_FUTURE_SLACK + 0.001,  # from the future
        T0 - STAMP_MAX_AGE - 0.001,  # from the far past
        -1e300,
        1e300,
    ],
)
def test_a_stamp_out_of_the_window_is_not_relayed(bad: float) -> None:
    arrived = Stamps(captured=bad, tracked=T0 - 0.02, sent=T0 - 0.01).arrived(T0)
    assert arrived == Stamps(tracked=T0 - 0.02, sent=T0 - 0.01, server_in=T0)


def test_stamps_out_of_the_paths_order_are_not_relayed() -> None:
    # "sent" before "tracked": the later stage cannot precede the earlier one.
    arrived = Stamps(captured=T0 - 0.03, tracked=T0 - 0.01, sent=T0 - 0.02).arrived(T0)
    assert arrived == Stamps(captured=T0 - 0.03, tracked=T0 - 0.01, server_in=T0)


def test_stamps_with_nothing_plausible_are_not_relayed_at_all() -> None:
    assert Stamps(captured=T0 + 3600).arrived(T0) is None
    assert Stamps().arrived(T0) is None

"""Fuzz: on any input the decoders either return a message or raise ProtocolError (§3).

With CI=true each test runs about as many cases as it takes to reach the branches of the
decoders it reaches (line arcs of facecast.protocol traced, Dec 2026): arbitrary bytes
reached 66 of its 72 arcs within 100 cases and the last 6 at 2,526 (the version check of a
decoded map, which the msgpack test reaches in its first cases), arbitrary msgpack all 70
within 277: 2,000 and 1,000 cases. Maps shaped like each message (valid, one field broken,
or loosely alike, nested maps too) reach 460-474 arcs in 3,000 cases, where message-like
maps (any type, any known key) reached 169 in 10,000, still finding new ones at 8,839: they
keep 1,000 cases for the unknown types and keys the shaped maps never send. 300 each
elsewhere.
"""

from __future__ import annotations

import contextlib
import os

import msgpack
from _protocol_strategies import msgpack_values, near_messages, shaped_messages
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.protocol import Limits, ProtocolError, decode_client, decode_server

CI = os.environ.get("CI") == "true"


def _fuzz(ci_examples: int):
    return settings(
        max_examples=ci_examples if CI else 300,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


# Small limits so that fuzzing also crosses them.
_SMALL = Limits(max_message_bytes=512, max_server_message_bytes=512, max_string=8, max_keys=12)


def _decode_all(data: bytes) -> None:
    for decode in (decode_client, decode_server):
        for limits in (Limits(), _SMALL):
            # Returning a message and raising ProtocolError are both fine; anything else
            # escapes and fails the test.
            with contextlib.suppress(ProtocolError):
                decode(data, limits)


@_fuzz(ci_examples=2_000)
@given(st.binary(max_size=512))
def test_decoders_raise_only_protocol_error_on_arbitrary_bytes(data: bytes) -> None:
    _decode_all(data)


@_fuzz(ci_examples=1_000)
@given(msgpack_values)
def test_decoders_raise_only_protocol_error_on_arbitrary_msgpack(value: object) -> None:
    _decode_all(msgpack.packb(value, use_bin_type=True))


@_fuzz(ci_examples=1_000)
@given(near_messages())
def test_decoders_raise_only_protocol_error_on_message_like_maps(value: dict) -> None:
    _decode_all(msgpack.packb(value, use_bin_type=True))


@_fuzz(ci_examples=3_000)
@given(shaped_messages())
def test_decoders_raise_only_protocol_error_on_maps_shaped_like_each_message(value: dict) -> None:
    _decode_all(msgpack.packb(value, use_bin_type=True))

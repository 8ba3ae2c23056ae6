"""Fuzz: on any input the decoders either return a message or raise ProtocolError (§3).

Runs at least 10,000 cases per test when the environment has CI=true.
"""

from __future__ import annotations

import contextlib
import os

import msgpack
from _protocol_strategies import msgpack_values, near_messages
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.protocol import Limits, ProtocolError, decode_client, decode_server

FUZZ_EXAMPLES = 10_000 if os.environ.get("CI") == "true" else 300
_fuzz = settings(
    max_examples=FUZZ_EXAMPLES,
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


@_fuzz
@given(st.binary(max_size=512))
def test_decoders_raise_only_protocol_error_on_arbitrary_bytes(data: bytes) -> None:
    _decode_all(data)


@_fuzz
@given(msgpack_values)
def test_decoders_raise_only_protocol_error_on_arbitrary_msgpack(value: object) -> None:
    _decode_all(msgpack.packb(value, use_bin_type=True))


@_fuzz
@given(near_messages())
def test_decoders_raise_only_protocol_error_on_message_like_maps(value: dict) -> None:
    _decode_all(msgpack.packb(value, use_bin_type=True))

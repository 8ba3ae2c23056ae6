"""Property: every valid message decodes to an equal message after encoding (§3)."""

from __future__ import annotations

import dataclasses

from _protocol_strategies import client_messages, results, server_messages
from hypothesis import given, settings

from facecast.protocol import Message, Result, decode_client, decode_server, encode, encode_result


@settings(max_examples=300, deadline=None)
@given(client_messages)
def test_client_message_round_trips(message: Message) -> None:
    assert decode_client(encode(message)) == message


@settings(max_examples=300, deadline=None)
@given(server_messages)
def test_server_message_round_trips(message: Message) -> None:
    assert decode_server(encode(message)) == message


@settings(max_examples=100, deadline=None)
@given(client_messages)
def test_encoding_is_deterministic(message: Message) -> None:
    assert encode(message) == encode(decode_client(encode(message)))


@settings(max_examples=300, deadline=None)
@given(results())
def test_encode_result_writes_the_bytes_of_the_result_message(result: Result) -> None:
    result = dataclasses.replace(result, server_ts=None)  # stream results carry none
    fast = encode_result(
        result.seq, result.ts, result.output, result.values, result.proc_us, result.dropped
    )
    assert fast == encode(result)

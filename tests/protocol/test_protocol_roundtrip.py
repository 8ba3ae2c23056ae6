"""Property: every valid message decodes to an equal message after encoding (§3)."""

from __future__ import annotations

from _protocol_strategies import client_messages, server_messages
from hypothesis import given, settings

from facecast.protocol import Message, decode_client, decode_server, encode


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

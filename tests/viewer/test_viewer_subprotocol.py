"""PROTOCOL.md §2.3 in a real Chromium: the bearer subprotocol needs ``facecast.v1`` beside it."""

from __future__ import annotations

import pytest

from facecast.cli.snapshot import serving

# Opens a WebSocket with the given subprotocols; resolves with what happened first.
_OPEN = """async ([url, protocols]) => await new Promise((resolve) => {
  const ws = new WebSocket(url, protocols);
  ws.onopen = () => { resolve("open " + ws.protocol); ws.close(); };
  ws.onerror = () => resolve("error");
})"""


@pytest.fixture
def auth_server(auth_settings):
    with serving(auth_settings) as base_url:
        yield base_url


def _stream_url(base_url: str) -> str:
    return base_url.replace("http://", "ws://", 1) + "/v1/stream"


def test_bearer_subprotocol_beside_facecast_v1_opens_and_selects_facecast_v1(page, auth_server):
    page.goto(auth_server + "/docs")
    outcome = page.evaluate(
        _OPEN, [_stream_url(auth_server), ["facecast.v1", "facecast.bearer.good-token"]]
    )
    assert outcome == "open facecast.v1"


def test_bearer_subprotocol_alone_fails_the_handshake_in_chromium(page, auth_server):
    page.goto(auth_server + "/docs")
    outcome = page.evaluate(_OPEN, [_stream_url(auth_server), ["facecast.bearer.good-token"]])
    assert outcome == "error"
    assert any("Sent non-empty 'Sec-WebSocket-Protocol' header" in e for e in page.errors)

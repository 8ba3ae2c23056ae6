"""PROTOCOL.md tells a client author what the server really does: §7 defaults, §10.6, §2.1 roles."""

from __future__ import annotations

import re
from importlib import resources

import pytest

from facecast.client.channel import FramePublisher, channel_url
from facecast.client.connection import connect
from facecast.protocol import ErrorCode, Hello, ProtocolError, decode_server
from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

_SPEC = resources.files("facecast.protocol").joinpath("PROTOCOL.md").read_text("utf-8")


def _section(number: str) -> str:
    start = _SPEC.index(f"\n## {number}. ")
    return _SPEC[start : _SPEC.index("\n## ", start + 1)]


def _table_default(key: str) -> float:
    match = re.search(rf"^\| `{key}` \| ([0-9][0-9 ]*)", _section("7"), re.MULTILINE)
    assert match is not None, f"§7 has no row for {key}"
    return float(match.group(1).replace(" ", ""))


@pytest.mark.parametrize(
    "key",
    ["max_fps", "rate_burst", "calibrate_rate", "calibrate_burst", "idle_timeout",
     "max_message_bytes"],
)  # fmt: skip
def test_section_7_states_the_servers_default(key):
    assert _table_default(key) == getattr(Settings(), key)


async def test_section_10_6_shows_the_limits_a_default_server_sends(tmp_path, rig, ws_impl):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    rig.save(rigs / "demo.rig")
    block = re.search(r"<!-- example: ready -->\s*```text\n(.*?)```", _SPEC, re.DOTALL)
    assert block is not None
    example = decode_server(bytes.fromhex(re.sub(r"\s", "", block.group(1))))
    async with run_server(Settings(rigs_dir=rigs), ws=ws_impl) as server:
        async with connect(server.base_url, "demo") as session:
            streamed = dict(session.ready.limits)
        publish = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(publish, Hello(rig="demo")) as publisher:
            assert publisher.ready is not None
            published = dict(publisher.ready.limits)
    assert dict(example.limits) == streamed == published


async def test_the_stream_needs_the_stream_role_as_section_2_1_says(tmp_path, rig, ws_impl):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    rig.save(rigs / "demo.rig")
    tokens = {"v": frozenset({"viewer"}), "s": frozenset({"stream"})}
    settings = Settings(rigs_dir=rigs, auth=True, tokens=tokens)
    assert "`/v1/stream` | One performer, one session" in _section("2")
    assert "Token role `stream`." in _section("2")
    async with run_server(settings, ws=ws_impl) as server:
        with pytest.raises(ProtocolError) as info:
            async with connect(server.base_url, "demo", token="v"):
                pass
        async with connect(server.base_url, "demo", token="s") as session:
            assert session.ready.rig == "demo"
    assert info.value.code == ErrorCode.FORBIDDEN

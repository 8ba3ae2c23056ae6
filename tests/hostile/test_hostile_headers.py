"""Requests that name their host or origin ambiguously (issue 25, item 7), on both of
uvicorn's HTTP implementations and a loopback bind.

Before: with two ``Origin`` headers the last one was checked, and an empty ``Host`` or an
absolute-form target naming a foreign host (``GET http://attacker.example/...``) was
answered. Now two ``Host`` or two ``Origin`` headers are 403 ``duplicate_host`` /
``duplicate_origin`` on any bind, and on a loopback bind an empty ``Host`` and a foreign
absolute-form target are 403 ``host_not_allowed`` (SERVER.md, "Browsers: Host and Origin").
"""

from __future__ import annotations

import asyncio
import base64
import json
import os

import pytest

from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

ATTACKER = "http://attacker.example"


async def raw_request(port: int, head: list[str], body: bytes = b"") -> tuple[int, dict]:
    """Send a request head exactly as given (one line per header); (status, JSON body)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + body)
        await writer.drain()
        response = await asyncio.wait_for(reader.read(), 10)
    finally:
        writer.close()
    header, _, payload = response.partition(b"\r\n\r\n")
    status = int(header.split(b" ", 2)[1])
    try:
        return status, json.loads(payload) if payload else {}
    except json.JSONDecodeError:
        return status, {}


def websocket_head(path: str, *headers: str) -> list[str]:
    key = base64.b64encode(os.urandom(16)).decode()
    return [f"GET {path} HTTP/1.1", "Upgrade: websocket", "Connection: Upgrade",
            f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13", *headers]  # fmt: skip


@pytest.fixture
async def server(tmp_path, http_impl):
    settings = Settings(rigs_dir=tmp_path / "rigs", access_log=False)
    async with run_server(settings, http=http_impl) as running:
        yield running


def own(server) -> str:
    return f"http://127.0.0.1:{server.port}"


@pytest.mark.parametrize("order", ["attacker-last", "attacker-first"])
async def test_two_origin_headers_are_refused_whichever_comes_last(server, order):
    origins = [f"Origin: {own(server)}", f"Origin: {ATTACKER}"]
    if order == "attacker-first":
        origins.reverse()
    status, body = await raw_request(
        server.port,
        ["DELETE /v1/rigs/face HTTP/1.1", f"Host: 127.0.0.1:{server.port}", *origins,
         "Connection: close"],
    )  # fmt: skip

    assert (status, body.get("code")) == (403, "duplicate_origin")


async def test_a_websocket_handshake_with_two_origin_headers_is_refused(server):
    head = websocket_head("/v1/stream", f"Host: 127.0.0.1:{server.port}",
                          f"Origin: {ATTACKER}", f"Origin: {own(server)}")  # fmt: skip
    status, _ = await raw_request(server.port, head)

    # websockets' handshake parser refuses two Origins itself (400) before the app runs.
    assert status == 400


async def test_two_host_headers_are_refused(server):
    status, body = await raw_request(
        server.port,
        ["GET /v1/rigs HTTP/1.1", "Host: attacker.example", f"Host: 127.0.0.1:{server.port}",
         "Connection: close"],
    )  # fmt: skip

    # h11 refuses two Hosts itself (400), before the app sees them.
    assert (status, body.get("code")) in ((403, "duplicate_host"), (400, None))


async def test_an_empty_host_is_refused_on_a_loopback_bind(server):
    status, body = await raw_request(
        server.port, ["GET /v1/rigs HTTP/1.1", "Host: ", "Connection: close"]
    )

    assert (status, body.get("code")) == (403, "host_not_allowed")


async def test_an_absolute_form_target_naming_a_foreign_host_is_refused(server):
    status, body = await raw_request(
        server.port,
        ["GET http://attacker.example/v1/rigs HTTP/1.1", f"Host: 127.0.0.1:{server.port}",
         "Connection: close"],
    )  # fmt: skip

    assert (status, body.get("code")) == (403, "host_not_allowed")


async def test_a_websocket_with_an_absolute_form_foreign_target_is_refused(server):
    head = websocket_head("http://attacker.example/v1/stream", f"Host: 127.0.0.1:{server.port}")
    status, _ = await raw_request(server.port, head)

    assert status == 403


async def test_the_ordinary_requests_still_pass(server):
    # One Host naming the server, HTTP/1.0 without Host (not a browser), one own Origin.
    port = server.port
    plain = await raw_request(port, ["GET /v1/rigs HTTP/1.1", f"Host: 127.0.0.1:{port}",
                                     "Connection: close"])  # fmt: skip
    old = await raw_request(port, ["GET /v1/rigs HTTP/1.0"])
    same_origin = await raw_request(
        port,
        ["DELETE /v1/rigs/nothing HTTP/1.1", f"Host: 127.0.0.1:{port}",
         f"Origin: {own(server)}", "Connection: close"],
    )  # fmt: skip

    assert plain == (200, {"rigs": []}) and old == (200, {"rigs": []})
    assert same_origin[0] == 404  # past the guard: the rig does not exist


async def test_a_public_bind_refuses_duplicates_but_does_not_check_hosts(tmp_path, http_impl):
    settings = Settings(rigs_dir=tmp_path / "rigs", host="0.0.0.0", access_log=False,
                        tokens={"admin-token": frozenset({"admin"})})  # fmt: skip
    async with run_server(settings, http=http_impl) as server:
        port = server.port
        auth = "Authorization: Bearer admin-token"
        empty_host = await raw_request(port, ["GET /v1/rigs HTTP/1.1", "Host: ", auth,
                                              "Connection: close"])  # fmt: skip
        duplicate = await raw_request(
            port,
            ["DELETE /v1/rigs/face HTTP/1.1", "Host: example.org", auth,
             "Origin: http://example.org", f"Origin: {ATTACKER}", "Connection: close"],
        )  # fmt: skip

    assert empty_host[0] == 200
    assert (duplicate[0], duplicate[1].get("code")) == (403, "duplicate_origin")

"""Host and Origin checks against a real uvicorn (issue 13, item 4): DNS rebinding and
cross-site pages cannot delete rigs or open sessions; the server's own pages, non-browser
clients and ``allowed_origins`` can."""

from __future__ import annotations

import dataclasses

import httpx
import pytest
import websockets
from _server_helpers import raw_websocket

from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

ATTACKER = "http://attacker.example"
VIEWER = "http://viewer.example:9000"


@pytest.fixture
async def served(settings, rig, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        yield server


def client(server) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=30)


async def test_a_rebound_host_cannot_delete_a_rig_on_a_loopback_server(served):
    async with client(served) as http:
        refused = await http.delete(
            "/v1/rigs/face", headers={"Host": "attacker.example:8000", "Origin": ATTACKER}
        )
        still = await http.get("/v1/rigs/face")

    assert (refused.status_code, refused.json()["code"]) == (403, "host_not_allowed")
    assert still.status_code == 200


async def test_a_cross_site_page_cannot_delete_a_rig(served):
    async with client(served) as http:
        refused = await http.delete("/v1/rigs/face", headers={"Origin": ATTACKER})
        still = await http.get("/v1/rigs/face")
        own = await http.delete("/v1/rigs/face", headers={"Origin": served.base_url})

    assert (refused.status_code, refused.json()["code"]) == (403, "origin_not_allowed")
    assert still.status_code == 200 and own.status_code == 204


@pytest.mark.parametrize("path", ["/v1/stream", "/v1/channels/stage/watch?rig=face"])
async def test_a_cross_site_websocket_handshake_is_refused_before_101(served, path):
    with pytest.raises(websockets.InvalidStatus) as info:
        async with websockets.connect(f"{served.ws_url}{path}", origin=ATTACKER):
            pass

    assert info.value.response.status_code == 403
    assert b'"code":"origin_not_allowed"' in info.value.response.body


async def test_a_websocket_with_a_rebound_host_is_refused(served):
    _, writer, status = await raw_websocket(
        served.host, served.port, "/v1/stream", {"Host": "attacker.example", "Origin": ATTACKER}
    )
    writer.close()

    assert status.startswith("HTTP/1.1 403")


@pytest.mark.parametrize("origin", ["own", None])
async def test_the_servers_own_pages_and_non_browser_clients_open_sessions(served, origin):
    page = served.base_url if origin == "own" else None
    async with websockets.connect(f"{served.ws_url}/v1/stream", origin=page) as ws:
        assert ws.response.status_code == 101


@pytest.mark.parametrize("name", ["localhost", "127.0.0.1", "[::1]", "studio.localhost"])
async def test_loopback_names_are_answered(served, name):
    async with client(served) as http:
        response = await http.get("/v1/rigs", headers={"Host": f"{name}:{served.port}"})

    assert response.status_code == 200


async def test_allowed_origins_may_use_websockets_and_read_the_api_with_cors(settings, rig):
    allowing = dataclasses.replace(settings, allowed_origins=(VIEWER,))
    async with run_server(allowing) as server, client(server) as http:
        server.app.state.store.put_rig("face", rig)
        preflight = await http.options(
            "/v1/rigs/face",
            headers={"Origin": VIEWER, "Access-Control-Request-Method": "GET",
                     "Access-Control-Request-Headers": "authorization"},
        )  # fmt: skip
        read = await http.get("/v1/rigs/face", headers={"Origin": VIEWER})
        other = await http.get("/v1/rigs/face", headers={"Origin": ATTACKER})
        async with websockets.connect(f"{server.ws_url}/v1/stream", origin=VIEWER) as ws:
            opened = ws.response.status_code

    assert preflight.status_code == 200
    assert preflight.headers["access-control-allow-origin"] == VIEWER
    assert "authorization" in preflight.headers["access-control-allow-headers"].lower()
    assert read.headers["access-control-allow-origin"] == VIEWER
    assert "access-control-allow-origin" not in other.headers
    assert opened == 101


async def test_allowed_hosts_admit_a_reverse_proxys_name(settings):
    proxied = dataclasses.replace(settings, allowed_hosts=("facecast.example",))
    async with run_server(proxied) as server, client(server) as http:
        named = await http.get("/v1/rigs", headers={"Host": "facecast.example"})
        other = await http.get("/v1/rigs", headers={"Host": "attacker.example"})

    assert named.status_code == 200 and other.status_code == 403


async def test_a_public_server_checks_origins_but_not_hosts(tmp_path):
    # Bound to a public address, auth is on and tokens guard it; its names are its own.
    public = Settings(
        rigs_dir=tmp_path / "rigs", host="0.0.0.0", tokens={"t": frozenset({"admin"})}
    )
    auth = {"Authorization": "Bearer t"}
    async with run_server(public) as server, client(server) as http:
        named = await http.get("/v1/rigs", headers={"Host": "facecast.example", **auth})
        cross = await http.delete("/v1/rigs/x", headers={"Origin": ATTACKER, **auth})

    assert named.status_code == 200
    assert (cross.status_code, cross.json()["code"]) == (403, "origin_not_allowed")

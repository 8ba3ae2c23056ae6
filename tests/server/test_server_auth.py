"""Auth on every endpoint: no token -> 401, wrong role -> 403, right role -> served."""

from __future__ import annotations

import dataclasses

import httpx
import pytest
import websockets
from _server_helpers import (
    folder_members,
    open_session,
    recv_error,
    server_logs,
    write_example_folder,
    zip_bytes,
)

from facecast.protocol import PUBLISH_PATH, WATCH_PATH, ErrorCode, Hello, encode
from facecast.server.logs import JsonFormatter
from facecast.server.settings import Settings, SettingsError
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

# (method, path, a role that may, a role that may not); the rig "face" exists.
ENDPOINTS = [
    ("GET", "/v1/rigs", "viewer", "publisher"),
    ("GET", "/v1/rigs/face", "viewer", "publisher"),
    ("GET", "/v1/rigs/face/model.glb", "stream", "publisher"),
    ("GET", "/v1/rigs/face/rig", "stream", "viewer"),
    ("PUT", "/v1/rigs/face", "admin", "stream"),
    ("PUT", "/v1/rigs/face/examples", "admin", "viewer"),
    ("DELETE", "/v1/rigs/face", "admin", "stream"),
]


def _body(method: str, path: str, rig, tmp_path) -> bytes | None:
    if method != "PUT":
        return None
    if path.endswith("/examples"):
        write_example_folder(tmp_path / "set")
        return zip_bytes(folder_members(tmp_path / "set"))
    return rig.to_bytes()


@pytest.mark.parametrize(("method", "path", "right", "wrong"), ENDPOINTS)
async def test_endpoint_needs_a_token_with_the_right_role(
    auth_settings, rig, tmp_path, method, path, right, wrong
):
    body = _body(method, path, rig, tmp_path)
    async with run_server(auth_settings) as server:
        server.app.state.store.put_rig("face", rig)
        async with httpx.AsyncClient(base_url=server.base_url, timeout=30) as http:
            missing = await http.request(method, path, content=body)
            unknown = await http.request(
                method, path, content=body, headers={"Authorization": "Bearer nope"}
            )
            forbidden = await http.request(
                method, path, content=body, headers={"Authorization": f"Bearer {wrong}-token"}
            )
            allowed = await http.request(
                method, path, content=body, headers={"Authorization": f"Bearer {right}-token"}
            )

    assert (missing.status_code, missing.json()["code"]) == (401, "unauthorized")
    assert missing.headers["www-authenticate"] == "Bearer"
    assert (unknown.status_code, unknown.json()["code"]) == (401, "unauthorized")
    assert (forbidden.status_code, forbidden.json()["code"]) == (403, "forbidden")
    assert allowed.status_code in (200, 201, 204), allowed.text


async def test_admin_token_is_allowed_everywhere(auth_settings, rig, tmp_path):
    statuses = []
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=30) as http,
    ):
        for method, path, _, _ in ENDPOINTS:
            server.app.state.store.put_rig("face", rig)
            response = await http.request(
                method,
                path,
                content=_body(method, path, rig, tmp_path / method / path.replace("/", "_")),
                headers={"Authorization": "Bearer admin-token"},
            )
            statuses.append(response.status_code)

    assert all(s in (200, 201, 204) for s in statuses), statuses


async def test_health_and_ready_need_no_token(auth_settings):
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        health = await http.get("/healthz")
        ready = await http.get("/readyz")

    assert health.status_code == ready.status_code == 200


async def test_metrics_needs_admin_when_auth_is_on(auth_settings):
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        missing = await http.get("/metrics")
        viewer = await http.get("/metrics", headers={"Authorization": "Bearer viewer-token"})
        admin = await http.get("/metrics", headers={"Authorization": "Bearer admin-token"})

    assert (missing.status_code, viewer.status_code, admin.status_code) == (401, 403, 200)


async def test_metrics_auth_off_opens_metrics_to_tokenless_scrapers(auth_settings):
    settings = dataclasses.replace(auth_settings, metrics_auth=False)
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        missing = await http.get("/metrics")
        rigs = await http.get("/v1/rigs")

    assert (missing.status_code, rigs.status_code) == (200, 401)


@pytest.mark.parametrize("path", ["/docs", "/openapi.json"])
async def test_api_docs_need_a_token_of_any_role_when_auth_is_on(auth_settings, path):
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        missing = await http.get(path)
        unknown = await http.get(path, headers={"Authorization": "Bearer nobody"})
        viewer = await http.get(path, headers={"Authorization": "Bearer viewer-token"})
        in_query = await http.get(path, params={"token": "publisher-token"})

    assert (missing.status_code, unknown.status_code) == (401, 401)
    assert viewer.status_code == in_query.status_code == 200


async def test_docs_page_opened_with_a_query_token_fetches_its_schema_with_it(auth_settings):
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        page = await http.get("/docs", params={"token": "viewer-token"})
        schema = await http.get("/openapi.json?token=viewer-token")

    assert "/openapi.json?token=viewer-token" in page.text
    assert "/v1/rigs" in schema.json()["paths"]


# -- how REST takes a token (issue 15, item 6) ---------------------------------------------

#: Every REST endpoint behind auth: each reads the header only, and refuses ?token= alike.
HEADER_ONLY = [(m, p) for m, p, _, _ in ENDPOINTS] + [
    ("GET", "/v1/channels"),
    ("GET", "/v1/channels/stage"),
    ("GET", "/v1/demo/animation"),
    ("GET", "/metrics"),
]


@pytest.mark.parametrize(("method", "path"), HEADER_ONLY)
async def test_rest_endpoints_refuse_a_query_token_and_say_where_it_goes(
    auth_settings, rig, tmp_path, method, path
):
    body = _body(method, path, rig, tmp_path)
    async with run_server(auth_settings) as server:
        server.app.state.store.put_rig("face", rig)
        async with httpx.AsyncClient(base_url=server.base_url, timeout=30) as http:
            response = await http.request(
                method, path, content=body, params={"token": "admin-token"}
            )
        still = server.app.state.store.get("face")  # a refused DELETE/PUT changed nothing

    assert (response.status_code, response.json()["code"]) == (401, "token_in_query")
    assert "Authorization: Bearer" in response.json()["detail"]
    assert "admin-token" not in response.text
    assert still.checksum == rig.checksum


async def test_docs_pages_keep_their_query_token_out_of_referers_and_caches(auth_settings):
    async with (
        run_server(auth_settings) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        page = await http.get("/docs", params={"token": "viewer-token"})
        schema = await http.get("/openapi.json", params={"token": "viewer-token"})

    for response in (page, schema):
        assert response.status_code == 200
        assert response.headers["referrer-policy"] == "no-referrer"
        assert response.headers["cache-control"] == "no-store"


async def test_a_query_token_never_reaches_the_logs(auth_settings, rig):
    secret = "stream-token"
    formatter = JsonFormatter()
    async with run_server(auth_settings) as server:
        server.app.state.store.put_rig("face", rig)
        with server_logs() as records:
            async with httpx.AsyncClient(base_url=server.base_url) as http:
                await http.get("/docs", params={"token": secret})
                await http.get("/v1/rigs", params={"token": secret})
            url = f"{server.ws_url}/v1/stream?token={secret}"
            async with websockets.connect(url) as ws:
                await open_session(ws, "face")
            url = f"{server.ws_url}/v1/stream?token=not-{secret}"
            async with websockets.connect(url) as ws:
                await recv_error(ws)
        logged = "\n".join(formatter.format(r) for r in records)

    assert "/v1/rigs" in logged and "session.open" in logged  # the requests were logged
    assert secret not in logged


# -- WebSocket ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("token", "code"),
    [
        (None, ErrorCode.UNAUTHORIZED),
        ("nope", ErrorCode.UNAUTHORIZED),
        ("viewer-token", ErrorCode.FORBIDDEN),
    ],
)
async def test_stream_without_the_stream_role_gets_an_error_then_close_1008(
    auth_settings, rig, ws_impl, token, code
):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    async with run_server(auth_settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with websockets.connect(
            f"{server.ws_url}/v1/stream", additional_headers=headers
        ) as ws:
            await ws.send(encode(Hello(rig="face")))
            error = await recv_error(ws)
            with pytest.raises(websockets.ConnectionClosed):
                await ws.recv()

    assert (error.code, error.fatal) == (code, True)
    assert ws.close_code == 1008


@pytest.mark.parametrize("via", ["header", "subprotocol", "query"])
async def test_stream_token_is_accepted_from_header_subprotocol_or_query(
    auth_settings, rig, ws_impl, via
):
    url_query, headers, protocols = "", {}, ["facecast.v1"]
    if via == "header":
        headers = {"Authorization": "Bearer stream-token"}
    elif via == "subprotocol":
        protocols.append("facecast.bearer.stream-token")
    else:
        url_query = "?token=stream-token"
    async with run_server(auth_settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with websockets.connect(
            f"{server.ws_url}/v1/stream{url_query}",
            additional_headers=headers,
            subprotocols=protocols,
        ) as ws:
            ready = await open_session(ws, "face")

    assert ready.rig == "face"
    assert ws.subprotocol == "facecast.v1"  # never the bearer one: it would echo the token


async def test_refusal_reaches_a_client_that_sends_nothing(auth_settings, ws_impl):
    async with (
        run_server(auth_settings, ws=ws_impl) as server,
        websockets.connect(f"{server.ws_url}/v1/stream") as ws,
    ):
        error = await recv_error(ws)

    assert error.code == ErrorCode.UNAUTHORIZED


async def test_every_websocket_refusal_is_counted_once_by_its_code(auth_settings, ws_impl):
    # /v1/stream and both channel endpoints refuse through one rule (refusal.refuse).
    async with run_server(auth_settings, ws=ws_impl) as server:
        paths = [
            ("/v1/stream", "viewer-token"),
            ("/v1/stream", None),
            (PUBLISH_PATH.format(name="stage"), None),
            (WATCH_PATH.format(name="stage") + "?rig=face", None),
        ]
        for path, token in paths:
            headers = {"Authorization": f"Bearer {token}"} if token else {}
            async with websockets.connect(
                f"{server.ws_url}{path}", additional_headers=headers
            ) as ws:
                await recv_error(ws)
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            admin = {"Authorization": "Bearer admin-token"}
            text = (await http.get("/metrics", headers=admin)).text

    assert 'facecast_errors_total{code="UNAUTHORIZED"} 3.0' in text
    assert 'facecast_errors_total{code="FORBIDDEN"} 1.0' in text


def test_public_bind_without_tokens_refuses_to_start():
    settings = Settings(host="0.0.0.0")

    with pytest.raises(SettingsError, match="no API tokens"):
        settings.check_startable()


def test_loopback_bind_has_auth_off_unless_forced():
    assert not Settings().auth_enabled
    assert Settings(auth=True).auth_enabled
    assert Settings(host="10.1.2.3", tokens={"t": ["admin"]}).auth_enabled

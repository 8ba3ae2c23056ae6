"""Roles on every channel endpoint: publish needs publisher, watch and GET need viewer (or admin)."""

from __future__ import annotations

import dataclasses

import httpx
import pytest

from facecast.client.channel import channel_url
from facecast.protocol import ErrorCode, Hello
from facecast.server.testing import run_server

from ._helpers import Publisher, Watcher, refused
from .conftest import TOKENS

pytestmark = pytest.mark.anyio


@pytest.fixture
def auth_settings(settings):
    return dataclasses.replace(settings, auth=True, tokens=TOKENS)


@pytest.mark.parametrize(
    ("token", "code"),
    [(None, ErrorCode.UNAUTHORIZED), ("wrong", ErrorCode.UNAUTHORIZED),
     ("viewer-token", ErrorCode.FORBIDDEN), ("stream-token", ErrorCode.FORBIDDEN)],
)  # fmt: skip
async def test_publish_needs_the_publisher_role(auth_settings, token, code, ws_impl):
    async with run_server(auth_settings, ws=ws_impl) as server:
        error, close = await refused(channel_url(server.ws_url, "stage", "publish"),
                                     token=token, hello=Hello(rig="alpha"))  # fmt: skip

    assert (error.code, close) == (code, 1008)


@pytest.mark.parametrize(
    ("token", "code"),
    [(None, ErrorCode.UNAUTHORIZED), ("wrong", ErrorCode.UNAUTHORIZED),
     ("publisher-token", ErrorCode.FORBIDDEN), ("stream-token", ErrorCode.FORBIDDEN)],
)  # fmt: skip
async def test_watch_needs_the_viewer_role(auth_settings, token, code, ws_impl):
    async with run_server(auth_settings, ws=ws_impl) as server:
        url = channel_url(server.ws_url, "stage", "watch", {"rig": "alpha"})
        error, close = await refused(url, token=token)

    assert (error.code, close) == (code, 1008)


@pytest.mark.parametrize(
    ("token", "status"),
    [(None, 401), ("wrong", 401), ("publisher-token", 403), ("stream-token", 403),
     ("viewer-token", 200), ("admin-token", 200)],
)  # fmt: skip
@pytest.mark.parametrize("path", ["/v1/channels", "/v1/channels/stage"])
async def test_channel_info_needs_the_viewer_role(auth_settings, token, status, path, ws_impl):
    async with run_server(auth_settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "alpha", token="viewer-token")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        async with httpx.AsyncClient(base_url=server.base_url) as http:
            response = await http.get(path, headers=headers)
        await watcher.close()

    assert response.status_code == status


async def test_the_right_roles_publish_and_watch(auth_settings, ws_impl):
    async with run_server(auth_settings, ws=ws_impl) as server:
        publisher = await Publisher.open(server.ws_url, "stage", "alpha", token="publisher-token")
        watcher = await Watcher.open(server.ws_url, "stage", "beta", token="viewer-token")
        admin = await Watcher.open(server.ws_url, "stage", "beta", token="admin-token")
        ready = await watcher.next()
        admin_ready = await admin.next()

    assert publisher.ready.rig == "alpha"
    assert (ready.rig, admin_ready.rig) == ("beta", "beta")

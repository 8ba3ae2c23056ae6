"""Connections that never complete a request cannot take the HTTP endpoints down (slowloris).

Issue #13 item 2: 265 TCP connections sending nothing or partial headers filled uvicorn's
``limit_concurrency`` and ``/healthz`` answered 503 for as long as they were held.
"""

from __future__ import annotations

import asyncio
import select
import socket
import time

import httpx
import pytest

from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

PARTIAL_HEAD = b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "


@pytest.fixture
def slow_settings(rigs_dir) -> Settings:
    return Settings(
        rigs_dir=rigs_dir,
        max_connections=10,
        max_pending_connections=20,
        request_idle_timeout=1.0,
        request_head_timeout=2.0,
        access_log=False,
    )


def open_silent(port: int, count: int, *, partial: bool) -> list[socket.socket]:
    sockets = []
    for _ in range(count):
        sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        if partial:
            sock.sendall(PARTIAL_HEAD)
        sockets.append(sock)
    return sockets


def closed_by_server(sock: socket.socket) -> bool:
    """Whether the server has closed ``sock`` (EOF or reset), without waiting."""
    if not select.select([sock], [], [], 0)[0]:
        return False
    try:
        return sock.recv(1) == b""
    except OSError:
        return True


async def test_health_and_rest_answer_while_slowloris_connections_are_held(
    slow_settings, http_impl
):
    # Far more than uvicorn's limit_concurrency (10 + 4 + 64 + 20 = 98) in all.
    async with run_server(slow_settings, http=http_impl) as server:
        silent = open_silent(server.port, 80, partial=False)
        partial = open_silent(server.port, 80, partial=True)
        try:
            async with httpx.AsyncClient(base_url=server.base_url, timeout=5) as http:
                statuses = [
                    (await http.get(path)).status_code
                    for path in ("/healthz", "/readyz", "/v1/rigs")
                ]
        finally:
            for sock in silent + partial:
                sock.close()

    assert statuses == [200, 200, 200]


async def test_connections_that_never_complete_a_request_are_closed_in_bounded_time(
    slow_settings, http_impl
):
    async with run_server(slow_settings, http=http_impl) as server:
        # Fewer than max_pending_connections: none is evicted, each must time out.
        sockets = open_silent(server.port, 8, partial=False) + open_silent(
            server.port, 8, partial=True
        )
        bound = slow_settings.request_idle_timeout + slow_settings.request_head_timeout + 2.0
        deadline = time.monotonic() + bound
        try:
            while not all(map(closed_by_server, sockets)) and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            closed = [closed_by_server(s) or s.fileno() == -1 for s in sockets]
        finally:
            for sock in sockets:
                sock.close()

    assert all(closed), closed


async def test_a_request_head_dribbled_byte_by_byte_is_cut_at_the_head_timeout(
    slow_settings, http_impl
):
    async with run_server(slow_settings, http=http_impl) as server:
        sock = socket.create_connection(("127.0.0.1", server.port), timeout=5)
        start = time.monotonic()
        bound = slow_settings.request_head_timeout + 2.0
        cut = False
        with sock:
            head = PARTIAL_HEAD + b"x" * 10_000
            for byte in head:  # one byte per 50 ms, never the blank line ending a head
                try:
                    sock.sendall(bytes((byte,)))
                except OSError:
                    cut = True
                    break
                if closed_by_server(sock):
                    cut = True
                    break
                if time.monotonic() - start > bound:
                    break
                await asyncio.sleep(0.05)  # the attacker's pace, not synchronisation
        took = time.monotonic() - start

    assert cut and took <= bound


async def test_one_connection_past_max_pending_connections_closes_the_oldest(rigs_dir, http_impl):
    settings = Settings(
        rigs_dir=rigs_dir,
        max_pending_connections=5,
        request_idle_timeout=30.0,
        request_head_timeout=30.0,
        access_log=False,
    )
    async with run_server(settings, http=http_impl) as server:
        held = open_silent(server.port, settings.max_pending_connections, partial=False)
        newest = open_silent(server.port, 1, partial=False)[0]
        try:
            oldest = held[0]
            deadline = time.monotonic() + 5.0  # far below the 30 s timeouts
            evicted = False
            while not evicted and time.monotonic() < deadline:
                evicted = closed_by_server(oldest)
                await asyncio.sleep(0.02)
            kept = [not closed_by_server(s) for s in [*held[1:], newest]]
        finally:
            for sock in [*held, newest]:
                sock.close()

    assert evicted and all(kept)

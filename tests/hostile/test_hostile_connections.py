"""A tokenless client flooding WebSocket pings and reading nothing costs bounded memory and time.

Issue #13 item 1: uvicorn's ``websockets-sansio`` wrote a pong per ping without
back-pressure, and a refused connection waited for ever to send its error.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.channels._helpers import wait_for

from ._raw import flood_pings, open_raw, server_write_buffers
from .conftest import TOKENS

pytestmark = pytest.mark.anyio

#: asyncio's default high-water mark: a transport buffers this much before it pauses.
HIGH_WATER = 64 * 1024
#: asyncio's selector transports read at most this much at once (``max_size``), and the
#: WebSocket protocol answers every ping of a read before the guard sees the first: the
#: pongs of one read (never larger than their pings) go out in one write.
READ_SIZE = 256 * 1024


def refusal_bound(settings: Settings) -> float:
    """The documented longest life of a refused connection, plus 2 s for a loaded machine.

    The refusal itself, then at most twice the close timeout for the closing handshake
    before the connection is dropped whatever the peer does.
    """
    return settings.refuse_timeout + 2 * settings.ws_close_timeout + 2.0


@pytest.fixture
def auth_settings(rigs_dir) -> Settings:
    return Settings(rigs_dir=rigs_dir, auth=True, tokens=TOKENS, refuse_timeout=2.0)


async def test_a_ping_flood_that_never_reads_cannot_grow_the_server_buffer(auth_settings, ws_impl):
    async with run_server(auth_settings, ws=ws_impl) as server:
        sock, conn = open_raw(server.port, "/v1/stream")
        with sock:
            flood = asyncio.ensure_future(
                asyncio.to_thread(flood_pings, sock, conn, count=200_000, seconds=8.0)
            )
            # Sampled while the flood runs: once the connection is cut its buffer is gone.
            peak = 0
            while not flood.done():
                peak = max([peak, *server_write_buffers(server)])
                await asyncio.wait([flood], timeout=0.002)
            await flood

    # 200 000 pongs would be 25 MB; the cap is the backlog allowed beyond a paused buffer,
    # plus the pongs of the one read that paused it (seen: 155,424 bytes under load).
    assert peak <= auth_settings.max_pong_backlog + HIGH_WATER + READ_SIZE, peak


async def test_a_refused_connection_that_floods_pings_is_closed_in_bounded_time(
    auth_settings, ws_impl
):
    async with run_server(auth_settings, ws=ws_impl) as server:
        state = server.server.server_state
        start = time.monotonic()
        sock, conn = open_raw(server.port, "/v1/stream")
        with sock:
            await asyncio.to_thread(flood_pings, sock, conn, count=200_000, seconds=4.0)
            bound = refusal_bound(auth_settings)
            await wait_for(lambda: not state.connections, bound, "the refused connection to end")
            took = time.monotonic() - start

    assert took <= bound


async def test_a_refused_connection_that_sends_and_reads_nothing_is_closed_in_bounded_time(
    auth_settings, ws_impl
):
    async with run_server(auth_settings, ws=ws_impl) as server:
        state = server.server.server_state
        start = time.monotonic()
        sock, _ = open_raw(server.port, "/v1/stream")
        with sock:
            bound = refusal_bound(auth_settings)
            await wait_for(lambda: not state.connections, bound, "the refused connection to end")
            took = time.monotonic() - start

    assert took <= bound


def rss_bytes() -> int:
    """This process's resident memory (the server runs in a thread of it)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def send_messages(sock, conn, *, count: int, size: int, seconds: float) -> None:
    """Send up to ``count`` binary messages of ``size`` bytes within ``seconds``."""
    conn.send_binary(b"\x00" * size)
    message = b"".join(conn.data_to_send())
    sock.settimeout(0.2)
    deadline = time.monotonic() + seconds
    for _ in range(count):
        view = memoryview(message)
        while view and time.monotonic() < deadline:
            try:
                view = view[sock.send(view) :]
            except TimeoutError:
                continue  # the server stopped reading
            except OSError:
                return


async def test_refused_connections_cannot_make_the_server_read_ahead_many_large_messages(
    auth_settings, ws_impl
):
    size = 2 * auth_settings.max_message_bytes  # just under uvicorn's ws_max_size
    connections = 2
    async with run_server(auth_settings, ws=ws_impl) as server:
        peers = [open_raw(server.port, "/v1/stream") for _ in range(connections)]
        before = peak = rss_bytes()
        sends = [
            asyncio.to_thread(send_messages, *peer, count=40, size=size, seconds=4.0)
            for peer in peers
        ]
        senders = [asyncio.create_task(send) for send in sends]
        while not all(task.done() for task in senders):
            peak = max(peak, rss_bytes())
            await asyncio.sleep(0.05)  # sampling memory while the peers send
        for sock, _ in peers:
            sock.close()

    # A few messages per connection (read ahead of the app, being parsed, one copy in
    # the app); uvicorn's legacy default read 32 messages (64 MiB) ahead of each.
    assert peak - before <= connections * 12 * size, (peak - before) / size / connections

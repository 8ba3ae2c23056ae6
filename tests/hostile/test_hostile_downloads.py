"""Big stored files and slow readers (issue 31, item 7), on a real uvicorn.

Before: ``GET /v1/rigs/{id}/character.glb`` read the whole file into memory for each
request and held it while the client read (8 slow viewers of a 262 MB character: 2.1 GB
of RSS), and a character of any size was stored. Now files stream from disk in chunks
(``http.downloads``), and a character over ``max_character_bytes`` is a 422.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import httpx
import pytest

from facecast.rig.sources.ict import locate_ict
from facecast.server.settings import Settings
from facecast.server.storage.characters import pack_character
from facecast.server.storage.rig_store import RigStore
from facecast.server.testing import run_server
from tests.channels._helpers import tiny_rig

#: The stored character's GLB, and the slow readers of it at once.
FILE_BYTES = 48 * 2**20
READERS = 6
#: What those readers may add to the server's RSS together (each held the whole file:
#: 6 x 48 MiB and more; a chunk and a write buffer each now).
MAX_GROWTH_BYTES = 16 * 2**20


def rss(pid: int) -> int:
    """The process's resident set, from /proc (bytes)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc status")


def stored_big_character(rigs: Path) -> None:
    store = RigStore(rigs)
    store.open()
    try:
        glb = b"glTF" + bytes(FILE_BYTES - 4)  # served as stored; never parsed on the way out
        record = {"format": "gltf", "meta": {}, "bindings": {}}
        store.put_rig("big", tiny_rig(0), character=pack_character(glb, record))
    finally:
        store.close()


def started_reader(port: int, path: str) -> socket.socket:
    """A client that asks for ``path``, reads the head and the first body bytes, then
    stops reading (its receive buffer kept small)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
    sock.settimeout(30)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    data = b""
    while b"\r\n\r\n" not in data or len(data) < data.index(b"\r\n\r\n") + 5:
        chunk = sock.recv(4096)
        assert chunk, f"connection closed: {data[:300]!r}"
        data += chunk
    assert data.startswith(b"HTTP/1.1 200"), data[:300]
    assert f"content-length: {FILE_BYTES}".encode() in data.lower()
    return sock


@pytest.mark.anyio
@pytest.mark.parametrize("path", ["/v1/rigs/big/character.glb", "/v1/rigs/big/rig"])
async def test_slow_readers_of_a_large_stored_file_keep_the_server_s_memory_bounded(tmp_path, path):
    rigs = tmp_path / "rigs"
    stored_big_character(rigs)
    if path.endswith("/rig"):  # the rig file itself as large: its bytes are not checked here
        (rigs / "big.rig").write_bytes(bytes(FILE_BYTES))
    # In this process (its own thread and loop): the readers below block only this test.
    async with run_server(Settings(rigs_dir=rigs)) as server:
        warm = httpx.get(f"{server.base_url}/v1/rigs")
        before = rss(os.getpid())
        readers = [started_reader(server.port, path) for _ in range(READERS)]
        try:
            # Each response has begun: the old code had read the whole file by then.
            grown = rss(os.getpid()) - before
        finally:
            for sock in readers:
                sock.close()
        whole = httpx.get(f"{server.base_url}{path}", timeout=60)

    assert warm.status_code == 200

    assert grown < MAX_GROWTH_BYTES, f"RSS grew {grown / 2**20:.1f} MiB with {READERS} readers"
    assert whole.status_code == 200 and len(whole.content) == FILE_BYTES


@pytest.mark.anyio
@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
@pytest.mark.parametrize("params", [{}, {"expressions": "transfer", "names": "jawOpen"}])
async def test_a_character_over_max_character_bytes_is_refused(tmp_path, params):
    from tests.rig._avatars import avatar

    body = avatar("neutral_only" if params else "arkit")
    # The transfer adds its morph targets: the neutral-only file fits, its end size not.
    limit = len(body) + (1000 if params else -1)
    settings = Settings(rigs_dir=tmp_path / "rigs", max_character_bytes=limit)
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=60) as http,
    ):
        put = await http.put("/v1/characters/ava", content=body, params=params)
        described = await http.get("/v1/rigs/ava")

    assert put.status_code == 422, put.text
    assert put.json()["code"] == "character_too_large"
    assert described.status_code == 404

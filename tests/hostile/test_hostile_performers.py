"""A performer token reaches only its own performers' profiles and rigs, and cannot hold every fit slot.

Issue #25 item 3: any ``performer`` token could read, overwrite, refit and delete any
other performer's profile and ``{rig}@{name}`` rig, and one performer token trickling
capture bodies held every fit slot (admin PUTs got 503 for ``body_timeout``).
"""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest

from facecast.rig import ExampleSet, fit
from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.channels._helpers import wait_for

pytestmark = pytest.mark.anyio

K = 20  # the mediapipe_face_mesh layout's feature points
NAMES = ("neutral", "smile", "frown", "jawOpen")

TOKENS = {
    "admin-token": frozenset({"admin"}),
    # The perform page's token for ann: capture (as ann only), publish, watch.
    "ann-token": frozenset({"performer:ann", "publisher", "viewer"}),
    "bob-token": frozenset({"performer:bob"}),
    # A studio operator's token, capturing for every performer (as before issue #25).
    "studio-token": frozenset({"performer"}),
}


def character(seed: int = 0, num_vertices: int = 24) -> ExampleSet:
    rng = np.random.default_rng(seed)
    source = np.repeat(rng.normal(scale=3.0, size=(1, K, 3)), len(NAMES), axis=0)
    source[1:] += rng.normal(scale=0.5, size=(len(NAMES) - 1, K, 3))
    target = np.repeat(rng.normal(size=(1, num_vertices, 3)), len(NAMES), axis=0)
    target[1:] += rng.normal(scale=0.3, size=(len(NAMES) - 1, num_vertices, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(num_vertices - 2)])
    return ExampleSet(NAMES, source, target, faces)


def capture(seed: int) -> dict:
    """A capture body: another face making the character's expressions."""
    rng = np.random.default_rng(100 + seed)
    neutral = rng.normal(scale=3.0, size=(K, 3))
    points = {"neutral": neutral}
    for name in NAMES[1:]:
        points[name] = neutral + rng.normal(scale=0.6, size=(K, 3))
    return {
        "layout": "mediapipe_face_mesh",
        "points": {n: p.tolist() for n, p in points.items()},
    }


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(rigs_dir=tmp_path / "rigs", auth=True, tokens=TOKENS, max_pending_fits=2)


@pytest.fixture
async def server(settings):
    async with run_server(settings) as running:
        running.app.state.store.put_rig("hero", fit(character()))
        running.app.state.store.put_rig("villain", fit(character(seed=3)))
        yield running


def client(server, token: str) -> httpx.AsyncClient:
    return httpx.AsyncClient(
        base_url=server.base_url, timeout=60, headers={"Authorization": f"Bearer {token}"}
    )


async def operate(server, token: str, operation: str, performer: str) -> httpx.Response:
    """One of the performer endpoints on ``performer``'s profile, with ``token``."""
    async with client(server, token) as http:
        if operation == "put":
            return await http.put(f"/v1/rigs/hero/performer/{performer}", json=capture(2))
        if operation == "get":
            return await http.get(f"/v1/performers/{performer}")
        if operation == "refit":
            return await http.post(f"/v1/performers/{performer}/refit", params={"rig": "villain"})
        return await http.delete(f"/v1/performers/{performer}")


async def stored(server, performer: str) -> tuple[bytes, set[str]]:
    """The performer's profile file and the ids of the rigs fitted for them."""
    profile = (server.app.state.settings.rigs_dir / "performers" / f"{performer}.json").read_bytes()
    rigs = {info.id for info in server.app.state.store.list() if info.id.endswith(f"@{performer}")}
    return profile, rigs


OPERATIONS = ("put", "get", "refit", "delete")


@pytest.mark.parametrize("operation", OPERATIONS)
async def test_a_bound_performer_token_is_refused_another_performers_profile(server, operation):
    async with client(server, "bob-token") as bob:
        assert (await bob.put("/v1/rigs/hero/performer/bob", json=capture(1))).status_code == 201
    before = await stored(server, "bob")

    response = await operate(server, "ann-token", operation, "bob")

    assert response.status_code == 403
    assert response.json()["code"] == "performer_forbidden"
    assert "ann" in response.json()["detail"]
    assert await stored(server, "bob") == before == (before[0], {"hero@bob"})


@pytest.mark.parametrize("token", ["ann-token", "admin-token", "studio-token"])
async def test_a_performer_profile_is_used_by_its_token_admin_or_an_unbound_token(server, token):
    async with client(server, "ann-token") as ann:
        assert (await ann.put("/v1/rigs/hero/performer/ann", json=capture(1))).status_code == 201

    answers = [(await operate(server, token, op, "ann")).status_code for op in OPERATIONS]

    assert answers == [200, 200, 201, 204]  # replaced, read, villain@ann new, deleted
    profile_gone = not (server.app.state.settings.rigs_dir / "performers" / "ann.json").exists()
    assert profile_gone
    assert {"hero@ann", "villain@ann"} <= {info.id for info in server.app.state.store.list()}


async def trickle(server, token: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A capture PUT whose head and first bytes are sent, the rest of its body never."""
    body = b'{"layout": "mediapipe_face_mesh", "points": {}}' * 10
    reader, writer = await asyncio.open_connection(server.host, server.port)
    writer.write(
        f"PUT /v1/rigs/hero/performer/ann HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {token}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n".encode()
        + body[:10]
    )
    await writer.drain()
    return reader, writer


async def response(reader: asyncio.StreamReader) -> bytes:
    """One HTTP response: its head, and a body of its Content-Length."""
    head = await reader.readuntil(b"\r\n\r\n")
    length = next(
        int(line.split(b":", 1)[1])
        for line in head.split(b"\r\n")
        if line.lower().startswith(b"content-length:")
    )
    return head + await reader.readexactly(length)


async def test_one_performer_token_trickling_captures_holds_one_fit_slot(server):
    # max_pending_fits is 2: before the per-token cap, two trickles held both.
    state = server.app.state
    first = await trickle(server, "ann-token")
    await wait_for(lambda: state.pending_fits == 1, 10, "the first trickle to hold a slot")
    second = await trickle(server, "ann-token")
    answer = asyncio.create_task(asyncio.wait_for(response(second[0]), 10))
    await wait_for(lambda: answer.done() or state.pending_fits == 2, 10, "the second trickle")
    async with client(server, "admin-token") as admin:
        rig = await admin.put("/v1/rigs/stored", content=fit(character(seed=5)).to_bytes())
    async with client(server, "bob-token") as bob:
        bobs = await bob.put("/v1/rigs/hero/performer/bob", json=capture(1))
    refused = await answer
    for _, writer in (first, second):
        writer.close()
    await wait_for(lambda: state.pending_fits == 0, 10, "the trickle to give its slot back")

    assert refused.startswith(b"HTTP/1.1 429 ")
    assert b'"too_many_fits"' in refused
    assert rig.status_code == 201, rig.text
    # The second slot was the admin's, and is free again for another token.
    assert bobs.status_code == 201, bobs.text

"""The transfer job under hostile timing and files (issue 31, items 3 and 4), on a real uvicorn.

A DELETE or a replace while the job is in its store stage wins (before: 204 or 201, then
the job stored its rig and character anyway), and the job's record says what happened.
The job is held at its store stage by the app's stage hook (``transfer.STAGE_HOOK``): an
event, no sleeps. Uploads no job could finish are refused before the 202 (before: a
markers.txt index of 2**63 was a 500, a node's ``weights`` of 5 a job failing
``internal_error``).
"""

from __future__ import annotations

import asyncio
import io
import json
import struct
import threading
import time
import zipfile

import anyio
import httpx
import pytest

from facecast.rig.sources.ict import locate_ict
from facecast.server.http.transfer import STAGE_HOOK
from facecast.server.settings import Settings
from facecast.server.storage.jobs import JOBS_DIR, JobStore
from facecast.server.testing import run_server
from tests.channels._helpers import tiny_rig

pytestmark = [
    pytest.mark.anyio,
    pytest.mark.ict,
    pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found"),
]

ONE = {"expressions": "transfer", "names": "jawOpen"}


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(rigs_dir=tmp_path / "rigs")


def neutral_only() -> bytes:
    from tests.rig._avatars import avatar

    return avatar("neutral_only")


def with_json(glb: bytes, change) -> bytes:
    """``glb`` with its JSON chunk changed by ``change(doc)`` (the BIN chunk as it was)."""
    length = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20 : 20 + length])
    change(doc)
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    rest = glb[20 + length :]
    body = struct.pack("<I4s", len(text), b"JSON") + text + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def zipped(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


class Hold:
    """The stage hook: holds the job as it enters ``stage`` until released."""

    def __init__(self, stage: str) -> None:
        self.stage = stage
        self.reached = threading.Event()
        self.release = threading.Event()

    def __call__(self, stage: str) -> None:
        if stage == self.stage:
            self.reached.set()
            self.release.wait(120)


async def settled(
    http: httpx.AsyncClient, settings: Settings, rig_id: str, timeout: float = 120.0
) -> dict:
    """The job's record once its record has ended and its thread let go of the transfer
    slot (a cancelled record ends at once, while the job may still be running): polled,
    the job is a resource."""
    jobs = JobStore(settings.rigs_dir / JOBS_DIR, scratch=lambda: settings.rigs_dir, max_records=4)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        record = (await http.get(f"/v1/characters/{rig_id}/job")).json()
        if record.get("state") in ("done", "failed", "cancelled") and jobs.slot_free():
            return record
        await asyncio.sleep(0.05)
    raise AssertionError(f"job not ended after {timeout} s: {record}")


async def held_at_store(server, http: httpx.AsyncClient) -> Hold:
    hold = Hold("store")
    setattr(server.app.state, STAGE_HOOK, hold)
    put = await http.put("/v1/characters/ava", content=neutral_only(), params=ONE)
    assert put.status_code == 202, put.text
    assert await anyio.to_thread.run_sync(hold.reached.wait, 120), "never reached the store"
    return hold


async def test_a_delete_during_the_store_stage_wins_and_the_job_says_so(settings):
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=60) as http,
    ):
        hold = await held_at_store(server, http)
        deleted = await http.delete("/v1/rigs/ava")
        hold.release.set()
        record = await settled(http, settings, "ava")
        rig = await http.get("/v1/rigs/ava")

    assert deleted.status_code == 204, deleted.text
    assert record["state"] == "cancelled", record
    assert record["error"]["code"] == "character_deleted"
    assert rig.status_code == 404, rig.text
    assert not list(settings.rigs_dir.glob("ava.*"))  # no .rig, no .character


async def test_a_replace_during_the_store_stage_wins_and_the_job_says_so(settings):
    replacement = tiny_rig(7).to_bytes()
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=60) as http,
    ):
        hold = await held_at_store(server, http)
        put = await http.put("/v1/rigs/ava", content=replacement)
        hold.release.set()
        record = await settled(http, settings, "ava")
        stored = await http.get("/v1/rigs/ava/rig")
        character = await http.get("/v1/rigs/ava/character.glb")

    assert put.status_code == 201, put.text
    assert record["state"] == "cancelled", record
    assert record["error"]["code"] == "character_replaced"
    assert stored.content == replacement  # the job did not overwrite it
    assert character.status_code == 404  # nor add its character to it


def _weights_five(doc) -> None:
    doc["nodes"][next(i for i, n in enumerate(doc["nodes"]) if "mesh" in n)]["weights"] = 5


@pytest.mark.parametrize(
    ("body", "code"),
    [
        (lambda: zipped({"ava.glb": neutral_only(), "markers.txt": b"0 0\n1 1\n2 %d\n" % 2**63}),
         "marker_out_of_range"),
        (lambda: zipped({"ava.glb": neutral_only(), "markers.txt": b"0 0\n-1 1\n2 2\n"}),
         "marker_out_of_range"),
        (lambda: with_json(neutral_only(), _weights_five), "bad_gltf"),
    ],
    ids=["marker_2_63", "marker_negative", "node_weights_5"],
)  # fmt: skip
async def test_an_upload_no_job_could_finish_is_a_named_4xx_before_the_202(tmp_path, body, code):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=60) as http,
    ):
        put = await http.put("/v1/characters/ava", content=body(), params=ONE)
        job = await http.get("/v1/characters/ava/job")

    assert put.status_code == 422, put.text
    assert put.json()["code"] == code
    assert job.status_code == 404  # no job was ever recorded

"""Characters stored beside rigs: the rig's description, the file with its licence rule,
a glTF sent where a rig is expected, and no server path in any error body."""

from __future__ import annotations

import httpx
import pytest
from _server_helpers import folder_members, tiny_example_set, write_example_folder, zip_bytes

from facecast.rig import fit
from facecast.server.character_store import pack_character
from facecast.server.settings import Settings
from facecast.server.store import RigStore
from facecast.server.testing import run_server
from tests.viewer._character import NAMES, build_character

pytestmark = pytest.mark.anyio

ADMIN = {"Authorization": "Bearer admin-token"}
VIEWER = {"Authorization": "Bearer viewer-token"}


def client(server, headers=None) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=30, headers=headers)


@pytest.fixture(scope="module")
def characters():
    made = {v: build_character(v) for v in ("gltf", "vrm0", "vrm1")}
    locked = build_character("vrm1", redistribution=False)
    return made, locked, fit(made["gltf"].examples)


def store_characters(rigs_dir, characters) -> None:
    made, locked, rig = characters
    store = RigStore(rigs_dir)
    store.open()
    try:
        for variant, c in made.items():
            store.put_rig(f"face-{variant}", rig, character=pack_character(c.glb, c.record))
        store.put_rig("face-locked", rig, character=pack_character(locked.glb, locked.record))
        store.put_rig("face-locked@ann", rig)
    finally:
        store.close()


async def test_a_rig_with_a_character_describes_it_with_bindings_per_weight(settings, characters):
    store_characters(settings.rigs_dir, characters)
    async with run_server(settings) as server, client(server) as http:
        described = (await http.get("/v1/rigs/face-vrm1")).json()
        glb = await http.get("/v1/rigs/face-vrm1/character.glb")
        performer = (await http.get("/v1/rigs/face-locked@ann")).json()

    character = described["character"]
    assert character["format"] == "vrm1"
    assert character["url"] == "/v1/rigs/face-vrm1/character.glb"
    assert character["meta"]["authors"] == ["Facecast Tests"]
    assert len(character["bindings"]) == len(described["names"]) == len(NAMES)
    by_name = dict(zip(described["names"], character["bindings"], strict=True))
    assert by_name["neutral"] == []
    assert by_name["jawOpen"] == [
        {"mesh": 0, "morph": 0, "weight": 1.0},
        {"mesh": 1, "morph": 0, "weight": 1.0},
    ]
    assert glb.status_code == 200
    assert glb.headers["content-type"] == "model/gltf-binary"
    assert glb.content == characters[0]["vrm1"].glb  # the file as uploaded, byte for byte
    # A performer's rig shows its base rig's character.
    assert performer["character"]["format"] == "vrm1"
    assert performer["character"]["url"] == "/v1/rigs/face-locked@ann/character.glb"


async def test_a_rig_without_a_character_has_none(settings, rig):
    async with run_server(settings) as server, client(server) as http:
        await http.put("/v1/rigs/plain", content=rig.to_bytes())
        described = (await http.get("/v1/rigs/plain")).json()
        glb = await http.get("/v1/rigs/plain/character.glb")
        missing = await http.get("/v1/rigs/nothing/character.glb")

    assert "character" not in described
    assert glb.status_code == 404 and glb.json()["code"] == "no_character"
    assert "PUT /v1/characters" in glb.json()["detail"]
    assert missing.status_code == 404 and missing.json()["code"] == "rig_not_found"


async def test_a_vrm_forbidding_redistribution_is_served_only_with_a_token(
    settings, auth_settings, characters
):
    store_characters(settings.rigs_dir, characters)
    async with run_server(settings) as server, client(server) as http:
        anonymous = await http.get("/v1/rigs/face-locked/character.glb")
        anonymous_performer = await http.get("/v1/rigs/face-locked@ann/character.glb")
        allowed = await http.get("/v1/rigs/face-vrm1/character.glb")
    auth = Settings(**{**auth_settings.__dict__, "rigs_dir": settings.rigs_dir})
    async with run_server(auth) as server, client(server, VIEWER) as http:
        with_token = await http.get("/v1/rigs/face-locked/character.glb")

    assert anonymous.status_code == 403
    assert anonymous.json()["code"] == "character_not_redistributable"
    assert anonymous_performer.status_code == 403
    assert allowed.status_code == 200
    assert with_token.status_code == 200 and with_token.content == characters[1].glb


async def test_the_character_goes_with_its_rig(settings, characters, rig):
    store_characters(settings.rigs_dir, characters)
    file = settings.rigs_dir / "face-gltf.character"
    async with run_server(settings) as server, client(server) as http:
        assert file.is_file()
        replaced = await http.put("/v1/rigs/face-gltf", content=rig.to_bytes())
        after_replace = (await http.get("/v1/rigs/face-gltf")).json()
        replaced_file = file.exists()
        deleted = await http.delete("/v1/rigs/face-vrm0")

    assert replaced.status_code == 200
    assert "character" not in after_replace and not replaced_file
    assert deleted.status_code == 204
    assert not (settings.rigs_dir / "face-vrm0.character").exists()
    assert not (settings.rigs_dir / "face-vrm0.rig").exists()


@pytest.mark.parametrize("variant", ["gltf", "vrm1"])
async def test_a_character_file_sent_as_a_rig_or_examples_says_how_to_upload_it(settings, variant):
    glb = build_character(variant).glb
    async with run_server(settings) as server, client(server) as http:
        as_rig = await http.put("/v1/rigs/avatar", content=glb)
        as_examples = await http.put("/v1/rigs/avatar/examples", content=glb)
        as_gltf = await http.put("/v1/rigs/avatar", content=b'{"asset": {"version": "2.0"}}')

    for response in (as_rig, as_examples, as_gltf):
        problem = response.json()
        assert response.status_code == 415, problem
        assert problem["code"] == "character_not_rig"
        assert "PUT /v1/characters/avatar" in problem["detail"]
        assert "facecast rigs put" in problem["detail"]


async def test_no_error_body_holds_a_server_path(settings, tmp_path):
    folder = tmp_path / "set"
    write_example_folder(folder, tiny_example_set())
    members = folder_members(folder, "set/")
    # Each a loader error that names the file at fault, as it is on the server.
    broken_obj = {**members, "set/target/neutral.obj": b"v 1 2\nf 1 2 3\n"}
    missing = {k: v for k, v in members.items() if k != "set/target/neutral.obj"}
    bad_toml = {**members, "set/facecast.toml": b"[source\n"}
    rigs = str(settings.rigs_dir)
    async with run_server(settings) as server, client(server) as http:
        answers = [
            await http.put("/v1/rigs/x/examples", content=zip_bytes(body))
            for body in (broken_obj, missing, bad_toml)
        ]

    for response in answers:
        text = response.text
        assert response.status_code == 422, text
        assert rigs not in text and ".scratch" not in text and "upload-" not in text, text
        assert "set/" in text  # the file at fault, by its path inside the upload

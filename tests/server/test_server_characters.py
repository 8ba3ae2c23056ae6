"""Characters stored beside rigs: the rig's description, the file with its licence rule,
a glTF sent where a rig is expected, and no server path in any error body."""

from __future__ import annotations

import json

import httpx
import pytest
from _server_helpers import folder_members, tiny_example_set, write_example_folder, zip_bytes

from facecast.rig import fit
from facecast.server.settings import Settings
from facecast.server.storage.characters import pack_character
from facecast.server.storage.rig_store import RigStore
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
        no_performer = await http.get("/v1/rigs/face-vrm1@bo/character.glb")

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
    assert no_performer.status_code == 404 and no_performer.json()["code"] == "rig_not_found"


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


# -- PUT /v1/characters/{id}: the real loader on the ICT-FaceKit test avatars -------------


def upload_avatar(variant: str, **kw) -> bytes:
    from tests.rig._avatars import avatar

    return avatar(variant, **kw)


@pytest.mark.parametrize("variant", ["arkit", "vrm0", "vrm1"])
async def test_a_character_file_uploads_as_it_is_and_is_fitted_and_served(
    settings, variant, tmp_path
):
    data = upload_avatar(variant)
    async with run_server(settings) as server, client(server) as http:
        put = await http.put("/v1/characters/ava", content=data)
        described = (await http.get("/v1/rigs/ava")).json()
        served = await http.get("/v1/rigs/ava/character.glb")
        model = await http.get("/v1/rigs/ava/model.glb")

    body = put.json()
    assert put.status_code == 201, body
    pairing = body["pairing"]
    assert "jawOpen" in pairing["paired"] and "eyeBlinkLeft" in pairing["paired"]
    assert pairing["face_mesh"] and pairing["entries"] and pairing["text"][0].startswith("pairing")
    assert body["names"][0] == "neutral" and set(body["names"][1:]) <= set(pairing["paired"])
    assert body["num_points"] == 26  # the generic ARKit source set: 24 landmarks and 2 irises
    fmt = {"arkit": "gltf"}.get(variant, variant)
    assert described["character"]["format"] == fmt
    jaw = described["character"]["bindings"][described["names"].index("jawOpen")]
    assert len({b["mesh"] for b in jaw}) == 2  # the face's and the teeth's morph
    assert served.status_code == 200 and served.content == data  # byte for byte
    assert model.status_code == 200  # the vertex outputs' face mesh, as for any rig
    # What facecast writes and serves passes the Khronos validator.
    from tests.rig.test_character import VRM0_NAME_WARNING, needs_validator, validate

    if needs_validator.args[0]:  # the validator's skip condition
        pytest.skip(needs_validator.kwargs["reason"])
    for name, content in (("character.glb", served.content), ("model.glb", model.content)):
        (tmp_path / name).write_bytes(content)
        issues = validate(tmp_path / name)
        warned = {m["code"] for m in issues["messages"] if m["severity"] == 1}
        allowed = {VRM0_NAME_WARNING} if variant == "vrm0" and name == "character.glb" else set()
        assert issues["numErrors"] == 0 and warned <= allowed, (name, issues["messages"][:5])


async def test_a_vrm_forbidding_redistribution_uploads_and_is_withheld_from_anonymous(settings):
    async with run_server(settings) as server, client(server) as http:
        put = await http.put(
            "/v1/characters/locked", content=upload_avatar("vrm1", redistribution=False)
        )
        served = await http.get("/v1/rigs/locked/character.glb")

    assert put.status_code == 201
    assert put.json()["character"]["meta"]["redistribution"] is False
    assert served.status_code == 403 and served.json()["code"] == "character_not_redistributable"


async def test_a_gltf_folder_uploads_as_a_zip_and_is_stored_as_one_valid_glb(settings, tmp_path):
    from tests.rig.test_character import needs_validator, split, validate

    doc, blob = split(upload_avatar("arkit"))
    view = doc["bufferViews"][doc["images"][0]["bufferView"]]
    png = blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
    doc["buffers"] = [{"byteLength": len(blob), "uri": "avatar.bin"}]
    doc["images"][0] = {"uri": "textures/skin.png"}
    members = {
        "avatar/avatar.gltf": json.dumps(doc).encode(),
        "avatar/avatar.bin": blob,
        "avatar/textures/skin.png": png,
    }
    async with run_server(settings) as server, client(server) as http:
        put = await http.put("/v1/characters/folder", content=zip_bytes(members))
        served = await http.get("/v1/rigs/folder/character.glb")

    assert put.status_code == 201, put.json()
    assert served.content[:4] == b"glTF"
    packed = tmp_path / "served.glb"
    packed.write_bytes(served.content)
    if needs_validator.args[0]:  # the validator's skip condition
        pytest.skip(needs_validator.kwargs["reason"])
    issues = validate(packed)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def _edited(variant: str, edit) -> bytes:
    from tests.rig.test_character import edited

    return edited(variant, edit)


def _bad_inputs() -> dict[str, tuple[bytes, int, str]]:
    from tests.rig.test_character import split

    arkit = upload_avatar("arkit")
    bomb = bytearray(arkit)
    at = bomb.index(b"\x89PNG\r\n\x1a\n")
    bomb[at + 16 : at + 24] = (60000).to_bytes(4, "big") * 2
    doc, _ = split(upload_avatar("neutral_only"))
    doc["buffers"] = [{"byteLength": 64, "uri": "../outside.bin"}]
    outside = zip_bytes({"a/avatar.gltf": json.dumps(doc).encode()})

    def broken_bind(doc):
        doc["extensions"]["VRMC_vrm"]["expressions"]["preset"]["aa"]["morphTargetBinds"][0][
            "index"
        ] = 999

    return {
        "truncated": (arkit[: len(arkit) // 2], 422, "truncated_file"),
        "external uri": (outside, 422, "external_uri"),
        "texture bomb": (bytes(bomb), 422, "texture_too_large"),
        "broken vrm bind": (_edited("vrm1", broken_bind), 422, "bad_vrm_bind"),
        "neutral only": (upload_avatar("neutral_only"), 422, "no_expressions"),
        "not a character": (b"hello there, not a model", 415, "unsupported_character"),
        "bare gltf": (b'{"asset": {"version": "2.0"}}', 415, "gltf_needs_archive"),
        "empty zip": (zip_bytes({"readme.txt": b"hi"}), 422, "no_character_in_archive"),
    }


async def test_bad_character_uploads_are_4xx_with_a_code_and_no_server_path(settings):
    cases = _bad_inputs()
    rigs = str(settings.rigs_dir)
    async with run_server(settings) as server, client(server) as http:
        answers = {
            name: await http.put("/v1/characters/bad", content=body)
            for name, (body, _, _) in cases.items()
        }
        performer = await http.put("/v1/characters/bad@ann", content=upload_avatar("arkit"))
        two = zip_bytes({"a.glb": upload_avatar("arkit"), "b.vrm": upload_avatar("vrm1")})
        several = await http.put("/v1/characters/bad", content=two)
        listed = (await http.get("/v1/rigs")).json()

    assert (performer.status_code, performer.json()["code"]) == (400, "invalid_rig_id")
    assert "performer" in performer.json()["detail"]
    assert (several.status_code, several.json()["code"]) == (422, "several_characters")
    for name, (_, status, code) in cases.items():
        problem = answers[name].json()
        assert (answers[name].status_code, problem["code"]) == (status, code), (name, problem)
        assert rigs not in answers[name].text and "upload-" not in answers[name].text, problem
    assert listed["rigs"] == []  # nothing stored for any of them
    assert "?expressions=transfer" in answers["neutral only"].json()["detail"]
    assert not list(settings.rigs_dir.glob("*.character"))

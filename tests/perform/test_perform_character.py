"""The performer studio shows the rig's character file as uploaded (a test-made VRM 0.x, and
the ICT avatar's VRM 1.0 uploaded through PUT /v1/characters) and poses it through its
bindings when the calibration walk-through shows an expression."""

from __future__ import annotations

import httpx
import pytest

from facecast.rig import fit
from facecast.server.storage.characters import pack_character
from facecast.server.storage.rig_store import RigStore

from ..rig import _avatars as ict_avatars
from ..rig._compressed import compressed, split_glb
from ..viewer._character import build_character
from ..viewer.test_viewer_character import SHOTS, canvas_png, iris, lips, loaded_character, teeth
from ..viewer.test_viewer_pages import pixels
from .conftest import open_page

RIG = "face-vrm0"


@pytest.fixture(scope="module")
def character_rig(rigs_dir) -> str:
    made = build_character("vrm0")
    store = RigStore(rigs_dir)
    store.open()
    try:
        store.put_rig(RIG, fit(made.examples), character=pack_character(made.glb, made.record))
    finally:
        store.close()
    return RIG


def drawn_again(page) -> None:
    """Wait until a draw that began after the last pose (weights) was applied has finished."""
    page.wait_for_function(
        "() => window.facecastStats.poses > 0 && "
        "window.facecastStats.posesDrawn === window.facecastStats.poses"
    )


def test_the_studio_shows_the_character_file_and_poses_its_examples(
    browser, server, character_rig, pages
):
    page = open_page(browser, f"{server}/perform?rig={character_rig}&channel=studio-character")
    pages.append(page)
    page.wait_for_function("window.facecastStats.character !== null")
    page.wait_for_function("window.facecastStats.track === 'tracking'")
    page.click("#calibrate")  # shows the neutral
    drawn_again(page)
    neutral = canvas_png(page)
    page.click('#steps button[data-name="jawOpen"]')
    drawn_again(page)
    jaw = canvas_png(page)
    SHOTS.mkdir(exist_ok=True)
    (SHOTS / "perform-face-vrm0-neutral.png").write_bytes(neutral)
    (SHOTS / "perform-face-vrm0-jaw.png").write_bytes(jaw)
    neutral_px, jaw_px = pixels(neutral), pixels(jaw)

    stats = page.evaluate("window.facecastStats.character")
    assert stats["format"] == "vrm0" and stats["vrm"] is True
    assert lips(neutral_px) > 100 and iris(neutral_px) > 10
    assert teeth(jaw_px).sum() > teeth(neutral_px).sum() + 200
    assert "Facecast Tests" in page.locator("#stage-meta").inner_text()
    assert page.errors == []


# -- an ICT-FaceKit test avatar uploaded as it is (PUT /v1/characters) ----------------------


@pytest.fixture(scope="module")
def ict_rig(server) -> str:
    """The ICT avatar's VRM 1.0 variant uploaded to the package's server as ``ict-vrm1``."""
    ict_avatars.require_ict()
    response = httpx.put(
        f"{server}/v1/characters/ict-vrm1",
        content=ict_avatars.avatar("vrm1"),
        params={"noise": 0.05, "clamp": "unit"},
        timeout=120,
    )
    assert response.status_code == 201, response.text
    return "ict-vrm1"


def test_the_studio_shows_an_uploaded_vrm_through_three_vrm_and_poses_both_meshes(
    browser, server, ict_rig, pages
):
    page = open_page(browser, f"{server}/perform?rig={ict_rig}&channel=studio-ict")
    pages.append(page)
    assert loaded_character(page) == "vrm"
    page.wait_for_function("window.facecastStats.track === 'tracking'")
    page.click("#calibrate")  # shows the neutral
    drawn_again(page)
    neutral_png = canvas_png(page)
    neutral = page.evaluate("window.characterState()")
    page.click('#steps button[data-name="jawOpen"]')
    drawn_again(page)
    jaw_png = canvas_png(page)
    jaw = page.evaluate("window.characterState()")
    SHOTS.mkdir(exist_ok=True)
    (SHOTS / "perform-ict-vrm1-neutral.png").write_bytes(neutral_png)
    (SHOTS / "perform-ict-vrm1-jaw.png").write_bytes(jaw_png)
    neutral_px, jaw_px = pixels(neutral_png), pixels(jaw_png)

    vrm = neutral["vrm"]
    assert vrm["humanoid"] and vrm["lookAt"] and vrm["expressionManager"], vrm
    assert vrm["springBoneManager"] and vrm["springJoints"] >= 2, vrm
    assert neutral["lookAt"]["target"] == "camera"
    # The studio shows the jawOpen example at weight 1: on the face and on the teeth.
    assert jaw["influences"]["face"] == {"jawOpen": pytest.approx(1.0)}
    assert jaw["influences"]["teeth"] == {"jawOpen": pytest.approx(1.0)}
    assert neutral["influences"] == {}
    assert lips(neutral_px) > 100 and iris(neutral_px) > 10
    assert teeth(jaw_px).sum() > teeth(neutral_px).sum() + 200
    assert "ICT test head" in page.locator("#stage-meta").inner_text()
    assert page.errors == []


def test_the_studio_shows_a_draco_compressed_upload_through_facecasts_own_decoder(
    browser, server, pages
):
    # /perform fetches Draco's decoder from /viewer/assets/draco/ as the viewer does.
    ict_avatars.require_ict()
    data = compressed(ict_avatars.avatar("arkit"), "draco")
    response = httpx.put(
        f"{server}/v1/characters/ict-draco",
        content=data,
        params={"noise": 0.05, "clamp": "unit"},
        timeout=120,
    )
    assert response.status_code == 201, response.text
    doc, _ = split_glb(data)
    declared = [
        (mesh["name"], doc["accessors"][mesh["primitives"][0]["attributes"]["POSITION"]]["count"])
        for mesh in doc["meshes"]
    ]

    page = open_page(browser, f"{server}/perform?rig=ict-draco&channel=studio-draco")
    pages.append(page)
    status = loaded_character(page)
    state = page.evaluate("window.characterState()")

    assert status == "gltf", page.evaluate("window.facecastStats.error")
    assert [(m["name"], m["vertices"]) for m in state["meshes"]] == declared
    assert page.errors == []

"""The performer studio shows the rig's character file as uploaded (a VRM 0.x here) and
poses it through its bindings when the calibration walk-through shows an expression."""

from __future__ import annotations

import pytest

from facecast.rig import fit
from facecast.server.storage.characters import pack_character
from facecast.server.storage.rig_store import RigStore

from ..viewer._character import build_character
from ..viewer.test_viewer_character import SHOTS, iris, lips, teeth
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
    stage = page.locator("#stage")
    page.click("#calibrate")  # shows the neutral
    drawn_again(page)
    neutral = stage.screenshot()
    page.click('#steps button[data-name="jawOpen"]')
    drawn_again(page)
    jaw = stage.screenshot()
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

"""Compressed characters in the pages: the ICT test avatar uploaded as meshopt, quantised and
Draco files (made at test time, tests/rig/_compressed.py) renders in a real Chromium through
three.js's own decoders, served by facecast, as its uncompressed twin does.

One server for the module; each file uploaded through ``PUT /v1/characters`` and shown on
``/viewer`` posed by a publisher (neutral, then jaw open). Checked through the page's
``characterState()`` (every mesh decoded with the twin's vertex count, the jaw's morphs
driven) and by pixel against the twin's screenshots.
"""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from facecast.cli.snapshot import serving
from facecast.rig.characters.generic import generic_sources
from facecast.server.pages.viewer import DRACO_ASSETS
from facecast.server.settings import Settings

from ..rig import _avatars as ict_avatars
from ..rig._compressed import GLTFPACK_MISSING, KINDS, compressed, gltfpack
from .test_viewer_character import (
    SHOTS,
    canvas_png,
    loaded_character,
    publishing,
    shown,
)
from .test_viewer_pages import changed_fraction, pixels

BACKGROUND = (0x14, 0x16, 0x1C)


@pytest.fixture(scope="module")
def compressed_server(tmp_path_factory) -> Iterator[str]:
    """A server holding the ICT ``arkit`` avatar as ``twin``, each compressed kind, and (where
    npm's gltfpack is installed) ``gltfpack -cc``'s output."""
    ict_avatars.require_ict()
    twin = ict_avatars.avatar("arkit")
    files = {"twin": twin, **{k: compressed(twin, k) for k in KINDS}}
    if GLTFPACK_MISSING is None:
        files["gltfpack"] = gltfpack(twin)
    settings = Settings(
        rigs_dir=tmp_path_factory.mktemp("compressed-rigs"), access_log=False, log_level="warning"
    )
    with serving(settings) as base_url:
        for rig_id, data in files.items():
            put = httpx.put(
                f"{base_url}/v1/characters/{rig_id}",
                content=data,
                params={"noise": 0.05, "clamp": "unit"},
                timeout=120,
            )
            assert put.status_code == 201, put.text
        yield base_url


def poses() -> np.ndarray:
    generic = generic_sources()
    return np.stack([generic.points[0], generic.source_points("jawOpen")]).astype(np.float32)


def show(page, base_url: str, rig_id: str) -> tuple[dict, np.ndarray, dict]:
    """The page's characterState and canvas at neutral, and its state with the jaw open."""
    with publishing(base_url, f"ch-{rig_id}", rig_id, poses()) as publisher:
        page.set_viewport_size({"width": 640, "height": 420})
        page.goto(f"{base_url}/viewer?rig={rig_id}&channel=ch-{rig_id}")
        status = loaded_character(page)
        assert status == "gltf", (status, page.evaluate("window.facecastStats.error"), page.errors)
        page.wait_for_function("window.facecastStats.state === 'live'", timeout=60_000)
        shown(page, publisher.pose(0))
        png = canvas_png(page)
        neutral = page.evaluate("window.characterState()")
        shown(page, publisher.pose(1))
        jaw = page.evaluate("window.characterState()")
    SHOTS.mkdir(parents=True, exist_ok=True)
    (SHOTS / f"compressed-{rig_id}.png").write_bytes(png)
    return neutral, pixels(png), jaw


@pytest.fixture(scope="module")
def twin_shown(compressed_server, browser) -> tuple[dict, np.ndarray, dict]:
    context = browser.new_context()
    try:
        return show(context.new_page(), compressed_server, "twin")
    finally:
        context.close()


@pytest.mark.parametrize("kind", [*KINDS, "gltfpack"])
def test_the_viewer_renders_a_compressed_character_as_its_uncompressed_twin(
    compressed_server, twin_shown, page, kind
):
    if kind == "gltfpack" and GLTFPACK_MISSING is not None:
        pytest.skip(GLTFPACK_MISSING)
    twin_state, twin_image, _ = twin_shown

    state, image, jaw = show(page, compressed_server, kind)

    # Every mesh decoded, with the vertices the twin has (ICT's face, teeth and eyes;
    # gltfpack names them mesh_0... and keeps every vertex).
    assert [m["vertices"] for m in state["meshes"]] == [m["vertices"] for m in twin_state["meshes"]]
    if kind != "gltfpack":
        assert [m["name"] for m in state["meshes"]] == [m["name"] for m in twin_state["meshes"]]
    assert min(m["vertices"] for m in state["meshes"]) > 1000
    assert state["morphs"] == twin_state["morphs"] == 51 + len(ict_avatars.TEETH_SHAPES)
    face, teeth = (m["name"] for m in state["meshes"][:2])
    assert jaw["influences"][face]["jawOpen"] > 0.5 and jaw["influences"][teeth]["jawOpen"] > 0.5
    # The same picture: a misdecoded mesh (scrambled vertices, a missing dequantisation)
    # would change most of the character's pixels.
    drawn = np.abs(twin_image[..., :3].astype(int) - BACKGROUND).max(axis=-1) > 12
    assert drawn.mean() > 0.05  # the twin itself shows a character
    assert changed_fraction(image, twin_image) < 0.001  # measured: at most 2e-4
    assert page.errors == []


def test_the_draco_decoder_is_served_by_facecast(compressed_server):
    for name, media_type in DRACO_ASSETS.items():
        response = httpx.get(f"{compressed_server}/viewer/assets/draco/{name}")
        assert response.status_code == 200 and response.content, name
        assert response.headers["content-type"] == media_type
    outside = httpx.get(f"{compressed_server}/viewer/assets/draco/draco_encoder.js")
    assert outside.status_code == 404 and outside.json()["code"] == "not_found"

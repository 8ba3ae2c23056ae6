"""The performer studio's HTTP routes on a real server: the page, its script and its model files."""

from __future__ import annotations

import httpx
import pytest

from facecast.cli.snapshot import serving
from facecast.server.pages.perform import PERFORM_ASSETS
from facecast.server.pages.viewer import viewer_dir
from facecast.server.settings import Settings

BUILT = all((viewer_dir() / "dist" / path).is_file() for path, _ in PERFORM_ASSETS.values())
needs_build = pytest.mark.skipif(
    not BUILT, reason="the performer studio is not built (npm run build in client/viewer)"
)


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(
        rigs_dir=tmp_path, auth=True, tokens={"t": frozenset({"viewer"})}, access_log=False
    )


@needs_build
def test_page_loads_without_a_token_and_points_at_its_script(settings):
    with serving(settings) as base_url:
        page = httpx.get(f"{base_url}/perform?channel=x&rig=ict")

    assert page.status_code == 200
    assert 'src="perform/assets/perform.js"' in page.text


@needs_build
@pytest.mark.parametrize(
    ("name", "media_type"),
    [
        ("perform.js", "text/javascript"),
        ("facemesh.json", "application/json"),
        ("facemesh.bin", "application/octet-stream"),
        ("blazeface.bin", "application/octet-stream"),
        ("iris.bin", "application/octet-stream"),
        ("tfjs-backend-wasm-simd.wasm", "application/wasm"),
    ],
)
def test_model_and_webassembly_files_are_served_with_their_media_types(settings, name, media_type):
    with serving(settings) as base_url:
        response = httpx.get(f"{base_url}/perform/assets/{name}")

    expected = (viewer_dir() / "dist" / PERFORM_ASSETS[name][0]).read_bytes()
    assert response.status_code == 200
    assert response.headers["content-type"].startswith(media_type)
    assert response.content == expected


@needs_build
def test_the_model_weights_are_the_npm_package_files_not_urls():
    # The graph model's manifest names weight files that are served here, beside it.
    import json

    for model in ("blazeface", "facemesh", "iris"):
        manifest = json.loads((viewer_dir() / "dist" / "perform" / f"{model}.json").read_text())
        paths = [p for group in manifest["weightsManifest"] for p in group["paths"]]
        assert paths == [f"{model}.bin"]
        assert (viewer_dir() / "dist" / "perform" / f"{model}.bin").stat().st_size > 100_000


@pytest.mark.parametrize("name", ["package.json", "..%2Fperform.html", "%2E%2E", "emotion.json"])
def test_only_the_listed_assets_are_served(settings, name):
    with serving(settings) as base_url:
        response = httpx.get(f"{base_url}/perform/assets/{name}")

    assert (response.status_code, response.json()["code"]) == (404, "not_found")

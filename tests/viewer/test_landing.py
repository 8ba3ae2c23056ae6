"""The landing page at ``/`` and the API docs at ``/docs``, in a real server and Chromium.

The landing page lists the rigs and live channels through the REST API with the page's
``?token=``; ``/docs`` runs Swagger UI from files the server serves itself (offline).
"""

from __future__ import annotations

from urllib.parse import parse_qs, urlsplit

import httpx
import pytest

from facecast.cli.snapshot import serving
from facecast.server.pages.api_docs import DOCS_ASSETS
from facecast.server.pages.landing import LANDING_ASSETS
from facecast.server.pages.viewer import viewer_dir
from facecast.server.settings import Settings

from .conftest import TOKENS
from .test_viewer_pages import FRAMES
from .test_viewer_watch import publishing

BUILT = (viewer_dir() / "dist" / "landing.js").is_file() and all(
    (viewer_dir() / "dist" / "docs" / name).is_file() for name in DOCS_ASSETS
)
needs_build = pytest.mark.skipif(not BUILT, reason="client/viewer is not built (npm run build)")

LOADED = "() => window.facecastLanding && window.facecastLanding.loaded"


@pytest.fixture
def landing_settings(demo_rigs) -> Settings:
    tokens = {**TOKENS, "publisher-token": frozenset({"publisher"})}
    return Settings(
        rigs_dir=demo_rigs, auth=True, tokens=tokens, access_log=False, log_level="warning"
    )


def _row(page, table: str, first_cell: str):
    return page.locator(f"#{table} tbody tr", has=page.locator("td", has_text=first_cell))


@needs_build
def test_landing_lists_rigs_and_live_channels_with_links_that_open(
    landing_settings, page, tmp_path
):
    with serving(landing_settings) as base_url, publishing(base_url, "stage", "publisher-token"):
        page.set_viewport_size({"width": 1000, "height": 640})
        page.goto(f"{base_url}/?token=viewer-token")
        page.wait_for_function(LOADED)
        page.screenshot(path=str(tmp_path / "landing.png"))
        rig_links = {
            a.text_content(): a.get_attribute("href")
            for a in _row(page, "rigs", "demo").locator("a").all()
        }
        channel = _row(page, "channels", "stage")
        live = channel.locator("td").nth(1).text_content()
        viewer_link = channel.locator("a", has_text="viewer")
        href = viewer_link.get_attribute("href")
        docs_href = page.locator("#docs-link").get_attribute("href")
        viewer_link.click()
        page.wait_for_url("**/viewer?**")
        page.wait_for_function(FRAMES, arg=3)
        state = page.evaluate("window.facecastStats.state")

    query = parse_qs(urlsplit(href).query)
    assert (urlsplit(href).path, live) == ("viewer", "live")
    assert query == {"channel": ["stage"], "rig": ["demo"], "token": ["viewer-token"]}
    assert sorted(rig_links) == ["overlay", "perform", "viewer"]
    perform = parse_qs(urlsplit(rig_links["perform"]).query)
    assert perform == {
        "channel": ["stage"],
        "rig": ["demo"],
        "performer": ["performer"],
        "token": ["viewer-token"],
    }
    assert docs_href == "docs?token=viewer-token"
    assert state == "live"
    assert page.errors == []


@needs_build
def test_landing_without_a_token_says_a_token_is_needed(landing_settings, page):
    with serving(landing_settings) as base_url:
        page.goto(f"{base_url}/")
        page.wait_for_function(LOADED)
        error = page.locator("#error").text_content()
        rigs = page.locator("#rigs tbody").text_content()

    assert error == (
        "This server requires a token: open this page as /?token=TOKEN with a token "
        "holding the viewer role (or admin)."
    )
    assert "Not listed" in rigs
    # The refused listings are the page's own message, not a script error.
    assert all("401" in e for e in page.errors)


@needs_build
def test_landing_with_a_token_lacking_the_role_says_which_list_it_may_not_read(
    landing_settings, page
):
    with serving(landing_settings) as base_url:
        page.goto(f"{base_url}/?token=publisher-token")
        page.wait_for_function(LOADED)
        error = page.locator("#error").text_content()

    assert "may not list rigs (403 forbidden)" in error
    assert "may not list channels (403 forbidden)" in error


@needs_build
def test_docs_render_swagger_ui_with_every_request_to_the_server(auth_settings, page, tmp_path):
    requests: list[str] = []
    page.on("request", lambda request: requests.append(request.url))
    with serving(auth_settings) as base_url:
        page.set_viewport_size({"width": 1000, "height": 700})
        page.goto(f"{base_url}/docs?token=viewer-token")
        page.wait_for_selector(".opblock-summary-path")
        paths = page.locator(".opblock-summary-path").all_text_contents()
        page.screenshot(path=str(tmp_path / "docs.png"))

    origin = urlsplit(base_url).netloc
    outside = [u for u in requests if urlsplit(u).scheme != "data" and urlsplit(u).netloc != origin]
    assert outside == []
    assert f"{base_url}/docs/assets/swagger-ui-bundle.js" in requests
    assert {"/v1/rigs", "/v1/channels", "/v1/rigs/{rig_id}/model.glb"} <= {
        p.replace("\u200b", "") for p in paths
    }
    assert page.errors == []


@needs_build
@pytest.mark.parametrize(
    ("prefix", "folder", "names"),
    [("/docs/assets", "docs", DOCS_ASSETS), ("/landing/assets", ".", LANDING_ASSETS)],
)
def test_asset_routes_serve_their_named_files(settings, prefix, folder, names):
    with serving(settings) as base_url:
        responses = {n: httpx.get(f"{base_url}{prefix}/{n}") for n in names}

    for name, response in responses.items():
        assert response.status_code == 200, name
        assert response.headers["content-type"] == names[name]
        assert response.content == (viewer_dir() / "dist" / folder / name).read_bytes()


@pytest.mark.parametrize(
    "path",
    [
        "/docs/assets/swagger-ui-bundle.js.map",
        "/docs/assets/index.html",
        "/docs/assets/swagger-initializer.js",
        "/docs/assets/..%2Fviewer.js",
        "/docs/assets/package.json",
        "/landing/assets/perform.js",
        "/landing/assets/viewer.js",
        "/landing/assets/..%2Findex.html",
        "/landing/assets/main.js",
    ],
)
def test_asset_routes_answer_404_for_any_other_name(settings, path):
    with serving(settings) as base_url:
        response = httpx.get(f"{base_url}{path}")

    assert (response.status_code, response.json()["code"]) == (404, "not_found")


@needs_build
def test_landing_page_is_served_without_a_token_and_keeps_it_out_of_referers(landing_settings):
    with serving(landing_settings) as base_url:
        response = httpx.get(f"{base_url}/")

    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    assert 'src="landing/assets/landing.js"' in response.text
    assert response.headers["referrer-policy"] == "no-referrer"

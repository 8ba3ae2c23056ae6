"""Fixtures of the viewer tests: the built viewer, a demo rig, a real server, a real Chromium.

Skips (with the reason) when Debian's chromium or the viewer's build output is missing;
under CI=true that fails instead (tests/_requires.py): scripts/setup --test builds the
viewer and installs chromium.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from facecast.cli.snapshot import chromium_path, launch, serving, write_demo_rig
from facecast.server.pages.viewer import viewer_dir
from facecast.server.settings import Settings

playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")

TOKENS = {
    "good-token": frozenset({"stream", "viewer"}),
    "viewer-token": frozenset({"viewer"}),
}


def _missing() -> str | None:
    if chromium_path() is None:
        return "no Chromium at /usr/bin/chromium (scripts/setup --test installs it)"
    if not (viewer_dir() / "dist" / "viewer.js").is_file():
        return "the viewer is not built (npm ci && npm run build in client/viewer)"
    return None


@pytest.fixture(scope="session")
def demo_rigs(tmp_path_factory) -> Path:
    """A rig directory holding the demo rig as ``demo``."""
    rigs = tmp_path_factory.mktemp("viewer-rigs")
    write_demo_rig(rigs)
    return rigs


@pytest.fixture
def settings(demo_rigs) -> Settings:
    return Settings(rigs_dir=demo_rigs, access_log=False, log_level="warning")


@pytest.fixture
def auth_settings(demo_rigs) -> Settings:
    return Settings(
        rigs_dir=demo_rigs, auth=True, tokens=TOKENS, access_log=False, log_level="warning"
    )


@pytest.fixture
def server(settings) -> Iterator[str]:
    """Base URL of a real uvicorn serving the app with the viewer mounted."""
    with serving(settings) as base_url:
        yield base_url


# Package scope: sync Playwright keeps an event loop running while it is open, which would
# stop any async test that runs after the viewer tests from starting its own.
@pytest.fixture(scope="package")
def browser():
    reason = _missing()
    if reason is not None:
        pytest.skip(reason)
    with playwright_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            yield browser
        finally:
            browser.close()


class PageErrors(list):
    """Console errors and uncaught exceptions of one page, as text."""


@pytest.fixture
def page(browser):
    """A fresh page (own context) recording its console errors in ``page.errors``."""
    context = browser.new_context(viewport={"width": 480, "height": 360})
    page = context.new_page()
    errors = PageErrors()
    page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
    page.on(
        "console",
        lambda msg: errors.append(f"console: {msg.text}") if msg.type == "error" else None,
    )
    page.errors = errors
    page.set_default_timeout(20_000)
    try:
        yield page
    finally:
        context.close()

"""The web viewer and overlay in a real headless Chromium against a real server.

Each test waits on ``window.facecastStats`` (the page's own counters), never on time.
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from facecast.cli.snapshot import serving

FRAMES = "n => window.facecastStats.frames > n"


def pixels(png: bytes) -> np.ndarray:
    """(H, W, 4) uint8 RGBA of a screenshot."""
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


def changed_fraction(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels whose colour differs by more than 8 levels in some channel."""
    return float((np.abs(a.astype(int) - b.astype(int)).max(axis=-1) > 8).mean())


def frames(page) -> int:
    return page.evaluate("window.facecastStats.frames")


def test_viewer_animates_the_demo_with_no_console_errors(server, page):
    page.goto(f"{server}/viewer?rig=demo")
    page.wait_for_function(FRAMES, arg=5)
    hud = page.locator("#hud")
    first = pixels(page.screenshot(mask=[hud]))
    # The performance has quiet moments: look again every 15 frames, for up to 2 s of it.
    changes = []
    for _ in range(8):
        page.wait_for_function(FRAMES, arg=frames(page) + 15)
        changes.append(changed_fraction(first, pixels(page.screenshot(mask=[hud]))))
        if changes[-1] > 0.002:
            break

    assert max(changes) > 0.002, changes
    assert page.evaluate("window.facecastStats.state") == "live"
    assert page.locator("#state").inner_text().startswith("live")
    assert page.errors == []


def test_overlay_background_is_transparent_around_the_character(server, page):
    page.set_viewport_size({"width": 320, "height": 240})
    page.goto(f"{server}/overlay?rig=demo&width=320&height=240")
    page.wait_for_function(FRAMES, arg=3)

    image = pixels(page.screenshot(omit_background=True))

    assert image.shape[:2] == (240, 320)
    corners = image[[0, 0, -1, -1], [0, -1, 0, -1], 3]
    assert corners.tolist() == [0, 0, 0, 0]
    assert image[120, 160, 3] == 255  # the face is opaque in the middle
    assert page.locator("#hud").is_hidden()
    assert page.errors == []


def test_vertices_mode_with_f16_results_animates(server, page):
    page.goto(f"{server}/overlay?rig=demo&output=vertices&dtype=f16")
    page.wait_for_function(FRAMES, arg=3)
    first = pixels(page.screenshot(omit_background=True))
    page.wait_for_function(FRAMES, arg=frames(page) + 10)
    second = pixels(page.screenshot(omit_background=True))

    assert changed_fraction(first, second) > 0.002
    assert page.errors == []


def test_moving_vertices_mode_with_f16_results_animates(server, page):
    page.goto(f"{server}/overlay?rig=demo&output=moving&dtype=f16")
    page.wait_for_function(FRAMES, arg=3)
    first = pixels(page.screenshot(omit_background=True))
    page.wait_for_function(FRAMES, arg=frames(page) + 10)
    second = pixels(page.screenshot(omit_background=True))

    assert changed_fraction(first, second) > 0.002
    assert page.errors == []


def test_viewer_reconnects_after_the_server_restarts_on_the_same_port(settings, page):
    with serving(settings) as base_url:
        page.goto(f"{base_url}/viewer?rig=demo")
        page.wait_for_function(FRAMES, arg=3)
    page.wait_for_function("window.facecastStats.state === 'waiting'")
    before = frames(page)
    assert page.locator("#state").inner_text() == "reconnecting"

    port = int(base_url.rsplit(":", 1)[1])
    with serving(settings, port=port):
        page.wait_for_function(FRAMES, arg=before + 10)
        stats = page.evaluate("window.facecastStats")

    assert stats["connects"] >= 2
    assert stats["state"] == "live"


def test_wrong_token_shows_an_authentication_error_on_the_page(auth_settings, page):
    with serving(auth_settings) as base_url:
        page.goto(f"{base_url}/viewer?rig=demo&token=wrong-token")
        error = page.locator("#error")
        error.wait_for(state="visible")
        text = error.inner_text()

    assert "Authentication failed" in text
    assert "unknown API token" in text
    assert page.evaluate("window.facecastStats.state") == "failed"
    assert page.evaluate("window.facecastStats.frames") == 0


def test_token_without_stream_role_shows_the_websocket_refusal(auth_settings, page):
    # The model loads (viewer role), the demo stream is refused (needs stream): the
    # refusal arrives as a protocol error over the WebSocket and must reach the page.
    with serving(auth_settings) as base_url:
        page.goto(f"{base_url}/viewer?rig=demo&token=viewer-token")
        error = page.locator("#error")
        error.wait_for(state="visible")
        text = error.inner_text()

    assert text.startswith("Not allowed (FORBIDDEN)")
    assert page.evaluate("window.facecastStats.connects") == 1


def test_right_token_streams_through_an_authenticated_server(auth_settings, page):
    with serving(auth_settings) as base_url:
        page.goto(f"{base_url}/viewer?rig=demo&token=good-token")
        page.wait_for_function(FRAMES, arg=3)
        state = page.evaluate("window.facecastStats.state")

    assert state == "live"
    assert page.errors == []


def test_bad_page_parameter_is_explained_on_the_page(server, page):
    page.goto(f"{server}/viewer?rig=demo&output=mesh")

    error = page.locator("#error")
    error.wait_for(state="visible")

    assert "output must be weights, vertices or moving" in error.inner_text()

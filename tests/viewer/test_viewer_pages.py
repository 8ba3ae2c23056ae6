"""The web viewer and overlay in a real headless Chromium against a real server.

Each test waits on ``window.facecastStats`` (the page's own counters) or
``window.facecastApplied()`` (the result the mesh was last posed with), never on time.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from facecast.cli.snapshot import serving
from facecast.rig import load_rig
from facecast.rig.demo import demo_animation

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


#: The newest applied result, once its seq passes n: one snapshot, read in one task of the
#: page (the seq, the frame it answers and the mesh it posed belong together).
APPLIED_AFTER = """n => {
  const applied = window.facecastApplied();
  return applied !== null && applied.seq > n ? applied : null;
}"""
#: Mantissa bits and smallest normal exponent of the wire's float types (IEEE 754).
FLOAT_BITS = {"f16": (10, -14), "f32": (23, -126)}
#: How far Python's evaluation of the rig may stray from the server's before rounding to
#: the wire, as a share of the largest value: the same code, but the server may blend
#: several frames in one product (summed in another order). 32 float32 epsilons; measured
#: 0 (f32 vertices came out bit for bit equal).
RECOMPUTE = 32 * 2.0**-23


def rounding_bound(values: np.ndarray, dtype: str) -> np.ndarray:
    """Largest error of rounding each value to ``dtype`` (to nearest): half a unit in the
    last place, 2**(e - bits - 1) for |x| in [2**e, 2**(e + 1)); 2**(e_min - bits - 1) below
    the smallest normal (subnormals). For f16 that is 1/2048 of the value at most."""
    bits, e_min = FLOAT_BITS[dtype]
    magnitude = np.maximum(np.abs(values), 2.0**e_min)
    return np.exp2(np.floor(np.log2(magnitude)) - bits - 1)


def within_wire_rounding(shown: np.ndarray, truth: np.ndarray, dtype: str) -> np.ndarray:
    """Where ``shown`` (the page's) lies within ``truth`` (Python's) rounded to ``dtype``.

    The server rounds each value to the wire's dtype once (f16: nearest binary16) and the
    page widens it to float32 exactly, so the page may be off by the rounding bound and
    the recomputation slack, no more. Measured on the demo rig (coordinates up to 11.0):
    f16 vertices 0.0039 at most, 0.0486 % of the value against the bound's 0.0488 %; f32
    vertices 0; f32 weights 1.7e-8 (float64 weights rounded to float32).
    """
    slack = RECOMPUTE * np.abs(truth).max()
    bound = rounding_bound(np.abs(truth) + slack, dtype) + slack
    return np.abs(shown - truth) <= bound


@pytest.fixture(scope="module")
def demo_truth(demo_rigs):
    """The rig the test's server holds and the demo performance's (F, K, 3) points as the
    page sends them (float32, as GET /v1/demo/animation serves them), evaluated in Python."""
    return load_rig(demo_rigs / "demo.rig"), demo_animation(with_vertices=False).points.astype(
        np.float32
    )


# Every output the page can pose the rig's mesh with, and both wire dtypes (f16's decode
# is the page's own, halfToFloat). The performance from 1 s on (start=1): its face is well
# away from the neutral there, so a page that applied nothing cannot pass.
@pytest.mark.parametrize(
    ("output", "dtype"),
    [("vertices", "f16"), ("vertices", "f32"), ("moving", "f16"), ("weights", "f32")],
)
def test_page_poses_the_mesh_as_the_rig_evaluates_the_frame_it_sent(
    server, page, demo_truth, output, dtype
):
    rig, points = demo_truth
    page.goto(f"{server}/overlay?rig=demo&output={output}&dtype={dtype}&start=1")
    first = page.wait_for_function(APPLIED_AFTER, arg=2).json_value()
    first_png = pixels(page.screenshot(omit_background=True))
    second = page.wait_for_function(APPLIED_AFTER, arg=first["seq"] + 10).json_value()
    second_png = pixels(page.screenshot(omit_background=True))

    neutral = rig.blend(np.eye(rig.num_examples)[0])
    for applied in (first, second):
        weights = rig.weights(points[applied["frame"]])
        if output == "weights":
            # The morph targets by name: model.glb leaves out the neutral (the rig's first
            # weight: it moves nothing). The mesh's own positions stay the neutral's.
            names = list(applied["influences"])
            assert sorted(names) == sorted(rig.names[1:])
            shown = np.array([applied["influences"][name] for name in names])
            truth = weights[[rig.names.index(name) for name in names]]
            moved = np.abs(truth).max()
            assert np.array_equal(np.array(applied["positions"]).reshape(-1, 3), neutral)
        else:
            # The whole mesh: a moving result's vertices go where rig.moving_vertices says,
            # every other vertex keeps the neutral's position.
            shown = np.array(applied["positions"]).reshape(-1, 3)
            truth = rig.blend(weights)
            moved = np.abs(truth - neutral).max()
        close = within_wire_rounding(shown, truth, dtype)
        assert close.all(), (applied["seq"], np.argwhere(~close)[:5], np.abs(shown - truth).max())
        assert moved > 100 * rounding_bound(np.abs(truth).max(), dtype)
    assert second["frame"] != first["frame"]
    assert changed_fraction(first_png, second_png) > 0.002
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

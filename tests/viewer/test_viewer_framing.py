"""How the overlay frames characters and how the viewer lays out its weight bars, in Chromium.

The character's box (its opaque pixels on the overlay's transparent background) must fill
50-90 % of the view's shorter side and sit in the middle, for the demo character and the
ICT-FaceKit face ``facecast import ict-facekit`` makes, landscape and portrait; the weight
bars must stay clear of their labels whatever the names.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from facecast.cli.snapshot import serving, write_demo_rig
from facecast.rig import fit
from facecast.rig.demo import demo_example_set
from facecast.rig.sources.ict import DEFAULT_LANDMARKS, locate_ict
from facecast.server.settings import Settings

from .test_viewer_pages import pixels

SIZES = [(640, 480), (1280, 720), (480, 854)]
ARCHIVE = locate_ict()
needs_ict = [
    pytest.mark.ict,
    pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found ($FACECAST_ICT)"),
]
# Long enough to overflow any fixed label column; the first is cut with an ellipsis.
LONG_NAMES = (
    "neutral", "mouthStretchLeftAndThenSome", "browInnerUp", "eyeLookDownRight", "jawOpen",
    "mouthRollLower", "cheekSquintLeft", "noseSneerRight", "mouthPressLeft", "eyeWideRight",
    "mouthSmileLeft", "mouthFrownRight", "eyeBlinkLeft",
)  # fmt: skip


@pytest.fixture(scope="module")
def framing_rigs(tmp_path_factory) -> Path:
    """``demo``, ``long`` (the demo with long names) and, with the data, ``ict``."""
    rigs = tmp_path_factory.mktemp("framing-rigs")
    write_demo_rig(rigs)
    fit(dataclasses.replace(demo_example_set(), names=LONG_NAMES)).save(rigs / "long.rig")
    if ARCHIVE is not None:
        from facecast.cli.commands.import_ import arkit_example_set

        example_set, _ = arkit_example_set(ARCHIVE, DEFAULT_LANDMARKS, "face")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exact ICT rig's noise-gain warning
            fit(example_set).save(rigs / "ict.rig")
    return rigs


@pytest.fixture(scope="module")
def framing_server(framing_rigs):
    settings = Settings(rigs_dir=framing_rigs, access_log=False, log_level="warning")
    with serving(settings) as base_url:
        yield base_url


def character_box(image: np.ndarray) -> tuple[float, float]:
    """(fill, offset): the opaque box's larger side and its centre's distance from the
    view's centre, both over the view's shorter side."""
    height, width = image.shape[:2]
    rows, cols = np.nonzero(image[:, :, 3] > 0)
    assert rows.size, "nothing drawn"
    shorter = min(width, height)
    fill = max(cols.max() - cols.min() + 1, rows.max() - rows.min() + 1) / shorter
    centre = np.array([(cols.min() + cols.max()) / 2, (rows.min() + rows.max()) / 2])
    offset = float(np.linalg.norm(centre - [(width - 1) / 2, (height - 1) / 2])) / shorter
    return fill, offset


def _open_overlay(page, base_url: str, rig: str) -> None:
    if rig == "demo":
        page.goto(f"{base_url}/overlay?rig=demo")
        page.wait_for_function("window.facecastStats.frames > 3")
    else:  # a channel nobody publishes to: the neutral face, drawn once loaded
        page.goto(f"{base_url}/overlay?channel=show&rig={rig}")
        page.wait_for_function("window.facecastStats.state === 'idle'")


def _assert_framed(page) -> None:
    fill, offset = character_box(pixels(page.screenshot(omit_background=True)))
    assert 0.5 <= fill <= 0.9, fill
    assert offset <= 0.05, offset


@pytest.mark.parametrize(
    "rig", ["demo", pytest.param("ict", marks=needs_ict)], ids=["demo", "ict-import"]
)
@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_overlay_frames_the_character_in_the_middle(framing_server, page, rig, size):
    page.set_viewport_size({"width": size[0], "height": size[1]})

    _open_overlay(page, framing_server, rig)

    _assert_framed(page)
    assert page.errors == []


@pytest.mark.parametrize(
    "rig", ["demo", pytest.param("ict", marks=needs_ict)], ids=["demo", "ict-import"]
)
def test_overlay_frames_the_character_again_when_the_window_changes_shape(
    framing_server, page, rig
):
    page.set_viewport_size({"width": 1280, "height": 720})
    _open_overlay(page, framing_server, rig)
    drawn = page.evaluate("window.facecastStats.rendered")

    page.set_viewport_size({"width": 480, "height": 854})
    page.wait_for_function("n => window.facecastStats.rendered > n", arg=drawn)

    _assert_framed(page)


BAR_LAYOUT = """() => Array.from(document.querySelectorAll('#weights .weight')).map((row) => {
  const [label, track] = row.children;
  const bar = track.firstElementChild;
  const style = getComputedStyle(label);
  return {
    name: label.textContent,
    clipped: style.overflow === 'hidden' && style.textOverflow === 'ellipsis',
    overflows: label.scrollWidth > label.clientWidth,
    labelRight: label.getBoundingClientRect().right,
    barLeft: bar.getBoundingClientRect().left,
    barRight: bar.getBoundingClientRect().right,
    barWidth: bar.getBoundingClientRect().width,
    rowRight: row.getBoundingClientRect().right,
  };
})"""


def test_weight_bars_stay_clear_of_their_labels(framing_server, page):
    page.set_viewport_size({"width": 960, "height": 600})
    page.goto(f"{framing_server}/viewer?rig=long")
    # Bars are painted at most ~15 times a second: wait until some bar has a width.
    page.wait_for_function(
        "Array.from(document.querySelectorAll('#weights i')).some(b => b.offsetWidth > 0)"
    )

    rows = page.evaluate(BAR_LAYOUT)

    assert [row["name"] for row in rows] == list(LONG_NAMES)
    for row in rows:
        # A name wider than its column is cut there (with "…"), never drawn under the bar.
        assert row["clipped"] or not row["overflows"], row
        assert row["barLeft"] >= row["labelRight"], row
        assert row["barRight"] <= row["rowRight"] + 0.5, row
    assert any(row["barWidth"] > 0 for row in rows)
    # Short names are not cut at all.
    assert not next(row for row in rows if row["name"] == "jawOpen")["overflows"]
    assert page.errors == []

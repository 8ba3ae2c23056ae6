"""What paces /perform's tracking: the camera's frames, taken as they come, never the page's
drawing of the character, which stays within its share of the page's time.

Not a speed test (the rate is the benchmark's, tests/perform/bench_perform.py): these
assert the rules that give the rate, from the page's own counters.
"""

from __future__ import annotations

import shutil

from .conftest import CHARACTER, FacePose, open_page

#: main.js's DRAW_SHARE: the character's draws may block the page this much of the time.
DRAW_SHARE = 0.1

CLOCK = "[window.facecastStats.drawn, window.facecastStats.drawCostMs, performance.now()]"


def test_frames_come_from_the_track_and_the_character_is_drawn_within_its_budget(
    browser, server, rigs_dir, camera, pages
):
    camera.show([FacePose()] * 10 + [FacePose(mouth=12.0)] * 10)
    rig = f"{CHARACTER}@rate"  # a performer's own rig: results come back and are drawn
    shutil.copy(rigs_dir / f"{CHARACTER}.rig", rigs_dir / f"{rig}.rig")
    page = open_page(browser, f"{server}/perform?channel=rate&rig={rig}")
    pages.append(page)
    page.wait_for_function("window.facecastStats.results >= 5", timeout=120_000)
    drawn_before, _, t_before = page.evaluate(CLOCK)
    assert isinstance(drawn_before, int), "the page does not count its draws of the character"
    page.wait_for_function(
        f"window.facecastStats.drawn >= {drawn_before + 2} "
        "&& window.facecastStats.drawCostMs !== null",
        timeout=120_000,
    )
    drawn_after, cost_ms, t_after = page.evaluate(CLOCK)
    stats = page.evaluate("window.facecastStats")

    assert stats["frameSource"] == "processor"  # MediaStreamTrackProcessor, not frame callbacks
    assert stats["error"] is None and page.errors == []
    # A draw of cost c is followed by none for c / DRAW_SHARE, so the draws in a window
    # block the page at most DRAW_SHARE of it (the mean cost is over earlier draws too:
    # twice the share as slack; drawn after every frame, they blocked most of it).
    draws = drawn_after - drawn_before
    assert (draws - 1) * cost_ms <= 2 * DRAW_SHARE * (t_after - t_before)
    assert stats["tracked"] > stats["drawn"]

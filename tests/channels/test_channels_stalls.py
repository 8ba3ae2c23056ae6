"""The loop's stall clock: which time a publisher's silence counts (sans-I/O, then on a loop)."""

from __future__ import annotations

import asyncio
import time

import pytest

from facecast.server.channels.stalls import StallClock, tick_forever


def _ticked(times: list[float]) -> StallClock:
    clock = StallClock(times[0], interval=0.05, slack=0.05)
    for now in times[1:]:
        clock.tick(now)
    return clock


def test_ticks_on_time_or_a_little_late_are_all_running_time():
    clock = _ticked([0.0, 0.05, 0.10, 0.19, 0.24])  # 0.04 late once: within the slack

    assert clock.running(0.0, 0.24) == pytest.approx(0.24)


def test_a_late_tick_takes_the_time_from_when_it_was_due_for_a_stall():
    clock = _ticked([0.0, 0.05, 1.55, 1.60])  # due at 0.10, ran at 1.55

    assert clock.stalled(0.0, 1.60) == pytest.approx(1.45)
    assert clock.running(0.0, 1.60) == pytest.approx(0.15)
    # Only the part of a stall inside the span counts.
    assert clock.stalled(1.0, 1.60) == pytest.approx(0.55)
    assert clock.running(1.55, 1.60) == pytest.approx(0.05)


def test_a_stall_not_yet_ticked_counts_already():
    # The loop is back, and what runs first (a bus evict) asks before the ticker ran.
    clock = _ticked([0.0, 0.05])

    assert clock.stalled(0.0, 1.55) == pytest.approx(1.45)  # due at 0.10
    assert clock.running(0.0, 0.12) == pytest.approx(0.12)  # 0.02 late: not a stall yet


@pytest.mark.anyio
async def test_a_loop_blocked_for_a_second_is_not_running_time():
    clock = StallClock(time.monotonic())
    ticker = asyncio.create_task(tick_forever(clock))
    try:
        await asyncio.sleep(0.2)
        since = time.monotonic()
        time.sleep(1.0)  # the loop is held: the ticker cannot run
        ran = clock.running(since, time.monotonic())
    finally:
        ticker.cancel()

    # At most the wait before the ticker was due (its interval) and its slack count.
    assert ran <= clock.interval + clock.slack

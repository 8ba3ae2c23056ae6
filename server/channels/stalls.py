"""The stalls of this process's event loop, so that a client's silence does not count them.

While the loop does not run (GC, a starved CPU, swapping, the process stopped) every
socket's bytes wait unread: a publisher that sends on looks silent. `StallClock` is
sans-I/O (told its ticks, asked about a span of time); `tick_forever` drives it.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque

__all__ = ["STALL_SLACK", "TICK_INTERVAL", "StallClock", "tick_forever"]

#: How often the loop's ticker wakes.
TICK_INTERVAL = 0.05
#: A tick later than due by more than this was held back by a stall of the loop: the time
#: from when it was due to when it ran did not run the loop. A busy loop's lateness
#: (callbacks of a few ms, the timer's resolution) stays well within it.
STALL_SLACK = 0.05
#: Stalls remembered, the oldest forgotten first: a span older than these counts its
#: earlier stalls as running time (as every span did before there was a clock).
MAX_STALLS = 64


class StallClock:
    """The spans of time the loop did not run, from the lateness of a ticker.

    ``tick(now)`` is called by a task sleeping ``interval`` between calls; a call later
    than ``interval + slack`` after the previous one records a stall from when it was due
    to ``now``. ``running(since, now)`` is the time in between minus the stalls in it, the
    one still going at ``now`` (no tick yet since the loop came back) included.
    A stall is estimated short by at most ``interval`` (where in the late tick's wait the
    loop stopped is not known), or missed when no longer than ``interval + slack``.
    """

    def __init__(
        self, now: float, *, interval: float = TICK_INTERVAL, slack: float = STALL_SLACK
    ) -> None:
        if interval <= 0 or slack < 0:
            raise ValueError(f"expected interval > 0 and slack >= 0, got {interval}, {slack}")
        self.interval = interval
        self.slack = slack
        self._last_tick = now
        #: (start, end) of each stall seen, oldest first.
        self._stalls: deque[tuple[float, float]] = deque(maxlen=MAX_STALLS)

    def tick(self, now: float) -> None:
        """The ticker ran at ``now``."""
        stall = self._late(now)
        if stall is not None:
            self._stalls.append(stall)
        self._last_tick = now

    def stalled(self, since: float, now: float) -> float:
        """Seconds of ``[since, now]`` the loop did not run."""
        spans = list(self._stalls)
        late = self._late(now)
        if late is not None:
            spans.append(late)
        return sum(max(0.0, min(end, now) - max(start, since)) for start, end in spans)

    def running(self, since: float, now: float) -> float:
        """Seconds of ``[since, now]`` the loop ran: ``now - since`` less its stalls."""
        return max(0.0, now - since - self.stalled(since, now))

    def _late(self, now: float) -> tuple[float, float] | None:
        due = self._last_tick + self.interval
        return (due, now) if now - due > self.slack else None


async def tick_forever(clock: StallClock) -> None:
    """Tick ``clock`` every ``clock.interval`` on the running loop (``time.monotonic``)."""
    while True:
        await asyncio.sleep(clock.interval)
        clock.tick(time.monotonic())

"""A connection's frame rate limit: which frames pass, and telling the client how many did not.

One rule for ``/v1/stream`` sessions and channel publishers (PROTOCOL.md §8): a frame
over ``max_fps`` (beyond ``rate_burst``) is discarded and counted; the client gets a
RATE_LIMITED error at most once per ``ERROR_INTERVAL``, carrying the total of discarded
frames. Frames discarded after the last total the client was sent (in a result or an
error) are reported when the interval is over, so a burst's tail is never lost without
a trace. No I/O here: the caller says how to send the error and what the total is.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable

from facecast.protocol import Error, ErrorCode

from .ratelimit import TokenBucket

__all__ = ["ERROR_INTERVAL", "FrameRateLimit"]

#: A client over its rate gets at most one RATE_LIMITED error per this many seconds.
ERROR_INTERVAL = 1.0


class FrameRateLimit:
    """The token bucket of one connection, and the RATE_LIMITED errors it owes the client.

    Parameters
    ----------
    max_fps, burst : the bucket's refill rate and depth
    total : the connection's dropped total now (what ``result.dropped`` would say)
    tell : queues an `Error` for the client
    """

    def __init__(
        self,
        max_fps: float,
        burst: int,
        *,
        total: Callable[[], int],
        tell: Callable[[Error], None],
    ) -> None:
        self.max_fps = max_fps
        self._bucket = TokenBucket(max_fps, burst)
        self._total = total
        self._tell = tell
        self._loop = asyncio.get_running_loop()
        self._told = 0
        self._last_error = -math.inf
        self._last_seq = 0
        self._late: asyncio.TimerHandle | None = None

    def allow(self) -> bool:
        """Whether the next frame is within the rate (takes a token if so)."""
        return self._bucket.take()

    def discarded(self, seq: int) -> None:
        """Frame ``seq`` was over the rate and the caller has counted it in its total."""
        self._last_seq = seq
        now = self._loop.time()
        if now - self._last_error >= ERROR_INTERVAL:
            self._send(now)
        elif self._late is None:
            self._late = self._loop.call_at(self._last_error + ERROR_INTERVAL, self._report_late)

    def told(self, dropped: int) -> None:
        """The client is sent ``dropped`` as its total (a result carries it)."""
        self._told = max(self._told, dropped)

    def close(self) -> None:
        if self._late is not None:
            self._late.cancel()
            self._late = None

    def _report_late(self) -> None:
        self._late = None
        if self._total() > self._told:
            self._send(self._loop.time())

    def _send(self, now: float) -> None:
        self._last_error = now
        total = self._total()
        self._told = max(self._told, total)
        self._tell(
            Error(
                code=ErrorCode.RATE_LIMITED,
                message=f"more than {self.max_fps:g} frames/s; frames over the rate are "
                f"discarded ({total} so far, in dropped)",
                seq=self._last_seq,
                dropped=total,
            )
        )

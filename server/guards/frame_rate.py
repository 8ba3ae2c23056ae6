"""A connection's frame rate limit: which frames pass, and telling the client how many did not.

One rule for ``/v1/stream`` sessions and channel publishers (PROTOCOL.md §8): a frame
over ``max_fps`` (beyond ``rate_burst``) is discarded and counted; the client gets a
RATE_LIMITED error at most once per ``ERROR_INTERVAL``, carrying the total of discarded
frames. Frames discarded after the last total the client was sent (in a result or an
error) are reported when the interval is over, so a burst's tail is never lost without
a trace. Sans-I/O: the caller passes the clock in, sends the errors it is handed, and
calls ``due`` at the ``deadline`` it is told; no timer here.
"""

from __future__ import annotations

import math

from facecast.protocol import Error, ErrorCode

from .token_bucket import TokenBucket

__all__ = ["ERROR_INTERVAL", "FrameRateLimit"]

#: A client over its rate gets at most one RATE_LIMITED error per this many seconds.
ERROR_INTERVAL = 1.0


class FrameRateLimit:
    """The token bucket of one connection, and the RATE_LIMITED errors it owes the client.

    Parameters
    ----------
    max_fps, burst : the bucket's refill rate and depth
    now : the clock (``time.monotonic()``) at the start
    """

    def __init__(self, max_fps: float, burst: int, now: float) -> None:
        self.max_fps = max_fps
        self._bucket = TokenBucket(max_fps, burst, now)
        self._told = 0
        self._last_error = -math.inf
        self._last_seq = 0
        #: When the errors owed for frames discarded since the last one are due, or None.
        self.deadline: float | None = None

    def allow(self, now: float) -> bool:
        """Whether the next frame is within the rate (takes a token if so)."""
        return self._bucket.take(now)

    def discarded(self, seq: int, now: float, total: int) -> Error | None:
        """Frame ``seq`` was over the rate; ``total`` counts it. The error to send now, if any."""
        self._last_seq = seq
        if now - self._last_error >= ERROR_INTERVAL:
            return self._error(now, total)
        if self.deadline is None:
            self.deadline = self._last_error + ERROR_INTERVAL
        return None

    def due(self, now: float, total: int) -> Error | None:
        """At or after ``deadline``: the error reporting frames not yet told, if any."""
        if self.deadline is None or now < self.deadline:
            return None
        self.deadline = None
        return self._error(now, total) if total > self._told else None

    def told(self, dropped: int) -> None:
        """The client is sent ``dropped`` as its total (a result carries it)."""
        self._told = max(self._told, dropped)

    def _error(self, now: float, total: int) -> Error:
        self._last_error = now
        self._told = max(self._told, total)
        return Error(
            code=ErrorCode.RATE_LIMITED,
            message=f"more than {self.max_fps:g} frames/s; frames over the rate are "
            f"discarded ({total} so far, in dropped)",
            seq=self._last_seq,
            dropped=total,
        )

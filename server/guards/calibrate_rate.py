"""A connection's calibration budget: how many ``calibrate`` messages may refit its rig.

A calibration refits the rig's projection (about a millisecond of CPU for ICT, tens of
frames' worth, and on a channel once more for every watched rig), so it has a budget of
its own beside ``max_fps`` (PROTOCOL.md §5.1.3): ``calibrate_rate`` per second on
average, ``calibrate_burst`` at once. A ``calibrate`` over it is refused with a non-fatal
RATE_LIMITED without a ``seq`` and changes nothing; ``reset`` costs no fit and is always
allowed. Sans-I/O: the caller passes the clock in and sends the error it is handed.
"""

from __future__ import annotations

from facecast.protocol import ErrorCode, ProtocolError

from .token_bucket import TokenBucket

__all__ = ["CalibrateRateLimit"]


class CalibrateRateLimit:
    """The token bucket of one connection's calibrations.

    Parameters
    ----------
    rate, burst : calibrations per second (the refill rate) and at once (the depth)
    now : the clock (``time.monotonic()``) at the start
    """

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.refused = 0
        self._bucket = TokenBucket(rate, burst, now)

    def refusal(self, now: float) -> ProtocolError | None:
        """None if a calibration may start at ``now`` (a token is taken), else the error."""
        if self._bucket.take(now):
            return None
        self.refused += 1
        return ProtocolError(
            ErrorCode.RATE_LIMITED,
            f"calibrate refused: more than {self.rate:g} calibrations/s "
            f"({self.refused} refused so far); the neutral is unchanged",
        )

"""How much memory a call holds at its peak, for the tests that bound it."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable


def traced_peak(call: Callable[[], object]) -> int:
    """The most bytes numpy and Python hold at once during ``call()`` (tracemalloc's peak)."""
    tracemalloc.start()
    try:
        call()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()

"""Large blocks the server frees go back to the system at once (glibc's mmap threshold).

glibc maps a block of at least its mmap threshold on its own and unmaps it when freed, but
raises the threshold (up to 32 MiB) to the largest such block freed: after one large
upload the next one's arrays of a few MB come from a thread's heap, which keeps them when
freed. A 500,000-vertex face's read left 12 MB so, beside the fit's arrays at the upload's
peak (SERVER.md "What an upload can cost the server"). Fixing the threshold stops that.
Nothing here knows what is allocated.

It costs the frame path: `facecast bench transport --duration 3 --max-streams 60`, two
pairs run in turn (2026-12-04 15:15 UTC, 2-core VM), 20 clients of the ICT rig's vertices:
latency p50 7.2 / 8.4 ms and p99 32 / 29 ms with it, 3.1 / 5.9 and 12 / 18 without; the
round trip's ratio to bare websockets 1.16 / 1.23 against 1.14 / 1.18. Fixing the
threshold also stops glibc's dynamic trim threshold (a likely cause, not measured apart).
Without it the upload memory test measured +214 MB once (over its 3.25x bound). Open:
issue 31.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["MMAP_THRESHOLD", "fix_mmap_threshold"]

#: Blocks of this size or more are mapped on their own, and unmapped when freed. Below it
#: (the frame path's buffers: a 26,719-vertex ICT result is 320 kB) blocks come from the
#: heaps as before, though the heaps are trimmed sooner (above); above, each block costs its page faults anew (an ICT character's upload and fit: ~2,400
#: more, ~10 MB of fresh pages; a float32 vertices frame of a rig over ~350,000 vertices
#: would pay them every frame).
MMAP_THRESHOLD = 4 << 20
#: mallopt's parameter number for it (malloc.h).
_M_MMAP_THRESHOLD = -3


def fix_mmap_threshold(size: int = MMAP_THRESHOLD) -> bool:
    """Set glibc's mmap threshold to ``size`` for the whole process, which also stops its
    dynamic growth; whether the C library took it (False without glibc: musl, macOS)."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, size))

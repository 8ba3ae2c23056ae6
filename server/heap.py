"""glibc's malloc set for the two kinds of work a server does: frames, and uploads' parses
and fits. Nothing here knows what is allocated; on another C library it does nothing.

Frames (the serving mode): blocks under 16 MiB come from the heaps and are used again, and a
heap keeps up to 32 MiB free at its top. The frame path makes blocks of several MB per
batch (ICT's: a (B, V, 3) blend scratch of 6-10 MB, a 5 MB product, a 14 MB gathered
basis); mapped anew each time, they are page faults and fresh zeroed pages every batch.

Uploads (while any ``upload()`` scope is open: every fit slot, every transfer job): blocks
of 4 MiB or more are mapped on their own and unmapped when freed, and a heap keeps at most
128 kB at its top, so an upload's large arrays go back to the system when freed instead of
staying in a thread's heap beside the fit's (SERVER.md "What an upload can cost the
server"). mallopt is process-wide, so the mode is the process's: scopes are counted (the
last one out sets the serving mode again), and frames served meanwhile pay the upload mode.
glibc cannot go back to its dynamic thresholds once one is set, so both modes are fixed.
A threshold decides only what is newly mapped: glibc serves a request from a free chunk of
the heap when it has one (tests/server/_heap_probe.py measures in a fresh interpreter).

Measured 2026-12-04 on the shared, loaded 2-core VM (spreads of runs in turn):
- The 4 MiB threshold fixed for the whole process (this module before) cost 20 ICT
  vertices clients 63-88 page faults a result (median 72), 0.1-0.5 now (glibc's dynamic
  thresholds: 0.1-0.8), and server CPU 1,392-1,717 us a result against 1,306-1,506 now
  (6 pairs; `facecast bench transport`, 3 pairs: 860-1,063 against 645-682 us a result for
  its exact vertices phase; its latencies moved more with the machine's load than between
  the two).
- Serving at 32 MiB (glibc's dynamic ceiling) held that server at 495 MB against 384 with
  the dynamic thresholds (blocks of 16-32 MiB, such as a read rig file, stayed in the
  heaps); at 16 MiB, 377-397 MB, as the dynamic thresholds (369-391); the fixed 4 MiB:
  324-330.
- The costliest face's upload: +185 MB in 8 runs of 8 (+203 MB with the 4 MiB threshold
  fixed for the whole process, 4 of 4; +202 serving during the upload); later the same
  day +203 MB in 5 runs of 13 without a change here, +185 in 14 of 14 with
  ``release_freed`` between the read and the fit.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import threading
from collections.abc import Iterator
from typing import Any

__all__ = [
    "SERVING_MMAP_THRESHOLD",
    "SERVING_TRIM_THRESHOLD",
    "UPLOAD_MMAP_THRESHOLD",
    "UPLOAD_TRIM_THRESHOLD",
    "release_freed",
    "serve_frames",
    "upload",
]

#: Serving: over the frame path's blocks for ICT's rig (the largest 14 MB; a rig with
#: larger ones pays for them, as it did over 32 MiB with glibc's dynamic threshold), under
#: the read of its 20 MB rig file; the heaps' tops at twice it, as glibc's dynamic trim
#: threshold is.
SERVING_MMAP_THRESHOLD = 16 << 20
SERVING_TRIM_THRESHOLD = 32 << 20
#: While an upload is read or fitted: its arrays of 4 MiB or more are mapped on their own
#: (a 26,719-vertex ICT frame is 320 kB: the frame path's single frames stay in the
#: heaps), and heaps are trimmed at glibc's default of 128 kB.
UPLOAD_MMAP_THRESHOLD = 4 << 20
UPLOAD_TRIM_THRESHOLD = 128 << 10
#: mallopt's parameter numbers (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def _load_libc() -> Any:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        libc.mallopt  # noqa: B018 - glibc's, absent from musl and macOS
    except (OSError, AttributeError, TypeError):
        return None
    return libc


_libc = _load_libc()
# The mode is the process's (mallopt is), whatever number of apps it serves: one count.
_lock = threading.Lock()
_uploads = 0


def _set(mmap_threshold: int, trim_threshold: int) -> bool:
    if _libc is None:
        return False
    return bool(_libc.mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(
        _libc.mallopt(_M_TRIM_THRESHOLD, trim_threshold)
    )


def release_freed() -> bool:
    """Give the heaps' free memory back to the system now (glibc's ``malloc_trim(0)``: every
    arena, the free pages inside a heap too, not only its top); False without glibc.

    An upload calls it between its read and its fit: the read's freed blocks under the
    upload mode's 4 MiB threshold lie in whichever arenas the threads that made them used,
    and which arena a thread gets depends on timing, so without it the costliest face's
    upload peaked at +185 MB in some runs and +203 MB (over 3 bodies and the constant) in
    others: 5 of 13 on 2026-12-04 (tests/hostile/test_hostile_upload_memory.py); with it,
    +185.0 to +185.4 MB in 14 of 14."""
    return _libc is not None and bool(_libc.malloc_trim(0))


def serve_frames() -> bool:
    """Set the serving mode unless an upload is in flight; whether glibc took it (False
    without glibc, or while an upload holds the upload mode)."""
    with _lock:
        return _uploads == 0 and _set(SERVING_MMAP_THRESHOLD, SERVING_TRIM_THRESHOLD)


@contextlib.contextmanager
def upload() -> Iterator[None]:
    """The upload mode while this scope is open (any thread; nested and concurrent scopes
    are counted: the last one out sets the serving mode again)."""
    global _uploads
    with _lock:
        _uploads += 1
        if _uploads == 1:
            _set(UPLOAD_MMAP_THRESHOLD, UPLOAD_TRIM_THRESHOLD)
    try:
        yield
    finally:
        with _lock:
            _uploads -= 1
            if _uploads == 0:
                _set(SERVING_MMAP_THRESHOLD, SERVING_TRIM_THRESHOLD)

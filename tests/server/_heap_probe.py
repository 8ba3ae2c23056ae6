"""Run by tests/server/test_server_heap.py in a fresh interpreter (a heap with no history,
as a server's): ``python -m tests.server._heap_probe SCENARIO`` prints its figures as JSON.

glibc serves a large request from a free chunk of the heap when it has one, whatever its
mmap threshold: a test process whose other modules freed megabytes of small objects
measures that heap, not the mode.
"""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import numpy as np

from facecast.server import heap

MiB = 1 << 20
#: A block of the frame path's size (ICT: a 20-frame blend scratch is 6.4 MB, a batch's
#: product 5 MB), over the upload mode's threshold and under the serving one's.
BLOCK = 6 * MiB


def _rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def given_back() -> int:
    """Bytes the process gives back when a BLOCK (every page written) is freed."""
    block = np.empty(BLOCK, np.uint8)
    block.fill(1)
    held = _rss()
    del block
    return held - _rss()


def serving() -> dict[str, object]:
    return {"glibc": heap.serve_frames(), "given_back": [given_back() for _ in range(3)]}


def nested() -> dict[str, object]:
    """Two uploads at once (two fit slots), ending one after the other."""
    glibc = heap.serve_frames()
    with heap.upload():
        with heap.upload():
            both = given_back()
        one_left = given_back()
    return {"glibc": glibc, "both": both, "one_left": one_left, "none_left": given_back()}


def threads() -> dict[str, object]:
    """Two uploads in other threads; an app starting meanwhile (``serve_frames``)."""
    glibc = heap.serve_frames()
    inside = threading.Barrier(3)
    leave = threading.Event()

    def fit() -> None:
        with heap.upload():
            inside.wait(timeout=10)
            leave.wait(timeout=10)

    workers = [threading.Thread(target=fit) for _ in range(2)]
    for worker in workers:
        worker.start()
    inside.wait(timeout=10)
    refused = not heap.serve_frames()
    during = given_back()
    leave.set()
    for worker in workers:
        worker.join()
    return {"glibc": glibc, "refused": refused, "during": during, "after": given_back()}


def trim() -> dict[str, object]:
    """An upload's thread frees blocks under the upload mode's threshold below one it keeps
    (a read's arrays under the fit's): they stay in its arena's heap, whose top is in use,
    until ``release_freed``."""
    glibc = heap.serve_frames()
    figures: dict[str, int] = {}

    def read_then_fit() -> None:
        with heap.upload():
            blocks = [np.full(MiB, 1, np.uint8) for _ in range(40)]
            kept = blocks.pop()  # the top of the heap stays in use
            held = _rss()
            del blocks
            figures["freed"] = held - _rss()
            held = _rss()
            heap.release_freed()
            figures["released"] = held - _rss()
            del kept

    worker = threading.Thread(target=read_then_fit)
    worker.start()
    worker.join()
    return {"glibc": glibc, **figures}


if __name__ == "__main__":
    scenarios = {"serving": serving, "nested": nested, "threads": threads, "trim": trim}
    print(json.dumps(scenarios[sys.argv[1]]()))

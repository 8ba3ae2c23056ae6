"""A fixed pool of daemon threads for work a stopping server abandons: uploads' parses and
fits, transfer jobs.

``concurrent.futures.ThreadPoolExecutor`` joins its threads when the interpreter exits, so
a process told to stop waited for a parse or a fit to end (118 s for a 200,000-node glTF,
issue 31). These threads are daemons: the process exits while they run, and what they
were doing is dropped (their requests have been answered 503 already; a transfer job's
record reads ``interrupted``). Work that must not be cut in half (a store's writes) never
runs here.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any, ParamSpec, TypeVar

__all__ = ["DaemonPool"]

P = ParamSpec("P")
T = TypeVar("T")

_Item = tuple[Future[Any], Callable[..., Any], tuple[Any, ...], dict[str, Any]]


#: How long an idle thread is given to take its stop sign from the queue and end.
_SETTLE_SECONDS = 0.2


class DaemonPool(Executor):
    """``threads`` daemon threads named ``name_<i>``, started on first use, FIFO."""

    def __init__(self, threads: int, name: str) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self._size = threads
        self._name = name
        self._queue: queue.SimpleQueue[_Item | None] = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._closed = False

    def submit(self, fn: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> Future[T]:
        future: Future[T] = Future()
        with self._lock:
            if self._closed:
                raise RuntimeError("cannot schedule new futures after shutdown")
            self._queue.put((future, fn, args, kwargs))
            if len(self._threads) < self._size:
                thread = threading.Thread(
                    target=self._work, name=f"{self._name}_{len(self._threads)}", daemon=True
                )
                self._threads.append(thread)
                thread.start()
        return future

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            future, fn, args, kwargs = item
            del item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:
                future.set_exception(exc)
            del future, fn, args, kwargs  # nothing held while idle

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """No new work; ``cancel_futures`` drops what has not started; ``wait`` joins
        the threads (each ends after its current work)."""
        with self._lock:
            self._closed = True
            threads = list(self._threads)
        if cancel_futures:
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[0].cancel()
        for _ in threads:
            self._queue.put(None)
        if wait:
            for thread in threads:
                thread.join()

    def busy(self) -> bool:
        """Whether a thread is still running work (after ``shutdown``, idle ones end at
        once: this asks whether any had work to abandon)."""
        return not self.idle(_SETTLE_SECONDS)

    def idle(self, timeout: float) -> bool:
        """Whether every thread has ended within ``timeout`` s (after ``shutdown``)."""
        with self._lock:
            threads = list(self._threads)
        deadline = time.monotonic() + timeout
        for thread in threads:
            thread.join(max(deadline - time.monotonic(), 0.0))
        return not any(t.is_alive() for t in threads)

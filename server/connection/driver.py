"""The asyncio half of a client connection: its two tasks, its deadline timer, its close.

Runs a reader and a writer task beside a `ConnectionCore` until either side ends it,
calls the core's ``tick`` at its ``deadline`` (one timer, not one per message) and sends
the close in bounded time. It makes no protocol decision (the core does) and reads and
writes nothing itself: subclasses (``session.Session``, ``outbox.Member``) do.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from typing import Any

from starlette.websockets import WebSocket, WebSocketDisconnect

from facecast.protocol import ProtocolError

from .core import CLOSE_GRACE, Closing, ConnectionCore

__all__ = ["Driver"]


class Driver:
    """Serve one accepted WebSocket with ``core``'s rules until either side ends it.

    Subclasses write ``_read_loop`` and ``_write_loop`` and ``_deliver`` (hand what the
    core queued to their writer); the hooks ``_stopping``, ``_extra_tasks``, ``_ended``
    and ``_log_end`` run, in that order, as the connection ends.
    """

    #: Logged (``event``) when a task fails with an unexpected exception.
    crash_event = "connection.crash"
    log = logging.getLogger("facecast.server")

    def __init__(self, websocket: WebSocket, core: ConnectionCore, name: str) -> None:
        self.ws = websocket
        self.core = core
        self._name = name
        self._loop = asyncio.get_running_loop()
        self._stop: asyncio.Future[Closing] = self._loop.create_future()
        self._done = asyncio.Event()
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = math.inf
        self._finishing = False

    # -- subclasses ----------------------------------------------------------------------
    async def _read_loop(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    async def _write_loop(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _deliver(self) -> None:
        """Hand the messages the core queued (``core.data_to_send()``) to the writer."""
        raise NotImplementedError  # pragma: no cover - overridden

    def _stopping(self) -> None:
        """The connection is ending: stop sending on other tasks' stacks."""

    def _extra_tasks(self) -> list[asyncio.Task[None]]:
        """Tasks of this connection besides the reader and writer, cancelled at the end."""
        return []

    async def _ended(self) -> None:
        """The tasks are gone; before the close is sent."""
        await self.leave()

    async def leave(self) -> None:
        """Unregister from what the connection joined (a channel); safe to call again."""

    def _log_end(self, ending: Closing | None) -> None:
        """Log the end (``ending`` None: the client left)."""

    # -- running -------------------------------------------------------------------------
    async def run(self) -> None:
        """Run until the client leaves, a fatal error, the idle timeout or ``close``."""
        name = self._name
        reader = asyncio.create_task(self._read_loop(), name=f"{name}-reader")
        writer = asyncio.create_task(self._write_loop(), name=f"{name}-writer")
        self.arm()
        ending: Closing | None = None
        order: tuple[asyncio.Future[Any], ...] = (self._stop, reader, writer)
        try:
            done, _ = await asyncio.wait(order, return_when=asyncio.FIRST_COMPLETED)
            ending = self._ending(done, order)
        finally:
            self._finishing = True
            self._disarm()
            self._stopping()
            tasks = [reader, writer, *self._extra_tasks()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self._ended()
            if ending is not None:
                await self._send_close(ending)
            self._log_end(ending)
            self._done.set()

    def _ending(
        self, done: set[asyncio.Future[Any]], tasks: tuple[asyncio.Future[Any], ...]
    ) -> Closing | None:
        """Why the connection ends, from the first of ``tasks`` that is done."""
        for task in tasks:
            if task not in done or task.cancelled():
                continue
            exc = task.exception()
            if isinstance(exc, Closing):
                return exc
            if isinstance(exc, WebSocketDisconnect | OSError):
                return None  # the client went away mid-send: a normal end
            if exc is not None:
                self.log.error(
                    "connection failed",
                    exc_info=exc,
                    extra={"event": self.crash_event, "session": self._name},
                )
                return Closing.internal()
            if task is self._stop:
                result: Closing = task.result()
                return result
            return None
        return None

    @property
    def ending(self) -> bool:
        """Whether the connection is ending: asked to stop, or its client left."""
        return self._finishing or self._stop.done()

    async def close(self, code: int, reason: str) -> None:
        """Ask the connection to end with ``code`` (e.g. 1001 at shutdown) and wait for it."""
        self.stop(Closing(code, reason))
        await self._done.wait()

    def stop(self, ending: Closing) -> None:
        """End the connection with ``ending`` (from outside its tasks); the first one wins."""
        if not self._stop.done():
            self._stop.set_result(ending)

    def end(self, error: ProtocolError) -> None:
        """End the connection with a fatal ``error`` (from outside its tasks)."""
        self.stop(Closing.for_error(error))

    async def _send_close(self, ending: Closing) -> None:
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_GRACE):
                data = self.core.closing_bytes(ending)
                if data is not None and self.ws.application_state.name == "CONNECTED":
                    await self.ws.send_bytes(data)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_GRACE):
                await self.ws.close(ending.code, ending.reason[:120])

    # -- the core's deadline -------------------------------------------------------------
    def arm(self) -> None:
        """(Re)arm the timer for the core's deadline, if that is sooner than the armed one."""
        deadline = self.core.deadline()
        if deadline is None or deadline >= self._timer_at:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer_at = deadline
        delay = max(0.0, deadline - time.monotonic())
        self._timer = self._loop.call_later(delay, self._on_deadline)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer, self._timer_at = None, math.inf

    def _on_deadline(self) -> None:
        self._timer, self._timer_at = None, math.inf
        if self._stop.done():
            return
        try:
            self.core.tick(time.monotonic())
        except Closing as ending:
            self.stop(ending)
            return
        self._deliver()
        self.arm()

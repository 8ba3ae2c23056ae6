"""The registry of open streaming sessions of one app: admission (max connections) and close-all.

It knows sessions only through the small ``Closable`` interface; what a session does
with its socket lives in ``session``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Protocol

__all__ = ["Closable", "SessionRegistry"]

log = logging.getLogger("facecast.server.sessions")


class Closable(Protocol):
    id: str

    async def close(self, code: int, reason: str) -> None: ...


class SessionRegistry:
    """Open sessions of one app, used from its event loop only."""

    def __init__(self) -> None:
        self._sessions: dict[str, Closable] = {}
        self.closing = False

    def __len__(self) -> int:
        return len(self._sessions)

    def __iter__(self):
        return iter(list(self._sessions.values()))

    def admit(self, session: Closable, limit: int) -> bool:
        """Register ``session`` unless ``limit`` sessions are open or the server is closing."""
        if self.closing or len(self._sessions) >= limit:
            return False
        self._sessions[session.id] = session
        return True

    def remove(self, session: Closable) -> None:
        self._sessions.pop(session.id, None)

    def get(self, session_id: str) -> Closable | None:
        return self._sessions.get(session_id)

    async def close_all(self, code: int, reason: str, *, timeout: float) -> None:
        """Close every open session with ``code``; refuse new ones from now on."""
        self.closing = True
        sessions = list(self._sessions.values())
        if not sessions:
            return
        log.info(
            "closing sessions",
            extra={"event": "sessions.close_all", "count": len(sessions), "code": code},
        )
        tasks = [asyncio.create_task(s.close(code, reason)) for s in sessions]
        _, pending = await asyncio.wait(tasks, timeout=max(timeout, 0.01))
        for task in pending:
            task.cancel()

"""The registry of open WebSocket connections of one app: admission (limits, quotas) and close-all.

It knows connections only through the small ``Closable`` interface; what a session does
with its socket lives in ``session`` and ``members``.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

from ..settings import Settings

__all__ = ["Closable", "Owner", "Quotas", "SessionRegistry"]

log = logging.getLogger("facecast.server.sessions")


class Closable(Protocol):
    id: str

    async def close(self, code: int, reason: str) -> None: ...


@dataclass(frozen=True)
class Quotas:
    """How many connections may be open: in all, per token, per address; 0 means no quota.

    ``publisher_slots`` connections beyond each of the three are kept for channel
    publishers: beyond ``max_connections``, and beyond every token's and every address's
    quota. Watchers (or streams) filling the server, their token's quota or their address's
    (one machine, a NAT, an untrusted proxy) therefore cannot lock the performer out.
    """

    max_connections: int
    publisher_slots: int = 0
    per_token: int = 0
    per_address: int = 0

    @classmethod
    def from_settings(cls, settings: Settings) -> Quotas:
        return cls(
            max_connections=settings.max_connections,
            publisher_slots=settings.publisher_slots,
            per_token=settings.max_connections_per_token,
            per_address=settings.max_connections_per_address,
        )


@dataclass(frozen=True)
class Owner:
    """Whom a connection's quotas count against: its token (digest) and its address."""

    token: str | None
    address: str | None

    @classmethod
    def of(cls, settings: Settings, principal: str, client: tuple[str, int] | None) -> Owner:
        # With auth off every caller is "anonymous": no token to tell them apart.
        return cls(principal if settings.auth_enabled else None, client[0] if client else None)


class SessionRegistry:
    """Open connections of one app, used from its event loop only."""

    def __init__(self) -> None:
        self._sessions: dict[str, Closable] = {}
        self._owners: dict[str, tuple[str | None, str | None]] = {}
        self._per_token: Counter[str] = Counter()
        self._per_address: Counter[str] = Counter()
        self.closing = False

    def __len__(self) -> int:
        return len(self._sessions)

    def __iter__(self) -> Iterator[Closable]:
        return iter(list(self._sessions.values()))

    def admit(
        self,
        session: Closable,
        quotas: Quotas,
        owner: Owner = Owner(None, None),
        *,
        publisher: bool = False,
    ) -> str | None:
        """Register ``session`` for ``owner``, or say why not (None: admitted)."""
        token, address = owner.token, owner.address
        if self.closing:
            return "the server is shutting down"
        # One rule for the three scopes: a publisher may go ``publisher_slots`` past each.
        extra = quotas.publisher_slots if publisher else 0
        kept = f" and {extra} kept for publishers" if extra else ""
        if len(self._sessions) >= quotas.max_connections + extra:
            return f"the server is at its limit of {quotas.max_connections} connections{kept}"
        if (
            token is not None
            and quotas.per_token
            and self._per_token[token] >= quotas.per_token + extra
        ):
            return f"this token already holds its limit of {quotas.per_token} connections{kept}"
        if (
            address is not None
            and quotas.per_address
            and self._per_address[address] >= quotas.per_address + extra
        ):
            return f"this address already holds its limit of {quotas.per_address} connections{kept}"
        self._sessions[session.id] = session
        self._owners[session.id] = (token, address)
        if token is not None:
            self._per_token[token] += 1
        if address is not None:
            self._per_address[address] += 1
        return None

    def remove(self, session: Closable) -> None:
        if self._sessions.pop(session.id, None) is None:
            return
        token, address = self._owners.pop(session.id)
        for counts, key in ((self._per_token, token), (self._per_address, address)):
            if key is not None:
                counts[key] -= 1
                if counts[key] <= 0:
                    del counts[key]

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

"""uvicorn's HTTP protocols with deadlines and a cap for connections that send no request.

A connection is *pending* from the moment it opens (or its previous response ends) until
its next request head is complete: it must send a first byte within
``request_idle_timeout`` and the whole head within ``request_head_timeout`` of that, and at
most ``max_pending_connections`` are pending at once (one more closes the oldest). So
slowloris connections can neither stay nor fill uvicorn's ``limit_concurrency``. And on
httptools, whose uvicorn protocol routes ``GET http://name/path`` by its path and drops
``name``, an absolute-form target's authority becomes the request's ``Host`` (RFC 9112
§3.2.2), so the Host check (``origins``) judges the host the request names. No request
handling here: only timers, the order connections opened in, and that header.

Subclasses uvicorn's own protocol classes (pinned in pyproject.toml) and relies on their
documented asyncio ``Protocol`` methods plus ``cycle`` (the request in progress) and
``on_response_complete``, which both of uvicorn's HTTP implementations have.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

__all__ = [
    "HTTP_IMPLEMENTATIONS",
    "PendingConnections",
    "absolute_authority",
    "guarded_http_protocol",
]

#: uvicorn's HTTP implementations by name ("auto" is uvicorn's choice with httptools,
#: which ``uvicorn[standard]`` installs).
HTTP_IMPLEMENTATIONS: dict[str, type] = {
    "auto": HttpToolsProtocol,
    "httptools": HttpToolsProtocol,
    "h11": H11Protocol,
}

log = logging.getLogger("facecast.server.http")


class PendingConnections:
    """The pending connections of one server, oldest first, and the limits they live by."""

    def __init__(self, *, idle_timeout: float, head_timeout: float, max_pending: int) -> None:
        self.idle_timeout = idle_timeout
        self.head_timeout = head_timeout
        self.max_pending = max_pending
        self._pending: dict[Any, None] = {}  # insertion order: the oldest first

    def add(self, connection: Any) -> None:
        self._pending.pop(connection, None)
        self._pending[connection] = None
        while len(self._pending) > self.max_pending:
            oldest = next(iter(self._pending))
            del self._pending[oldest]
            oldest.cut("evicted: too many connections without a request")

    def discard(self, connection: Any) -> None:
        self._pending.pop(connection, None)


class _Guarded:
    """Mixin for a uvicorn HTTP protocol class; ``pending`` is set by the factory."""

    pending: PendingConnections
    transport: asyncio.Transport
    cycle: Any
    loop: asyncio.AbstractEventLoop

    def connection_made(self, transport: asyncio.Transport) -> None:
        # A mixin: the uvicorn protocol class it is mixed into has the method.
        super().connection_made(transport)  # type: ignore[misc]
        self._deadline: asyncio.TimerHandle | None = None
        self._request: Any = None  # the cycle whose head completed last
        self._await_request()

    def _await_request(self) -> None:
        self._head_started = False
        self.pending.add(self)
        self._arm(self.pending.idle_timeout, "no request")

    def _arm(self, delay: float, why: str) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        self._deadline = self.loop.call_later(delay, self._expired, why)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self.pending.discard(self)

    def _expired(self, why: str) -> None:
        self._deadline = None
        self.pending.discard(self)
        self.cut(why)

    def cut(self, why: str) -> None:
        """Close at once: a pending connection has no response in flight worth flushing."""
        self._disarm()
        log.debug("connection cut", extra={"event": "http.cut", "reason": why})
        if not self.transport.is_closing():
            self.transport.abort()

    def data_received(self, data: bytes) -> None:
        if self._deadline is not None and not self._head_started:
            self._head_started = True
            self._arm(self.pending.head_timeout, "request head too slow")
        super().data_received(data)  # type: ignore[misc]
        protocol: object = self.transport.get_protocol()
        if protocol is not self:
            self._disarm()  # upgraded to WebSocket: its own limits apply from here
        elif self.cycle is not None and self.cycle is not self._request:
            self._request = self.cycle
            self._disarm()

    def on_response_complete(self) -> None:
        super().on_response_complete()  # type: ignore[misc]
        idle = self.cycle is None or self.cycle.response_complete
        if idle and not self.transport.is_closing():
            self._await_request()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)  # type: ignore[misc]


def absolute_authority(target: bytes) -> bytes | None:
    """The ``host[:port]`` an absolute-form request target (``http://host/path``) names."""
    if not target[:8].lower().startswith((b"http://", b"https://")):
        return None
    authority = target.split(b"://", 1)[1].split(b"/", 1)[0].split(b"?", 1)[0]
    return authority.rsplit(b"@", 1)[-1]


class _TargetHost:
    """httptools only: an absolute-form target's authority replaces the ``Host`` header.

    Relies on uvicorn's ``HttpToolsProtocol`` collecting the target in ``url`` and the
    headers in ``headers`` (the list its scope holds) before ``on_headers_complete``.
    """

    url: bytes
    headers: list[tuple[bytes, bytes]]

    def on_headers_complete(self) -> None:
        authority = absolute_authority(self.url)
        if authority is not None:
            self.headers[:] = [h for h in self.headers if h[0] != b"host"]
            self.headers.append((b"host", authority))
        super().on_headers_complete()  # type: ignore[misc]


def guarded_http_protocol(pending: PendingConnections, http: str = "auto") -> type:
    """uvicorn's HTTP protocol ``http`` (see ``HTTP_IMPLEMENTATIONS``) under ``pending``."""
    base = HTTP_IMPLEMENTATIONS[http]
    mixins = (_Guarded, _TargetHost) if base is HttpToolsProtocol else (_Guarded,)
    return type(f"Guarded{base.__name__}", (*mixins, base), {"pending": pending})

"""Which browsers' requests the server answers: the Host check and the Origin check.

A pure-ASGI middleware refusing, before any route runs, (1) on a loopback-bound server a
``Host`` that is not a loopback name, the bound host or in ``allowed_hosts`` (DNS
rebinding: a page of attacker.example resolved to 127.0.0.1), and (2) a WebSocket
handshake or unsafe method (PUT, POST, PATCH, DELETE) whose ``Origin`` is neither the
server's own nor in ``allowed_origins`` (any web page the user visits). Requests without
``Origin`` (every non-browser client) pass. A request naming itself ambiguously is refused
whatever the bind: two ``Host`` or two ``Origin`` headers (which one would a proxy, or we,
believe?). On a loopback bind an empty ``Host`` is refused like a foreign one, and so is
an absolute-form target (``GET http://name/...``) naming a foreign host: its authority is
the request's host (RFC 9112 §3.2.2; ``http_guard`` puts it in ``Host`` for httptools, h11
leaves it in ``raw_path``). A request without ``Host`` (HTTP/1.0) passes: no browser sends
one. Refusals are logged once per streak (``logs.RefusalLog``). No auth and no CORS here
(``app`` adds Starlette's CORS middleware for ``allowed_origins``).
"""

from __future__ import annotations

import logging
import time
from urllib.parse import urlsplit

from starlette.types import ASGIApp, Receive, Scope, Send

from ..errors import problem
from ..logs import RefusalLog
from ..serving.http_guard import absolute_authority
from ..settings import Settings, is_loopback, normalise_origin

__all__ = ["OriginGuard", "host_name"]

log = logging.getLogger("facecast.server")

#: Methods a cross-site page may not use on us: they change state.
_UNSAFE_METHODS = frozenset({"PUT", "POST", "PATCH", "DELETE"})
#: The denial of a WebSocket handshake as an HTTP response (ASGI extension).
_WS_DENIAL = "websocket.http.response"


def host_name(host_header: str) -> str:
    """The name in a ``Host`` header, without port or IPv6 brackets, in lower case."""
    value = host_header.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


def _is_loopback_name(name: str) -> bool:
    # RFC 6761: *.localhost never resolves to the network.
    return name.endswith(".localhost") or is_loopback(name)


class OriginGuard:
    """Refuse requests by ``Host`` (loopback binds) and ``Origin`` (see the module's doc)."""

    def __init__(self, app: ASGIApp, *, settings: Settings) -> None:
        self.app = app
        self.check_host = is_loopback(settings.host) and "*" not in settings.allowed_hosts
        self.hosts = frozenset(
            {host_name(settings.host), *settings.allowed_hosts}
        )  # lower-cased by Settings
        self.any_origin = "*" in settings.allowed_origins
        self.origins = frozenset(o for o in settings.allowed_origins if o != "*")
        self.refusals = RefusalLog(log, "http.refused", "request refused")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        hosts = [v for k, v in scope.get("headers", ()) if k == b"host"]
        origins = [v for k, v in scope.get("headers", ()) if k == b"origin"]
        refusal = _duplicate("Host", hosts) or _duplicate("Origin", origins)
        host = hosts[0].decode("latin-1") if hosts else None
        if refusal is None:
            # h11 passes an absolute-form target on as raw_path (httptools: http_guard).
            target = absolute_authority(scope.get("raw_path") or b"")
            refusal = self._host_refusal(host if target is None else target.decode("latin-1"))
        if (
            refusal is None
            and origins
            and (scope["type"] == "websocket" or scope["method"] in _UNSAFE_METHODS)
        ):
            refusal = self._origin_refusal(origins[0].decode("latin-1"), host or "")
        if refusal is None:
            await self.app(scope, receive, send)
            return
        code, detail = refusal
        self.refusals.refused(code, time.monotonic(), path=scope.get("path"))
        await _deny(scope, receive, send, code, detail)

    def _host_refusal(self, host: str | None) -> tuple[str, str] | None:
        if not self.check_host or host is None:  # no Host at all (HTTP/1.0): not a browser
            return None
        if not host.strip():
            return (
                "host_not_allowed",
                "this server is bound to a loopback address and answers to loopback names "
                "only, not an empty Host",
            )
        name = host_name(host)
        if _is_loopback_name(name) or name in self.hosts:
            return None
        return (
            "host_not_allowed",
            f"this server is bound to a loopback address and answers to loopback names only, "
            f"not {name[:80]!r} (add it to allowed_hosts, e.g. behind a reverse proxy)",
        )

    def _origin_refusal(self, origin: str, host: str) -> tuple[str, str] | None:
        if self.any_origin:
            return None
        try:
            normal = normalise_origin(origin)
        except ValueError:
            normal = origin  # "null" (a file or sandboxed page) or garbage: not ours
        if normal in self.origins or (host and _netloc(normal) == _netloc(f"http://{host}")):
            return None  # listed, or the server's own pages (the viewer)
        return (
            "origin_not_allowed",
            f"requests from pages of {origin[:80]!r} are not allowed here (add the origin "
            "to allowed_origins)",
        )


def _duplicate(name: str, values: list[bytes]) -> tuple[str, str] | None:
    if len(values) < 2:
        return None
    return (
        f"duplicate_{name.lower()}",
        f"the request has {len(values)} {name} headers; send one",
    )


def _netloc(url: str) -> str | None:
    try:
        parts = urlsplit(url)
        return f"{(parts.hostname or '').lower()}:{parts.port or ''}"
    except ValueError:
        return None


async def _deny(scope: Scope, receive: Receive, send: Send, code: str, detail: str) -> None:
    """A 403 problem+json; for a WebSocket, as the handshake's answer (no 101)."""
    response = problem(403, code, detail)
    if scope["type"] == "http":
        await response(scope, receive, send)
        return
    message = await receive()  # websocket.connect
    if message["type"] != "websocket.connect":
        return
    if _WS_DENIAL in scope.get("extensions", {}):
        await send({"type": "websocket.http.response.start", "status": 403,
                    "headers": response.raw_headers})  # fmt: skip
        await send({"type": "websocket.http.response.body", "body": response.body})
    else:
        await send({"type": "websocket.close", "code": 1008})

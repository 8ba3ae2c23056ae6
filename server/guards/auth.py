"""API-token auth: who is calling (token -> roles) and whether a role may use an endpoint.

Tokens come from ``Settings.tokens``; compared in constant time. REST endpoints take the
token from the ``Authorization: Bearer`` header only; ``?token=`` is refused there with
its own code (URLs end up in logs, histories and Referer headers), and accepted only by
the pages a browser opens by URL (``/docs``, ``/openapi.json``: ``authorize_page``) and by
WebSockets (PROTOCOL.md §2.2). This module decides, it does not send responses: callers
turn ``ApiError`` into 401/403 or a WS close 1008.

A token's ``performer:NAME`` roles bind it to those performers (``Principal.performers``,
checked by ``check_performer``); plain ``performer`` and ``admin`` reach every performer.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from fastapi import Request

from ..errors import ApiError
from ..settings import PERFORMER_ROLE, ROLES, Settings, bound_performer

__all__ = [
    "READ_ROLES",
    "Principal",
    "authorize",
    "authorize_page",
    "authorize_request",
    "check_performer",
    "requires",
    "token_from_request",
]

#: Roles allowed to read rig metadata and meshes; ``admin`` is always allowed too.
#: A publisher only sends points to a channel and learns K from its session's ready.
READ_ROLES = frozenset({"viewer", "stream"})


@dataclass(frozen=True)
class Principal:
    """An authenticated caller. ``name`` is a short token digest, safe to log.

    ``roles`` are plain roles (``performer:NAME`` counts as ``performer``);
    ``performers`` the performer names a token bound by ``performer:NAME`` roles may
    capture, read, refit and delete, None for every name.
    """

    name: str
    roles: frozenset[str]
    performers: frozenset[str] | None = None

    @classmethod
    def holding(cls, name: str, roles: frozenset[str]) -> Principal:
        """The caller whose token holds ``roles`` as configured (``Settings.tokens``)."""
        bound = frozenset(n for n in map(bound_performer, roles) if n is not None)
        plain = frozenset(r for r in roles if r in ROLES) | (
            {PERFORMER_ROLE} if bound else frozenset()
        )
        return cls(name, plain, bound if bound and "admin" not in plain else None)

    def has_any(self, roles: Iterable[str]) -> bool:
        return "admin" in self.roles or bool(self.roles & frozenset(roles))

    def may_perform(self, performer: str) -> bool:
        """Whether this caller may use ``performer``'s profile and rigs (after ``requires``)."""
        return self.performers is None or performer in self.performers


ANONYMOUS = Principal("anonymous", frozenset({"admin"}))


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()


def _lookup(tokens: Mapping[str, frozenset[str]], token: str) -> frozenset[str] | None:
    """Find ``token`` comparing against every configured token in constant time."""
    wanted = _digest(token)
    found: frozenset[str] | None = None
    for candidate, roles in tokens.items():
        # Compare digests (equal length) and never stop early, so timing reveals
        # neither which token nor how much of it matched.
        if hmac.compare_digest(_digest(candidate), wanted):
            found = roles
    return found


def authorize(settings: Settings, token: str | None, roles: Iterable[str]) -> Principal:
    """Return the caller if ``token`` holds one of ``roles`` (or admin).

    Raises
    ------
    ApiError
        401 ``unauthorized`` for no or an unknown token, 403 ``forbidden`` for a
        known token without a suitable role.
    """
    if not settings.auth_enabled:
        return ANONYMOUS
    needed = frozenset(roles)
    if not token:
        raise ApiError(
            401,
            "unauthorized",
            "this endpoint needs an API token (Authorization: Bearer TOKEN)",
            headers={"WWW-Authenticate": "Bearer"},
        )
    held = _lookup(settings.tokens, token)
    if held is None:
        raise ApiError(
            401, "unauthorized", "unknown API token", headers={"WWW-Authenticate": "Bearer"}
        )
    principal = Principal.holding(_digest(token).hex()[:8], held)
    if not principal.has_any(needed):
        wanted = " or ".join(sorted(needed | {"admin"}))
        raise ApiError(403, "forbidden", f"this endpoint needs the role {wanted}")
    return principal


def _bearer(value: str | None) -> str | None:
    if not value:
        return None
    scheme, _, credentials = value.partition(" ")
    if scheme.lower() != "bearer" or not credentials.strip():
        return None
    return credentials.strip()


def token_from_request(request: Request) -> str | None:
    """The bearer token of the ``Authorization`` header (the only place REST reads one)."""
    return _bearer(request.headers.get("authorization"))


def authorize_request(request: Request, roles: Iterable[str]) -> Principal:
    """The caller of a REST request, by its ``Authorization`` header (see the module doc).

    Raises ``ApiError`` as ``authorize`` does, and 401 ``token_in_query`` when auth is on
    and the token came as ``?token=`` instead (it is not used, so no URL carries it).
    """
    settings: Settings = request.app.state.settings
    token = token_from_request(request)
    if token is None and settings.auth_enabled and "token" in request.query_params:
        raise ApiError(
            401,
            "token_in_query",
            "this endpoint takes the token as 'Authorization: Bearer TOKEN' only; ?token= is "
            "accepted by /docs and WebSockets, where no header can be set",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return authorize(settings, token, roles)


def authorize_page(request: Request, roles: Iterable[str]) -> tuple[Principal, str | None]:
    """The caller of a page a browser opens by URL: header, else ``?token=``.

    Returns the query token too, for a page that must hand it on to its own requests.
    """
    query = request.query_params.get("token")
    token = token_from_request(request) or query
    return authorize(request.app.state.settings, token, roles), query


def check_performer(principal: Principal, performer: str) -> None:
    """Raise 403 ``performer_forbidden`` unless ``principal`` may use ``performer``."""
    if principal.may_perform(performer):
        return
    names = ", ".join(sorted(principal.performers or ()))
    raise ApiError(
        403,
        "performer_forbidden",
        f"this token is bound to the performer(s) {names}, not {performer[:64]!r}",
    )


def requires(*roles: str) -> Callable[[Request], Principal]:
    """A FastAPI dependency admitting callers holding any of ``roles`` (admin always)."""
    unknown = set(roles) - ROLES
    if unknown:  # pragma: no cover - programming error caught at import of the routes
        raise ValueError(f"unknown roles {unknown}")

    def dependency(request: Request) -> Principal:
        principal = authorize_request(request, roles)
        request.state.principal = principal
        return principal

    return dependency

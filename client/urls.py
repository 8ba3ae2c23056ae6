"""Where a facecast server's endpoints are, given its base URL, and which token to present.

Pure string work: derives ws(s):// stream URLs and REST URLs and picks the token from an
argument or ``FACECAST_TOKEN``; it never opens a connection.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from urllib.parse import quote, urlsplit, urlunsplit

from facecast.protocol import STREAM_PATH

__all__ = ["TOKEN_ENV", "auth_headers", "resolve_token", "rest_url", "stream_url"]

#: Environment variable read when no token is given explicitly.
TOKEN_ENV = "FACECAST_TOKEN"

_WS_SCHEMES = {"http": "ws", "https": "wss", "ws": "ws", "wss": "wss"}


def _split(base_url: str) -> tuple[str, str, str]:
    """(scheme, netloc, path prefix) of a server base URL, or ValueError saying why not."""
    parts = urlsplit(base_url.strip())
    scheme = parts.scheme.lower()
    if scheme not in _WS_SCHEMES or not parts.netloc:
        raise ValueError(
            f"server URL {base_url!r} must look like http://host:port or https://host "
            "(ws:// and wss:// are accepted too)"
        )
    if parts.query or parts.fragment:
        raise ValueError(f"server URL {base_url!r} must not carry a query or a fragment")
    return scheme, parts.netloc, parts.path.rstrip("/")


def stream_url(base_url: str) -> str:
    """The WebSocket URL of ``/v1/stream`` under ``base_url``.

    ``http://h:p`` -> ``ws://h:p/v1/stream``, ``https://h`` -> ``wss://h/v1/stream``; a
    base URL that already ends in ``/v1/stream`` is kept as is.
    """
    scheme, netloc, prefix = _split(base_url)
    if prefix.endswith(STREAM_PATH):
        prefix = prefix[: -len(STREAM_PATH)]
    return urlunsplit((_WS_SCHEMES[scheme], netloc, prefix + STREAM_PATH, "", ""))


def rest_url(base_url: str, *segments: str) -> str:
    """The HTTP(S) URL of ``/v1/<segments...>`` under ``base_url``, each segment quoted."""
    scheme, netloc, prefix = _split(base_url)
    if prefix.endswith(STREAM_PATH):
        prefix = prefix[: -len(STREAM_PATH)]
    http = "https" if scheme in ("https", "wss") else "http"
    path = "/".join([prefix, "v1", *(quote(s, safe="") for s in segments)])
    return urlunsplit((http, netloc, path, "", ""))


def resolve_token(token: str | None, env: Mapping[str, str] | None = None) -> str | None:
    """``token`` when given, else ``FACECAST_TOKEN`` from ``env`` (default the process's)."""
    if token:
        return token
    env = os.environ if env is None else env
    return env.get(TOKEN_ENV) or None


def auth_headers(token: str | None) -> dict[str, str]:
    """The ``Authorization: Bearer`` header for ``token``, or no headers without one."""
    return {"Authorization": f"Bearer {token}"} if token else {}

"""Blocking REST look-ups a streaming client needs: a rig's summary and its rig file.

Plain httpx GETs under ``/v1`` with the bearer token; failures become `ServerRequestError`
with the server's problem ``code``. It never streams and never writes files.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import httpx

from .errors import RigNotFound, ServerRequestError
from .urls import auth_headers, resolve_token, rest_url

if TYPE_CHECKING:
    from facecast.rig import Rig

__all__ = ["RigNotFound", "ServerRequestError", "fetch_rig", "fetch_rig_bytes", "fetch_summary"]

#: Largest rig file downloaded (bytes); a bigger answer is refused, not buffered.
MAX_RIG_BYTES = 512 * 1024 * 1024


def _get(url: str, token: str | None, *, timeout: float, max_bytes: int) -> bytes:
    try:
        with (
            httpx.Client(timeout=timeout, headers=auth_headers(resolve_token(token))) as client,
            client.stream("GET", url) as response,
        ):
            if response.status_code != 200:
                response.read()
                raise _problem(url, response)
            chunks: list[bytes] = []
            size = 0
            for chunk in response.iter_bytes():
                size += len(chunk)
                if size > max_bytes:
                    raise ServerRequestError(
                        f"GET {url}: answer is over {max_bytes} bytes", status=200, code="too_large"
                    )
                chunks.append(chunk)
            return b"".join(chunks)
    except httpx.HTTPError as exc:
        raise ServerRequestError(
            f"GET {url}: cannot reach the server ({type(exc).__name__}: {exc})",
            status=None,
            code="unreachable",
        ) from exc


def _problem(url: str, response: httpx.Response) -> ServerRequestError:
    code, detail = "http_error", response.reason_phrase
    try:
        body = response.json()
        code = str(body.get("code", code))
        detail = str(body.get("detail", detail))
    except ValueError:
        pass
    # The one refusal a caller may handle apart: the rig asked for is not there.
    kind = (
        RigNotFound
        if response.status_code == 404 and code == "rig_not_found"
        else ServerRequestError
    )
    return kind(
        f"GET {url}: {response.status_code} {code}: {detail}",
        status=response.status_code,
        code=code,
    )


def fetch_summary(
    base_url: str, rig_id: str, *, token: str | None = None, timeout: float = 30.0
) -> dict[str, Any]:
    """``GET /v1/rigs/{id}``: the rig's ``summary()`` plus ``id`` (num_points, names, ...)."""
    data = _get(rest_url(base_url, "rigs", rig_id), token, timeout=timeout, max_bytes=16 << 20)
    summary: dict[str, Any] = json.loads(data)
    return summary


def fetch_rig_bytes(
    base_url: str, rig_id: str, *, token: str | None = None, timeout: float = 60.0
) -> bytes:
    """``GET /v1/rigs/{id}/rig``: the rig file's bytes (needs a token with the stream role)."""
    return _get(
        rest_url(base_url, "rigs", rig_id, "rig"), token, timeout=timeout, max_bytes=MAX_RIG_BYTES
    )


def fetch_rig(
    base_url: str, rig_id: str, *, token: str | None = None, timeout: float = 60.0
) -> Rig:
    """The server's rig ``rig_id`` as a `facecast.rig.Rig` (downloaded and loaded)."""
    from facecast.rig import rig_from_bytes

    return rig_from_bytes(fetch_rig_bytes(base_url, rig_id, token=token, timeout=timeout))

"""HTTP errors as values: ``ApiError(status, code, detail)`` and the problem+json responses.

Route code raises ``ApiError`` (or lets a ``RigError`` through); the handlers here turn
them into one JSON shape, once, at the boundary. No route logic lives here.

The server's exceptions, all here (the root is ``facecast.errors.FacecastError``; a
class's ``code`` is its default, and the module that raises each re-exports it)::

    ApiError(status, code, detail)                 "api_error"          code: the problem's
    SettingsError(ValueError)                      "bad_setting"        raised by settings.py
    RigNotFoundError(LookupError)                  "rig_not_found"      store.py
    StoreClosedError(OSError)                      "store_closed"       rig_store.py
    ProfileNotFoundError(LookupError)              "profile_not_found"  performers.py
    ArchiveError(ValueError)(status, code, ...)    "bad_archive"        archive.py
    BusUnavailable(ConnectionError)                "bus_unavailable"    bus.py
"""

from __future__ import annotations

import contextlib
import logging
import re
from collections.abc import Iterator, Mapping
from http import HTTPStatus
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Receive, Scope, Send

from facecast.errors import FacecastError
from facecast.rig.errors import RigError

__all__ = [
    "ApiError",
    "ArchiveError",
    "BusUnavailable",
    "LogOnce",
    "ProfileNotFoundError",
    "RigNotFoundError",
    "SettingsError",
    "install_error_handlers",
    "problem",
    "redact_paths",
    "upload_paths_hidden",
]

log = logging.getLogger("facecast.server")

PROBLEM_TYPE = "application/problem+json"

#: Stable codes for the status codes Starlette raises on its own (routing, methods).
_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid_request",
    429: "too_many_requests",
    503: "server_busy",
}


class ApiError(FacecastError):
    """An HTTP failure with a stable machine-readable ``code`` and a human ``detail``."""

    code: str = "api_error"

    def __init__(
        self, status: int, code: str, detail: str, *, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.code = code
        self.detail = detail
        self.headers = headers


class ArchiveError(FacecastError, ValueError):
    """A rejected archive; ``status`` and ``code`` are the HTTP answer."""

    code: str = "bad_archive"

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code


class BusUnavailable(FacecastError, ConnectionError):
    """The shared registry (Redis) cannot be reached right now."""

    code: str = "bus_unavailable"


class ProfileNotFoundError(FacecastError, LookupError):
    code: str = "profile_not_found"

    def __init__(self, performer: str) -> None:
        super().__init__(f"no performer profile named {performer!r}")
        self.performer = performer


class SettingsError(FacecastError, ValueError):
    """A configuration value that cannot be used; the message names the setting."""

    code: str = "bad_setting"


class RigNotFoundError(FacecastError, LookupError):
    code: str = "rig_not_found"

    def __init__(self, rig_id: str) -> None:
        super().__init__(f"no rig with id {rig_id!r}")
        self.rig_id = rig_id


class StoreClosedError(FacecastError, OSError):
    """The rig store was closed (the server stopping): work abandoned then writes nothing."""

    code: str = "store_closed"


#: Set in a request's scope by the 500 handler once it has logged the failure.
_LOGGED = "facecast.error_logged"


class LogOnce:
    """Pure ASGI, around Starlette's ServerErrorMiddleware: a failure logged once.

    That middleware answers an unexpected exception with the 500 handler's response, then
    raises it again "so that servers can log it", and uvicorn logs its traceback a second
    time. Here a failure the handler has already logged ends the request instead.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await self.app(scope, receive, send)
        except Exception:
            if not scope.get(_LOGGED):
                raise


def redact_paths(text: str, roots: list[Path]) -> str:
    """``text`` with every path under one of ``roots`` cut to its last part.

    A safety net for error bodies: a server path (the rig directory, a scratch folder)
    tells a caller nothing it can use and something about the host it should not know.
    """
    for root in roots:
        for form in {str(root), str(root.resolve())}:
            text = re.sub(
                re.escape(form) + r"(/[^\s'\"`:,;()]*)?",
                lambda m: m.group(0).rsplit("/", 1)[-1] if m.group(1) else "<server>",
                text,
            )
    return text


@contextlib.contextmanager
def upload_paths_hidden(root: Path) -> Iterator[None]:
    """Engine errors raised inside shown with paths relative to the upload's folder ``root``.

    Loaders name the file at fault by its path, which for an upload is a scratch folder on
    the server: ``.../upload-x/set/neutral.obj`` becomes ``set/neutral.obj``.
    """
    try:
        yield
    except RigError as exc:
        message = exc.message
        for form in {str(root), str(root.resolve())}:
            message = message.replace(form + "/", "").replace(form, "the upload")
        exc.args = (message, *exc.args[1:])
        raise


def problem(
    status: int, code: str, detail: str, *, headers: Mapping[str, str] | None = None
) -> JSONResponse:
    """An RFC 9457 problem response extended with our ``code``."""
    body = {
        "type": "about:blank",
        "title": _title(status),
        "status": status,
        "code": code,
        "detail": detail,
    }
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_TYPE)


def _title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return problem(exc.status, exc.code, exc.detail, headers=exc.headers)

    @app.exception_handler(RigError)
    async def _rig_error(request: Request, exc: RigError) -> JSONResponse:
        # Routes hide their upload folders (``upload_paths_hidden``); no other server path
        # may reach a caller either.
        roots = [request.app.state.store.directory]
        return problem(422, exc.code, redact_paths(exc.message or exc.code, roots))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(p) for p in err.get("loc", ()))
            parts.append(f"{where}: {err.get('msg', 'invalid')}")
        return problem(422, "invalid_request", "; ".join(parts) or "invalid request")

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, f"http_{exc.status_code}")
        return problem(exc.status_code, code, str(exc.detail), headers=exc.headers)

    @app.exception_handler(ClientDisconnect)
    async def _client_left(request: Request, exc: ClientDisconnect) -> JSONResponse:
        # The client closed the connection while sending its body: nobody to answer, and
        # nothing failed here (not a 500, no traceback). The access log shows the 400.
        log.info(
            "client left mid-request",
            extra={"event": "http.client_disconnect", "path": request.url.path},
        )
        return problem(400, "client_disconnected", "the client closed the connection mid-body")

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # The one place an unexpected failure is logged with its traceback (``LogOnce``
        # keeps uvicorn from logging it again).
        log.exception(
            "unhandled error", extra={"event": "http.unhandled", "path": request.url.path}
        )
        request.scope[_LOGGED] = True
        return problem(500, "internal_error", "internal server error")

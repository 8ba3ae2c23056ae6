"""The API docs: ``/docs`` (Swagger UI), ``/openapi.json`` and Swagger UI's files, served offline.

Swagger UI's script, stylesheet, icon and licence come from the npm package swagger-ui-dist,
copied into client/viewer/dist/docs/ by ``npm run build``; nothing is loaded from elsewhere.
"""

from __future__ import annotations

from urllib.parse import quote

from fastapi import APIRouter, FastAPI, Request, Response
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse

from ..errors import ApiError
from ..guards.auth import authorize_page
from ..settings import ROLES
from .viewer import viewer_dir

__all__ = ["DOCS_ASSETS", "mount_docs"]

DOCS_ASSETS_PATH = "/docs/assets"
#: The only files under /docs/assets/ (name -> media type); anything else is 404.
DOCS_ASSETS: dict[str, str] = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
    "favicon-32x32.png": "image/png",
    "LICENSE": "text/plain; charset=utf-8",
    "NOTICE": "text/plain; charset=utf-8",
}
#: Headers of the pages that may carry ``?token=`` in their URL: never sent on in a
#: Referer and never cached.
_TOKEN_PAGE_HEADERS = {"Referrer-Policy": "no-referrer", "Cache-Control": "no-store"}
_NOT_BUILT = """<!doctype html><meta charset="utf-8"><title>facecast API docs not built</title>
<body style="font:15px system-ui;background:#14161c;color:#ffd8dc;padding:2em">
<h1>The API docs' page is not built</h1>
<p>Run <code>scripts/setup</code> (or <code>npm ci &amp;&amp; npm run build</code> in
<code>client/viewer</code>), then reload this page. The schema itself is at
<a href="/openapi.json" style="color:#f0a070">/openapi.json</a>.</p>"""


def _docs_token(request: Request) -> str | None:
    """Admit any valid token (header, or ``?token=`` for a browser) when auth is on.

    Returns the query token, which the docs page must hand on to its schema request.
    """
    _, query = authorize_page(request, ROLES)
    return query


def mount_docs(app: FastAPI) -> None:
    """Add ``/docs``, ``/openapi.json`` (behind auth when it is on) and ``/docs/assets/{name}``.

    The assets hold no data and need no token.
    """
    dist = viewer_dir() / "dist" / "docs"
    router = APIRouter(include_in_schema=False)

    @router.get("/openapi.json")
    async def openapi(request: Request) -> JSONResponse:
        _docs_token(request)
        return JSONResponse(request.app.openapi(), headers=_TOKEN_PAGE_HEADERS)

    @router.get("/docs")
    async def docs(request: Request) -> HTMLResponse:
        token = _docs_token(request)
        if not all((dist / name).is_file() for name in DOCS_ASSETS):
            return HTMLResponse(_NOT_BUILT, status_code=503, headers=_TOKEN_PAGE_HEADERS)
        schema = "/openapi.json" if token is None else f"/openapi.json?token={quote(token)}"
        page = get_swagger_ui_html(
            openapi_url=schema,
            title="facecast API",
            swagger_js_url=f"{DOCS_ASSETS_PATH}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS_PATH}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_ASSETS_PATH}/favicon-32x32.png",
            # No badge asking an online validator about the schema.
            swagger_ui_parameters={"validatorUrl": None},
        )
        page.headers.update(_TOKEN_PAGE_HEADERS)
        return page

    @router.get(DOCS_ASSETS_PATH + "/{name}")
    async def asset(name: str) -> Response:
        media_type = DOCS_ASSETS.get(name)
        if media_type is None or not (dist / name).is_file():
            raise ApiError(404, "not_found", f"no API-docs asset {name[:80]!r}")
        return FileResponse(dist / name, media_type=media_type)

    app.include_router(router)

"""The landing page at ``/``: the server's rigs and live channels, linked to its pages.

Serves client/viewer/index.html and its script as built by ``npm run build`` (never builds
or imports client code); the page lists through the REST API from the browser itself.
"""

from __future__ import annotations

import anyio
from fastapi import APIRouter, FastAPI, Response
from fastapi.responses import FileResponse, HTMLResponse

from ..errors import ApiError
from .viewer import viewer_dir

__all__ = ["LANDING_ASSETS", "mount_landing"]

#: The only files under /landing/assets/; anything else is 404 (no directory serving).
LANDING_ASSETS = {
    "landing.js": "text/javascript; charset=utf-8",
    "landing.js.map": "application/json",
    "landing.js.LEGAL.txt": "text/plain; charset=utf-8",
}
#: The page's URL may carry ``?token=``: never sent on in a Referer.
_HEADERS = {"Cache-Control": "no-cache", "Referrer-Policy": "no-referrer"}
_NOT_BUILT = """<!doctype html><meta charset="utf-8"><title>facecast</title>
<body style="font:15px system-ui;background:#14161c;color:#ffd8dc;padding:2em">
<h1>facecast</h1>
<p>The web pages are not built: run <code>scripts/setup</code> (or <code>npm ci &amp;&amp;
npm run build</code> in <code>client/viewer</code>), then reload this page. The API is
described at <a href="/openapi.json" style="color:#f0a070">/openapi.json</a>.</p>"""


def mount_landing(app: FastAPI) -> None:
    """Add ``/`` and ``/landing/assets/{name}`` (the names of ``LANDING_ASSETS``).

    The page needs no token (it holds no data); the browser presents the ``?token=`` of
    the page URL to the API.
    """
    root = viewer_dir()
    dist = root / "dist"
    router = APIRouter(include_in_schema=False)

    @router.get("/")
    async def page() -> Response:
        if not (dist / "landing.js").is_file():
            return HTMLResponse(_NOT_BUILT, status_code=503, headers=_HEADERS)
        html = await anyio.Path(root / "index.html").read_text(encoding="utf-8")
        return HTMLResponse(html, headers=_HEADERS)

    @router.get("/landing/assets/{name}")
    async def asset(name: str) -> Response:
        media_type = LANDING_ASSETS.get(name)
        if media_type is None or not (dist / name).is_file():
            raise ApiError(404, "not_found", f"no landing-page asset {name[:80]!r}")
        return FileResponse(
            dist / name, media_type=media_type, headers={"Cache-Control": "no-cache"}
        )

    app.include_router(router)

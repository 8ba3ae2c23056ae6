"""The performer studio's routes: ``/perform``, its built script, face model and WebAssembly files.

Serves files that ``npm run build`` in client/viewer copied into dist/ (never builds or
imports client code, never fetches anything); the page authenticates from the browser.
"""

from __future__ import annotations

from pathlib import Path

import anyio
from fastapi import APIRouter, FastAPI, Response
from fastapi.responses import FileResponse, HTMLResponse

from ..errors import ApiError
from .viewer import viewer_dir

__all__ = ["PERFORM_ASSETS", "mount_perform"]

_JS = "text/javascript; charset=utf-8"
_JSON = "application/json"
_BIN = "application/octet-stream"
# WebAssembly.instantiateStreaming refuses any other type.
_WASM = "application/wasm"
#: The only files under /perform/assets/ (name -> path under dist/, media type); anything
#: else is 404 (no directory serving). build.mjs writes them.
PERFORM_ASSETS: dict[str, tuple[str, str]] = {
    "perform.js": ("perform.js", _JS),
    "perform.js.map": ("perform.js.map", _JSON),
    "perform.js.LEGAL.txt": ("perform.js.LEGAL.txt", "text/plain; charset=utf-8"),
    "blazeface.json": ("perform/blazeface.json", _JSON),
    "blazeface.bin": ("perform/blazeface.bin", _BIN),
    "facemesh.json": ("perform/facemesh.json", _JSON),
    "facemesh.bin": ("perform/facemesh.bin", _BIN),
    "iris.json": ("perform/iris.json", _JSON),
    "iris.bin": ("perform/iris.bin", _BIN),
    "tfjs-backend-wasm.wasm": ("perform/tfjs-backend-wasm.wasm", _WASM),
    "tfjs-backend-wasm-simd.wasm": ("perform/tfjs-backend-wasm-simd.wasm", _WASM),
    "tfjs-backend-wasm-threaded-simd.wasm": ("perform/tfjs-backend-wasm-threaded-simd.wasm", _WASM),
}
_NOT_BUILT = """<!doctype html><meta charset="utf-8"><title>facecast performer studio not built</title>
<body style="font:15px system-ui;background:#14161c;color:#ffd8dc;padding:2em">
<h1>The facecast performer studio is not built</h1>
<p>Run <code>scripts/setup</code> (or <code>npm ci &amp;&amp; npm run build</code> in
<code>client/viewer</code>), then reload this page.</p>"""


def mount_perform(app: FastAPI) -> None:
    """Add ``/perform`` and ``/perform/assets/{name}`` (the names of ``PERFORM_ASSETS``).

    The page needs no token (it holds no data); the browser presents the ``?token=`` of
    the page URL to the API and the WebSocket.
    """
    root = viewer_dir()
    dist: Path = root / "dist"
    router = APIRouter(include_in_schema=False)

    @router.get("/perform")
    async def page() -> Response:
        if not all((dist / path).is_file() for path, _ in PERFORM_ASSETS.values()):
            return HTMLResponse(_NOT_BUILT, status_code=503)
        html = await anyio.Path(root / "perform.html").read_text(encoding="utf-8")
        return HTMLResponse(html, headers={"Cache-Control": "no-cache"})

    @router.get("/perform/assets/{name}")
    async def asset(name: str) -> Response:
        entry = PERFORM_ASSETS.get(name)
        if entry is None or not (dist / entry[0]).is_file():
            raise ApiError(404, "not_found", f"no performer-studio asset {name[:80]!r}")
        path, media_type = entry
        return FileResponse(
            dist / path, media_type=media_type, headers={"Cache-Control": "no-cache"}
        )

    app.include_router(router)

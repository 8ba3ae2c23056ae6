"""The web viewer's routes: ``/viewer``, ``/overlay``, their built script, Draco's decoder, and the
demo performance.

Serves files built by ``npm run build`` in client/viewer (never builds or imports client
code) and ``GET /v1/demo/animation``; the pages authenticate from the browser themselves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Annotated

import anyio
import msgpack
import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Query, Request, Response
from fastapi.responses import FileResponse, HTMLResponse

from facecast.protocol import array_to_wire

from ..errors import ApiError
from ..guards.auth import READ_ROLES, requires
from ..settings import Settings
from ..storage.rig_store import RIG_ID_PATTERN, RigNotFoundError, RigStore, valid_rig_id

__all__ = [
    "DEMO_ANIMATION_PATH",
    "DRACO_ASSETS",
    "demo_animation_bytes",
    "mount_viewer",
    "performance_of",
    "viewer_dir",
]

DEMO_ANIMATION_PATH = "/v1/demo/animation"
#: The only files under /viewer/assets/; anything else is 404 (no directory serving).
_ASSETS = {
    "viewer.js": "text/javascript; charset=utf-8",
    "viewer.js.map": "application/json",
    "viewer.js.LEGAL.txt": "text/plain; charset=utf-8",
}
#: The only files under /viewer/assets/draco/: three.js's build of Draco's decoder, which the
#: pages' DRACOLoader fetches for KHR_draco_mesh_compression characters (build.mjs copies
#: them into dist/draco/; nothing is fetched from elsewhere).
DRACO_ASSETS = {
    "draco_decoder.js": "text/javascript; charset=utf-8",
    "draco_wasm_wrapper.js": "text/javascript; charset=utf-8",
    "draco_decoder.wasm": "application/wasm",
    "README.md": "text/markdown; charset=utf-8",
}
_PAGES = {"viewer": "viewer.html", "overlay": "overlay.html"}
_NOT_BUILT = """<!doctype html><meta charset="utf-8"><title>facecast viewer not built</title>
<body style="font:15px system-ui;background:#14161c;color:#ffd8dc;padding:2em">
<h1>The facecast web viewer is not built</h1>
<p>Run <code>scripts/setup</code> (or <code>npm ci &amp;&amp; npm run build</code> in
<code>client/viewer</code>), then reload this page.</p>"""


def viewer_dir() -> Path:
    """client/viewer of this installation, found without importing the client package."""
    spec = importlib.util.find_spec("facecast.client")
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover - broken install
        return Path(__file__).resolve().parents[2] / "client" / "viewer"
    return Path(next(iter(spec.submodule_search_locations))) / "viewer"


@functools.lru_cache(maxsize=4)
def demo_animation_bytes(performance: str = "demo", num_points: int | None = None) -> bytes:
    """A demo performance as one msgpack map (built once, ~0.5 s each, then cached).

    ``{"v": 1, "type": "animation", "fps": float, "points": array (F, K, 3) f32,
    "performance": "demo" | "generic"}``, the array in the wire format of PROTOCOL.md §4:
    ``"demo"`` on the demo rig's 21 points, ``"generic"`` the same performance acted as
    ARKit weights on the generic ARKit set's 24 points (``facecast.rig.demo.arkit``), or
    its first ``num_points`` (a character fitted on the layout's earlier 20).
    """
    fps, points = _demo_performance(performance)
    data: bytes = msgpack.packb(
        {
            "v": 1,
            "type": "animation",
            "fps": fps,
            "points": array_to_wire(points[:, :num_points]),
            "performance": performance,
        }
    )
    return data


@functools.lru_cache(maxsize=2)
def _demo_performance(performance: str) -> tuple[float, np.ndarray]:
    """A demo performance's frame rate and points (F, K, 3) little-endian f32, built once
    (each point count of it is a slice)."""
    from facecast.rig.demo import arkit_demo_animation, demo_animation

    if performance == "generic":
        animation = arkit_demo_animation()
    else:
        animation = demo_animation(with_vertices=False)
    return float(animation.fps), animation.points.astype("<f4")


def performance_of(store: RigStore, rig_id: str) -> tuple[str, int]:
    """The demo performance rig ``rig_id`` takes (``rig.demo.performance_for``) and its
    point count, or an ApiError: 404 for no such rig, 409 ``no_demo_performance`` for a rig
    on other points."""
    from facecast.rig.demo import performance_for

    if not valid_rig_id(rig_id):
        raise ApiError(400, "invalid_rig_id", f"rig id {rig_id[:80]!r} must match {RIG_ID_PATTERN}")
    try:
        rig = store.get(rig_id)
    except RigNotFoundError:
        raise ApiError(404, "rig_not_found", f"no rig with id {rig_id!r}") from None
    neutral = rig.model.source_neutral if rig.calibration is None else rig.calibration
    performance = performance_for(neutral)
    if performance is None:
        raise ApiError(
            409,
            "no_demo_performance",
            f"rig {rig_id!r} takes {rig.num_points} feature points of its own source (a "
            "tracker's, a performer's calibration): the demo performance comes on the demo "
            "rig's points and on the generic ARKit set's (characters uploaded as files); "
            "watch a channel its performer publishes to instead",
        )
    return performance, rig.num_points


def mount_viewer(app: FastAPI, settings: Settings) -> None:
    """Add ``/viewer``, ``/overlay``, ``/viewer/assets/{name}``, ``/viewer/assets/draco/{name}``
    and ``GET /v1/demo/animation``.

    The pages themselves need no token (they hold no data); the browser presents the
    ``?token=`` of the page URL to the API and the WebSocket.
    """
    root = viewer_dir()
    dist = root / "dist"
    router = APIRouter(include_in_schema=False)

    def page(name: str) -> Callable[[], Awaitable[Response]]:
        async def handler() -> Response:
            if not (dist / "viewer.js").is_file():
                return HTMLResponse(_NOT_BUILT, status_code=503)
            html = await anyio.Path(root / _PAGES[name]).read_text(encoding="utf-8")
            return HTMLResponse(html, headers={"Cache-Control": "no-cache"})

        return handler

    router.add_api_route("/viewer", page("viewer"), methods=["GET"])
    router.add_api_route("/overlay", page("overlay"), methods=["GET"])

    @router.get("/viewer/assets/{name}")
    async def asset(name: str) -> Response:
        media_type = _ASSETS.get(name)
        path = dist / name
        if media_type is None or not path.is_file():
            raise ApiError(404, "not_found", f"no viewer asset {name[:80]!r}")
        return FileResponse(path, media_type=media_type, headers={"Cache-Control": "no-cache"})

    @router.get("/viewer/assets/draco/{name}")
    async def draco_asset(name: str) -> Response:
        media_type = DRACO_ASSETS.get(name)
        path = dist / "draco" / name
        if media_type is None or not path.is_file():
            raise ApiError(404, "not_found", f"no Draco decoder file {name[:80]!r}")
        return FileResponse(path, media_type=media_type, headers={"Cache-Control": "no-cache"})

    @router.get(
        DEMO_ANIMATION_PATH,
        include_in_schema=True,
        tags=["demo"],
        summary="The demo performance's feature points, for the demo rig or ?rig= (msgpack; "
        "see server/pages/viewer.py)",
        response_class=Response,
        responses={200: {"content": {"application/vnd.msgpack": {}}}},
        dependencies=[Depends(requires(*READ_ROLES))],
    )
    async def demo_animation(
        request: Request,
        rig: Annotated[
            str | None,
            Query(
                max_length=300,
                description="the rig to play it on: the performance on that rig's source "
                "points (the demo rig's, or the generic ARKit set's for a character "
                "uploaded as a file); 409 no_demo_performance for a rig on other points",
            ),
        ] = None,
    ) -> Response:
        performance, num_points = "demo", None
        if rig is not None:
            store: RigStore = request.app.state.store
            performance, num_points = await anyio.to_thread.run_sync(performance_of, store, rig)
        if performance == "demo":
            num_points = None  # one cached copy of the demo rig's
        data = await anyio.to_thread.run_sync(demo_animation_bytes, performance, num_points)
        return Response(
            data,
            media_type="application/vnd.msgpack",
            headers={"Cache-Control": "public, max-age=3600"},
        )

    app.include_router(router)

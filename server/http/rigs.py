"""The REST API under ``/v1``: upload, fit, list, describe, download and delete rigs.

Thin handlers: auth by dependency, bodies read with a size limit while streaming, all
file and numeric work in threads (store I/O in anyio's pool, fitting in its own executor).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import tempfile
from collections import Counter
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import Executor
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar

import anyio
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from facecast.rig import fit
from facecast.rig.characters.character_examples import (
    character_fit_options as character_fit_options_for,
)
from facecast.rig.characters.loaders import load_example_set

from ..errors import ApiError, upload_paths_hidden
from ..guards.auth import READ_ROLES, Principal, requires
from ..heap import upload as upload_heap
from ..settings import Settings
from ..storage.archive import ArchiveError, ArchiveLimits, extract_archive, find_example_root
from ..storage.characters import audience, base_id, character_view, looks_like_character
from ..storage.rig_store import RIG_ID_PATTERN, RigNotFoundError, RigStore, valid_rig_id
from .downloads import stream_file

if TYPE_CHECKING:
    from facecast.rig import Rig

T = TypeVar("T")

__all__ = [
    "CharacterFitOptions",
    "FitOptions",
    "archive_limits",
    "character_fit_options",
    "fit_options",
    "fit_slot",
    "read_body",
    "refuse_character",
    "router",
    "run_fit",
]

log = logging.getLogger("facecast.server.rest")

router = APIRouter(prefix="/v1", tags=["rigs"])

Reader = Annotated[Principal, Depends(requires(*READ_ROLES))]
Admin = Annotated[Principal, Depends(requires("admin"))]
# A stream client may fetch the rig file to clone locally; viewers only see meshes.
Downloader = Annotated[Principal, Depends(requires("stream"))]


def _store(request: Request) -> RigStore:
    store: RigStore = request.app.state.store
    return store


def _settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def _scratch(request: Request) -> Path:
    return _store(request).scratch


def _check_id(rig_id: str) -> str:
    if not valid_rig_id(rig_id):
        raise ApiError(
            400,
            "invalid_rig_id",
            f"rig id {rig_id[:80]!r} must match {RIG_ID_PATTERN}",
        )
    return rig_id


def _not_found(rig_id: str) -> ApiError:
    return ApiError(404, "rig_not_found", f"no rig with id {rig_id!r}")


async def read_body(request: Request, limit: int) -> bytes:
    """The request body, refused with 413 as soon as it is known to exceed ``limit``.

    Checks ``Content-Length`` first, then counts while streaming, so an oversized or
    unannounced (chunked) body is never buffered beyond ``limit`` bytes; one that takes
    longer than ``body_timeout`` to arrive is 408 ``body_timeout``, and one still arriving
    when the server begins to shut down 503 ``shutting_down`` (``unless_stopping``).
    """
    timeout = _settings(request).body_timeout
    try:
        async with asyncio.timeout(timeout):
            return await unless_stopping(request, _read_body(request, limit))
    except TimeoutError:
        raise ApiError(
            408, "body_timeout", f"the request body took longer than {timeout:g} s to arrive"
        ) from None


async def _read_body(request: Request, limit: int) -> bytes:
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            size = int(declared)
        except ValueError:
            raise ApiError(400, "bad_request", "Content-Length is not a number") from None
        if size > limit:
            raise ApiError(
                413, "payload_too_large", f"body of {size} bytes is over the limit of {limit}"
            )
    chunks: list[bytes] = []
    received = 0
    async for chunk in request.stream():
        received += len(chunk)
        if received > limit:
            raise ApiError(413, "payload_too_large", f"body is over the limit of {limit} bytes")
        chunks.append(chunk)
    if received == 0:
        raise ApiError(400, "empty_body", "the request body is empty")
    return b"".join(chunks)


async def unless_stopping(request: Request, work: Awaitable[T]) -> T:
    """``work``'s result, or 503 ``shutting_down`` as soon as the server begins to stop.

    uvicorn gives requests in flight ``shutdown_timeout`` s, then cancels them: a 500 with
    a traceback at error level for an upload still arriving (a slow or trickled body) or
    a fit still running. Told at once instead (the app's ``stopping`` event, set by
    ``runner``), such a request answers 503 with ``Connection: close``; ``work`` is
    cancelled (a fit's thread runs to its end, and its result is dropped).
    """
    stopping: asyncio.Event = request.app.state.stopping
    task = asyncio.ensure_future(work)
    waiter = asyncio.ensure_future(stopping.wait())
    try:
        await asyncio.wait((task, waiter), return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()
        if not task.done():
            task.cancel()  # stopping, or this request cancelled (its body_timeout)
    if not task.done() or task.cancelled():
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raise ApiError(
            503,
            "shutting_down",
            "the server is shutting down; send the request again in a moment",
            headers={"Retry-After": "5", "Connection": "close"},
        )
    return task.result()


@contextlib.contextmanager
def fit_slot(request: Request, principal: Principal) -> Iterator[None]:
    """Hold one of ``max_pending_fits`` fit slots for ``principal``, or refuse.

    503 ``server_busy`` when all are held; 429 ``too_many_fits`` when a caller without
    the admin role already holds ``max_fits_per_token`` (one token trickling bodies until
    ``body_timeout`` must not hold every slot). Check and count happen together on the
    event loop (no await between), so no number of simultaneous requests can get past a
    limit. Take it before reading the body: concurrent uploads then cannot buffer more
    bodies than there are fits.
    """
    state = request.app.state
    settings = _settings(request)
    held: Counter[str] = state.fits_per_token
    capped = settings.max_fits_per_token > 0 and "admin" not in principal.roles
    if capped and held[principal.name] >= settings.max_fits_per_token:
        raise ApiError(
            429,
            "too_many_fits",
            f"this token already has {settings.max_fits_per_token} fit(s) running or queued; "
            "retry when it ends",
            headers={"Retry-After": "5"},
        )
    if state.pending_fits >= settings.max_pending_fits:
        raise ApiError(
            503,
            "server_busy",
            f"{settings.max_pending_fits} fits are already running or queued; retry later",
            headers={"Retry-After": "5"},
        )
    state.pending_fits += 1
    held[principal.name] += 1
    try:
        # glibc's upload mode while the body is read and fitted (heap.py).
        with upload_heap():
            yield
    finally:
        state.pending_fits -= 1
        held[principal.name] -= 1
        if held[principal.name] <= 0:
            del held[principal.name]


async def run_fit(request: Request, job: Callable[[], T], *, size: int) -> T:
    """Run ``job`` (a parse and a fit of an upload of ``size`` bytes) in the app's fit
    executor, or its small lane up to ``small_upload_bytes``; the caller holds a ``fit_slot``."""
    # Fitting is seconds of numpy: it runs in the dedicated fit executor, never on the
    # event loop and never in the pool that clones frames. Small uploads and captures
    # have a lane of their own: they never queue behind a large file's parse.
    state = request.app.state
    limit = _settings(request).small_upload_bytes
    small = limit > 0 and size <= limit
    executor: Executor = state.small_fit_executor if small else state.fit_executor
    return await unless_stopping(request, asyncio.wrap_future(executor.submit(job)))


def _described(rig_id: str, rig: Rig) -> dict[str, Any]:
    return {"id": rig_id, **rig.summary()}


@router.get("/rigs", summary="List stored rigs")
async def list_rigs(request: Request, _: Reader) -> dict[str, Any]:
    return {"rigs": await anyio.to_thread.run_sync(_listed, _store(request))}


def _listed(store: RigStore) -> list[dict[str, Any]]:
    """Each stored rig: id, size, modified, and its character's format, name and who is
    shown it (``storage.characters.audience``), null for a rig without one."""
    out: list[dict[str, Any]] = []
    for info in store.list():
        stored = store.character(base_id(info.id), with_glb=False)
        character = None
        if stored is not None:
            character = {
                "format": stored.format,
                "name": stored.meta.get("name"),
                **audience(stored.meta, rights_holder=stored.rights_holder),
            }
        out.append(
            {"id": info.id, "size": info.size, "modified": info.modified, "character": character}
        )
    return out


@router.get("/rigs/{rig_id}", summary="Describe a rig (Rig.summary())")
async def get_rig(request: Request, rig_id: str, _: Reader) -> dict[str, Any]:
    _check_id(rig_id)
    store = _store(request)
    try:
        rig = await anyio.to_thread.run_sync(store.get, rig_id)
    except RigNotFoundError:
        raise _not_found(rig_id) from None
    described = _described(rig_id, rig)
    # A performer's rig shows its base rig's character (the same expressions, by name).
    stored = await anyio.to_thread.run_sync(
        lambda: store.character(base_id(rig_id), with_glb=False)
    )
    character = character_view(rig_id, rig.names, stored)
    if character is not None:
        described["character"] = character
    return described


@router.put(
    "/rigs/{rig_id}",
    summary="Store a fitted rig file (bytes of Rig.to_bytes())",
    status_code=201,
    openapi_extra={"requestBody": {"content": {"application/octet-stream": {}}, "required": True}},
)
async def put_rig(request: Request, rig_id: str, principal: Admin) -> JSONResponse:
    _check_id(rig_id)
    # A fit slot as for examples: at most that many upload bodies are held at once.
    with fit_slot(request, principal):
        data = await read_body(request, _settings(request).max_upload_bytes)
        refuse_character(data, rig_id)
        rig, created = await anyio.to_thread.run_sync(_store(request).put_bytes, rig_id, data)
    log.info(
        "rig stored",
        extra={"event": "rig.stored", "rig": rig_id, "bytes": len(data), "by": principal.name},
    )
    return JSONResponse(_described(rig_id, rig), status_code=201 if created else 200)


def fit_options(
    noise: Annotated[
        float, Query(ge=0.0, allow_inf_nan=False, description="expected landmark noise")
    ] = 0.0,
    pca_threshold: Annotated[float | None, Query(gt=0.0, lt=1.0)] = None,
    kernel: Annotated[str, Query(max_length=32)] = "bspline",
    clamp: Annotated[
        Literal["nonneg", "unit"] | None,
        Query(
            description="bound the non-neutral weights to >= 0 or [0, 1] (default: nonneg "
            "when noise > 0, unbounded at 0)"
        ),
    ] = None,
    sparsity: Annotated[
        float | None,
        Query(
            ge=0.0,
            allow_inf_nan=False,
            description="with clamp: the sparsity prior's rate (default 0, the plain projection)",
        ),
    ] = None,
) -> dict[str, Any]:
    """The fit's query options (keyword arguments of ``facecast.rig.fit``), checked."""
    if sparsity is not None and sparsity > 0 and clamp is None:
        # The engine refuses this too, but only after the upload has been read and unpacked.
        raise ApiError(
            422,
            "sparsity_without_clamp",
            "sparsity is a prior on bounded weights: it needs clamp 'nonneg' or 'unit'",
        )
    return {
        "noise": noise,
        "pca_threshold": pca_threshold,
        "kernel": kernel,
        "clamp": clamp,
        "sparsity": sparsity,
    }


FitOptions = Annotated[dict[str, Any], Depends(fit_options)]


def character_fit_options(request: Request, options: FitOptions) -> dict[str, Any]:
    """``fit_options`` for a character paired with the generic ARKit set: without a
    ``noise`` query, the rig side's live defaults (``character_examples.character_fit_options``:
    ``characters.generic.CHARACTER_FIT_DEFAULTS``, docs/characters.md "Fit defaults")."""
    given = {k: v for k, v in options.items() if k != "noise" or "noise" in request.query_params}
    return character_fit_options_for(given)


CharacterFitOptions = Annotated[dict[str, Any], Depends(character_fit_options)]


def archive_limits(settings: Settings) -> ArchiveLimits:
    return ArchiveLimits(
        max_members=settings.max_archive_members,
        max_extracted_bytes=settings.max_extracted_bytes,
        max_compression_ratio=settings.max_compression_ratio,
    )


def refuse_character(data: bytes, rig_id: str) -> None:
    """415 ``character_not_rig`` for a glTF/VRM sent where a rig or example set is expected."""
    if looks_like_character(data):
        raise ApiError(
            415,
            "character_not_rig",
            "the body is a glTF/VRM character file, not a rig file or an example-set archive: "
            f"upload a character with PUT /v1/characters/{rig_id} (body: the .glb or .vrm as "
            "it is, or a zip of the .gltf with its files), or `facecast rigs put URL "
            f"{rig_id} avatar.glb`",
        )


@router.put(
    "/rigs/{rig_id}/examples",
    summary="Fit a rig from an example-set archive (zip, tar, tar.gz) and store it",
    status_code=201,
    openapi_extra={
        "requestBody": {
            "content": {"application/zip": {}, "application/gzip": {}, "application/x-tar": {}},
            "required": True,
        }
    },
)
async def put_examples(
    request: Request, rig_id: str, principal: Admin, options: FitOptions
) -> JSONResponse:
    _check_id(rig_id)
    settings = _settings(request)
    limits = archive_limits(settings)
    with fit_slot(request, principal):
        # The slot is held from before the body is read: concurrent uploads cannot all
        # pass the check while none is counted yet, nor buffer more bodies than fits.
        data = await read_body(request, settings.max_upload_bytes)
        refuse_character(data, rig_id)
        try:
            rig = await run_fit(
                request, _FitJob(data, limits, options, _scratch(request)), size=len(data)
            )
        except ArchiveError as exc:
            raise ApiError(exc.status, exc.code, str(exc)) from None
    created = await anyio.to_thread.run_sync(_store(request).put_rig, rig_id, rig)
    log.info(
        "rig fitted",
        extra={
            "event": "rig.fitted",
            "rig": rig_id,
            "bytes": len(data),
            "kernel": options["kernel"],
            "noise": options["noise"],
            "clamp": options["clamp"],
            "sparsity": options["sparsity"],
            "by": principal.name,
        },
    )
    # The fit's warnings (collapsing examples, noise amplification) go to the uploader, who
    # would otherwise never see them.
    described = {**_described(rig_id, rig), "warnings": list(rig.fit_report.get("warnings", []))}
    return JSONResponse(described, status_code=201 if created else 200)


class _FitJob:
    """Extract, load and fit one uploaded example set (runs in a worker thread)."""

    def __init__(
        self, data: bytes, limits: ArchiveLimits, options: dict[str, Any], scratch: Path
    ) -> None:
        self.data = data
        self.limits = limits
        #: Where the archive is unpacked: the rig store's scratch folder, which the next
        #: start cleans if this process is killed mid-fit.
        self.scratch = scratch
        # Keyword arguments of facecast.rig.fit: noise, pca_threshold, kernel, clamp, sparsity.
        self.options = options

    def __call__(self) -> Rig:
        with tempfile.TemporaryDirectory(prefix="upload-", dir=self.scratch) as tmp:
            dest = Path(tmp)
            extract_archive(self.data, dest, self.limits)
            with upload_paths_hidden(dest):
                example_set = load_example_set(find_example_root(dest))
        return fit(example_set, **self.options)


@router.get(
    "/rigs/{rig_id}/model.glb",
    summary="The target mesh with every example as a morph target (glTF binary)",
    response_class=Response,
    responses={200: {"content": {"model/gltf-binary": {}}}},
)
async def get_model(request: Request, rig_id: str, _: Reader) -> Response:
    _check_id(rig_id)
    try:
        glb = await anyio.to_thread.run_sync(_store(request).glb, rig_id)
    except RigNotFoundError:
        raise _not_found(rig_id) from None
    return Response(glb, media_type="model/gltf-binary")


@router.get(
    "/rigs/{rig_id}/rig",
    summary="Download the rig file",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
async def download_rig(request: Request, rig_id: str, _: Downloader) -> Response:
    _check_id(rig_id)
    try:
        fh, size = await anyio.to_thread.run_sync(_store(request).open_rig_file, rig_id)
    except RigNotFoundError:
        raise _not_found(rig_id) from None
    # Streamed from disk in chunks (``downloads``), as the character file is.
    return stream_file(
        fh,
        size,
        "application/octet-stream",
        {"Content-Disposition": f'attachment; filename="{rig_id}.rig"'},
    )


@router.delete("/rigs/{rig_id}", summary="Delete a rig", status_code=204)
async def delete_rig(request: Request, rig_id: str, principal: Admin) -> Response:
    _check_id(rig_id)
    try:
        await anyio.to_thread.run_sync(_store(request).delete, rig_id)
    except RigNotFoundError:
        raise _not_found(rig_id) from None
    log.info("rig deleted", extra={"event": "rig.deleted", "rig": rig_id, "by": principal.name})
    return Response(status_code=204)

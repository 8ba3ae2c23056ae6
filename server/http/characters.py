"""Characters as files: ``PUT /v1/characters/{id}`` fits a rig from a glTF/VRM as uploaded.

The file is paired with the generic ARKit source set (``facecast.rig.io.character``),
fitted in the fit pool, and stored beside the rig (``storage.characters``); the rig's
description and ``GET /v1/rigs/{id}/character.glb`` give it to the pages.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse

from facecast.rig import fit
from facecast.rig.io.character import PairingReport, character_example_set, load_character

from ..errors import ApiError, upload_paths_hidden
from ..guards.auth import ANONYMOUS, READ_ROLES, Principal, requires
from ..names import PERFORMER_SEPARATOR
from ..storage.archive import ArchiveError, ArchiveLimits, extract_archive
from ..storage.characters import (
    base_id,
    character_not_served,
    character_view,
    pack_character,
)
from ..storage.rig_store import RIG_ID_PATTERN, RigStore, valid_rig_id
from .rigs import CharacterFitOptions, archive_limits, fit_slot, read_body, run_fit

if TYPE_CHECKING:
    from facecast.rig import Rig

__all__ = ["router"]

log = logging.getLogger("facecast.server.http.characters")

router = APIRouter(prefix="/v1", tags=["characters"])

Reader = Annotated[Principal, Depends(requires(*READ_ROLES))]
Admin = Annotated[Principal, Depends(requires("admin"))]

#: What an archive may hold as its character (the one such file in it).
CHARACTER_SUFFIXES = (".gltf", ".glb", ".vrm")


def _store(request: Request) -> RigStore:
    store: RigStore = request.app.state.store
    return store


def _check_id(rig_id: str) -> str:
    if not valid_rig_id(rig_id):
        raise ApiError(400, "invalid_rig_id", f"rig id {rig_id[:80]!r} must match {RIG_ID_PATTERN}")
    return rig_id


@router.put(
    "/characters/{rig_id}",
    summary="Fit a rig from a character file (.glb, .vrm, or a zip/tar of a .gltf folder)",
    status_code=201,
    openapi_extra={
        "requestBody": {
            "content": {
                "model/gltf-binary": {},
                "application/zip": {},
                "application/x-tar": {},
                "application/gzip": {},
            },
            "required": True,
        }
    },
)
async def put_character(
    request: Request, rig_id: str, principal: Admin, options: CharacterFitOptions
) -> JSONResponse:
    _check_id(rig_id)
    if PERFORMER_SEPARATOR in rig_id:
        raise ApiError(
            400,
            "invalid_rig_id",
            f"a character is stored under a base id, not a performer's rig ({rig_id!r}); "
            "performers calibrate on it with PUT /v1/rigs/{id}/performer/{name}",
        )
    settings = request.app.state.settings
    job = _CharacterJob(archive_limits(settings), options, _store(request).scratch)
    with fit_slot(request, principal):
        data = await read_body(request, settings.max_upload_bytes)
        try:
            fitted = await run_fit(request, lambda: job(data))
        except ArchiveError as exc:
            raise ApiError(exc.status, exc.code, str(exc)) from None
    rig, packed, pairing, fmt = fitted
    created = await anyio.to_thread.run_sync(
        lambda: _store(request).put_rig(rig_id, rig, character=packed)
    )
    log.info(
        "character fitted",
        extra={
            "event": "character.fitted",
            "rig": rig_id,
            "bytes": len(data),
            "format": fmt,
            "by": principal.name,
        },
    )
    stored = await anyio.to_thread.run_sync(
        lambda: _store(request).character(rig_id, with_glb=False)
    )
    described = {
        "id": rig_id,
        **rig.summary(),
        "warnings": list(rig.fit_report.get("warnings", [])),
        "pairing": pairing,
        "character": character_view(rig_id, rig.names, stored),
    }
    return JSONResponse(described, status_code=201 if created else 200)


@router.get(
    "/rigs/{rig_id}/character.glb",
    summary="The rig's character file as uploaded (glTF binary; a VRM is one too)",
    response_class=Response,
    responses={200: {"content": {"model/gltf-binary": {}}}},
)
async def get_character(request: Request, rig_id: str, principal: Reader) -> Response:
    _check_id(rig_id)
    # The rig itself must exist: ``x@nobody`` shows no character, even if ``x`` has one.
    if not await anyio.to_thread.run_sync(_store(request).exists, rig_id):
        raise ApiError(404, "rig_not_found", f"no rig with id {rig_id!r}")
    stored = await anyio.to_thread.run_sync(
        lambda: _store(request).character(base_id(rig_id), with_glb=True)
    )
    if stored is None:
        raise ApiError(
            404,
            "no_character",
            f"rig {rig_id!r} has no character file (it was not uploaded with "
            "PUT /v1/characters/{id}); its mesh is GET /v1/rigs/{id}/model.glb",
        )
    if character_not_served(stored.meta, anonymous=principal is ANONYMOUS):
        raise ApiError(
            403,
            "character_not_redistributable",
            f"the character of rig {rig_id!r} is a VRM whose licence forbids redistribution: "
            "it is served only to callers with a token (the viewer role); its mesh is "
            f"GET /v1/rigs/{rig_id}/model.glb",
        )
    return Response(
        stored.glb,
        media_type="model/gltf-binary",
        headers={
            "Cache-Control": "no-store"
            if stored.meta.get("redistribution") is False
            else "no-cache"
        },
    )


class _CharacterJob:
    """Unpack (an archive), load, pair with the generic source set and fit (a worker thread)."""

    def __init__(self, limits: ArchiveLimits, options: dict[str, Any], scratch: Path) -> None:
        self.limits = limits
        self.options = options
        self.scratch = scratch

    def __call__(self, data: bytes) -> tuple[Rig, bytes, dict[str, Any], str]:
        if data[:4] == b"glTF":
            character = load_character(data, label="the uploaded file")
        elif data.lstrip()[:1] == b"{":
            raise ApiError(
                415,
                "gltf_needs_archive",
                "a .gltf refers to its buffers and images by file name: send it in a zip or "
                "tar with its files (`facecast rigs put URL ID avatar.gltf` does), or as a .glb",
            )
        else:
            with tempfile.TemporaryDirectory(prefix="upload-", dir=self.scratch) as tmp:
                dest = Path(tmp)
                try:
                    extract_archive(data, dest, self.limits)
                except ArchiveError as exc:
                    if exc.code == "unsupported_archive":
                        raise ArchiveError(
                            415,
                            "unsupported_character",
                            "the body is neither a glTF binary (.glb, .vrm) nor a zip/tar of a "
                            ".gltf folder",
                        ) from None
                    raise
                found = _find_character(dest)
                with upload_paths_hidden(dest):
                    character = load_character(found, label=found.relative_to(dest).as_posix())
        example_set, report = character_example_set(character)
        rig = fit(example_set, **self.options)
        record = {
            "format": character.format,
            "meta": character.meta,
            "bindings": {
                name: [[b.mesh, b.morph, b.weight] for b in expression.bindings]
                for name, expression in character.expressions.items()
            },
        }
        return rig, pack_character(character.glb, record), _pairing(report), character.format


def _find_character(dest: Path) -> Path:
    """The one .gltf/.glb/.vrm in an unpacked upload (at its top or one folder down)."""
    found = [
        p
        for pattern in ("*", "*/*")
        for p in dest.glob(pattern)
        if p.is_file() and p.suffix.lower() in CHARACTER_SUFFIXES
    ]
    if not found:
        raise ArchiveError(
            422,
            "no_character_in_archive",
            "the archive holds no .gltf, .glb or .vrm at its top level or one folder down",
        )
    if len(found) > 1:
        names = ", ".join(sorted(str(p.relative_to(dest)) for p in found)[:4])
        raise ArchiveError(
            422, "several_characters", f"the archive holds more than one character file ({names})"
        )
    return found[0]


def _pairing(report: PairingReport) -> dict[str, Any]:
    """The pairing report as JSON, with its lines as ``facecast fit`` prints them."""
    return {**report.to_dict(), "text": report.lines()}

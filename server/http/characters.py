"""Characters as files: ``PUT /v1/characters/{id}`` fits a rig from a glTF/VRM as uploaded.

The file is paired with the generic ARKit source set (``facecast.rig.characters.character``),
fitted in the fit pool, and stored beside the rig (``storage.characters``); the rig's
description and ``GET /v1/rigs/{id}/character.glb`` give it to the pages.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import anyio
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from facecast.rig import fit
from facecast.rig.characters.character import character_example_set
from facecast.rig.errors import ExampleSetError
from facecast.rig.io.gltf import GltfLimits

from ..errors import ApiError
from ..guards.auth import ANONYMOUS, READ_ROLES, Principal, requires
from ..heap import release_freed
from ..names import PERFORMER_SEPARATOR
from ..storage.archive import ArchiveError, ArchiveLimits
from ..storage.characters import (
    PackedCharacter,
    base_id,
    character_not_served,
    character_view,
    pack_character,
)
from ..storage.rig_store import RIG_ID_PATTERN, RigStore, valid_rig_id
from .character_upload import (
    character_record,
    check_character_size,
    gltf_limits,
    pairing_view,
    read_character_upload,
)
from .downloads import stream_file
from .rigs import CharacterFitOptions, archive_limits, fit_slot, read_body, run_fit
from .transfer import start_transfer, transfer_available

if TYPE_CHECKING:
    from facecast.rig import Rig

__all__ = ["router"]

log = logging.getLogger("facecast.server.http.characters")

router = APIRouter(prefix="/v1", tags=["characters"])

Reader = Annotated[Principal, Depends(requires(*READ_ROLES))]
Admin = Annotated[Principal, Depends(requires("admin"))]


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
    responses={202: {"description": "expressions=transfer: the job (GET .../job follows it)"}},
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
    request: Request,
    rig_id: str,
    principal: Admin,
    options: CharacterFitOptions,
    expressions: Annotated[
        Literal["transfer"] | None,
        Query(
            description="transfer: give a character with only a neutral (or too few "
            "expressions) ICT-FaceKit's ARKit shapes by deformation transfer, as a job (202)"
        ),
    ] = None,
    markers: Annotated[
        Literal["auto"] | None,
        Query(
            description="with expressions=transfer: auto fits the correspondence without "
            "markers (else a markers.txt beside the character in a zip, or none for ICT's "
            "own topology)"
        ),
    ] = None,
    names: Annotated[
        str | None,
        Query(
            max_length=2000,
            description="with expressions=transfer: comma-separated ARKit names to make "
            "(default all the character lacks)",
        ),
    ] = None,
    rights_holder: Annotated[
        bool,
        Query(
            description="the uploader declares they hold the rights to show this character: "
            "a VRM whose licence forbids redistribution is then served to viewers without a "
            "token too (default false: only to token holders)"
        ),
    ] = False,
) -> JSONResponse:
    _check_id(rig_id)
    if PERFORMER_SEPARATOR in rig_id:
        raise ApiError(
            400,
            "invalid_rig_id",
            f"a character is stored under a base id, not a performer's rig ({rig_id!r}); "
            "performers calibrate on it with PUT /v1/rigs/{id}/performer/{name}",
        )
    if expressions == "transfer":
        return await start_transfer(
            request,
            rig_id,
            principal,
            options,
            markers=markers,
            names=names,
            rights_holder=rights_holder,
        )
    if markers is not None or names is not None:
        raise ApiError(
            422,
            "transfer_options_without_transfer",
            "markers and names choose how expressions are transferred: add expressions=transfer",
        )
    settings = request.app.state.settings
    job = _CharacterJob(
        archive_limits(settings),
        gltf_limits(settings),
        options,
        _store(request).scratch,
        settings.max_character_bytes,
        rights_holder=rights_holder,
    )
    with fit_slot(request, principal):
        data = await read_body(request, settings.max_upload_bytes)
        try:
            fitted = await run_fit(request, lambda: job(data), size=len(data))
        except ArchiveError as exc:
            raise ApiError(exc.status, exc.code, str(exc)) from None
        except ExampleSetError as exc:
            if exc.code != "no_expressions":
                raise
            # Only a server that has expressions to transfer (transfer_source) is offered:
            # any other answers ?expressions=transfer with 503 transfer_unavailable.
            if await anyio.to_thread.run_sync(transfer_available, settings):
                remedy = (
                    "Or let this server make them: upload it again with ?expressions=transfer "
                    f"(`facecast rigs put URL {rig_id} FILE --expressions transfer`)"
                )
            else:
                remedy = (
                    "This server has no expressions to transfer (setting transfer_source): "
                    "make them with `facecast expressions FILE -o FOLDER` where ICT-FaceKit "
                    "is, then upload the example set"
                )
            raise ApiError(422, exc.code, f"{exc.message}. {remedy}") from None
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
            "rights_holder": rights_holder,
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
    opened = await anyio.to_thread.run_sync(_store(request).open_character, base_id(rig_id))
    if opened is None:
        raise ApiError(
            404,
            "no_character",
            f"rig {rig_id!r} has no character file (it was not uploaded with "
            "PUT /v1/characters/{id}); its mesh is GET /v1/rigs/{id}/model.glb",
        )
    stored, fh, size = opened
    if character_not_served(
        stored.meta, anonymous=principal is ANONYMOUS, rights_holder=stored.rights_holder
    ):
        fh.close()
        raise ApiError(
            403,
            "character_not_redistributable",
            f"the character of rig {rig_id!r} is a VRM whose licence forbids redistribution: "
            "it is served only to callers with a token (the viewer role), unless its uploader "
            "declares they hold the rights to show it (?rights_holder=true on the upload); "
            f"its mesh is GET /v1/rigs/{rig_id}/model.glb",
        )
    # Streamed from disk in chunks (``downloads``): a slow viewer holds one, not the file.
    return stream_file(
        fh,
        size,
        "model/gltf-binary",
        {"Cache-Control": "no-store" if stored.meta.get("redistribution") is False else "no-cache"},
    )


class _CharacterJob:
    """Unpack (an archive), load, pair with the generic source set and fit (a worker thread)."""

    def __init__(
        self,
        limits: ArchiveLimits,
        gltf: GltfLimits,
        options: dict[str, Any],
        scratch: Path,
        max_bytes: int,
        *,
        rights_holder: bool = False,
    ) -> None:
        self.limits = limits
        self.gltf = gltf
        self.options = options
        self.scratch = scratch
        self.max_bytes = max_bytes
        self.rights_holder = rights_holder

    def __call__(self, data: bytes) -> tuple[Rig, PackedCharacter, dict[str, Any], str]:
        character, _ = read_character_upload(data, self.limits, self.scratch, self.gltf)
        check_character_size(character, self.max_bytes)
        record = character_record(character, rights_holder=self.rights_holder)
        glb, fmt = character.glb, character.format
        example_set, report = character_example_set(character, displaced=True)
        # The largest arrays go as soon as they are used (SERVER.md "What an upload can
        # cost"): the character's displacements once in the example set, that once fitted.
        del character
        release_freed()  # the read's freed blocks, before the fit's peak (heap.py)
        rig = fit(example_set, **self.options)
        del example_set
        return rig, pack_character(glb, record), pairing_view(report), fmt

"""Performer calibration routes: fit a character's rig on a performer's own captured expressions.

``PUT /v1/rigs/{id}/performer/{performer}`` takes a capture and stores the rig
``{id}@{performer}`` and the performer's profile; ``/v1/performers/{performer}`` shows,
refits (onto another character) or deletes that profile. A token bound to performer
names reaches only those (``auth.check_performer``, before any body is read). Thin
handlers: parsing and files in threads, fitting in the fit executor (``rest.run_fit``,
holding a ``rest.fit_slot``). See server/SERVER.md.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from facecast.rig import Rig
from facecast.rig.characters.generic import composed_captures
from facecast.rig.retarget import NEUTRAL, fit_performer, shared_names
from facecast.rig.sources.layouts import load_layout

from ..errors import ApiError
from ..guards.auth import Principal, check_performer, requires
from ..names import NAME_PATTERN, performer_rig_id, valid_name
from ..settings import Settings
from ..storage.profiles import (
    Capture,
    PerformerProfile,
    ProfileNotFoundError,
    ProfileStore,
    parse_capture,
)
from ..storage.rig_store import RigNotFoundError, RigStore
from .rigs import fit_slot, read_body, run_fit

__all__ = ["PROFILES_DIR", "profile_store", "router"]

log = logging.getLogger("facecast.server.performers")

router = APIRouter(prefix="/v1", tags=["performers"])

#: Profiles live in this folder of the rig store.
PROFILES_DIR = "performers"

Performer = Annotated[Principal, Depends(requires("performer"))]


def profile_store(settings: Settings, rigs: RigStore) -> ProfileStore:
    """The app's profile store: ``performers/`` in the rig store (built by ``create_app``)."""
    return ProfileStore(
        settings.rigs_dir / PROFILES_DIR,
        max_bytes=settings.max_capture_bytes,
        scratch=lambda: rigs.scratch,
    )


def _profiles(request: Request) -> ProfileStore:
    profiles: ProfileStore = request.app.state.profiles
    return profiles


def _check_rig_id(rig_id: str) -> str:
    if not valid_name(rig_id):
        raise ApiError(
            400,
            "invalid_rig_id",
            f"rig id {rig_id[:80]!r} must be a character's own rig, matching {NAME_PATTERN} "
            "(a performer rig is refitted from its character's)",
        )
    return rig_id


def _check_performer(performer: str) -> str:
    if not valid_name(performer):
        raise ApiError(
            400,
            "invalid_performer",
            f"performer name {performer[:80]!r} must match {NAME_PATTERN}",
        )
    return performer


def _profile_error(performer: str, exc: Exception) -> ApiError:
    log.error(
        "performer profile unreadable",
        extra={"event": "performer.bad_profile", "performer": performer, "error": str(exc)},
    )
    return ApiError(500, "bad_profile", f"the stored profile does not validate: {exc}")


class _PerformerFit:
    """Fit ``capture`` onto the stored rig ``rig_id`` (runs in the fit executor).

    ``shared_only``: leave out captured expressions the rig does not have (a profile
    refitted onto another character) instead of refusing them (a capture for this one).
    """

    def __init__(
        self, store: RigStore, rig_id: str, capture: Capture, *, shared_only: bool
    ) -> None:
        self.store = store
        self.rig_id = rig_id
        self.capture = capture
        self.shared_only = shared_only

    def __call__(self) -> tuple[Rig, list[str], list[str]]:
        try:
            base = self.store.get(self.rig_id)
        except RigNotFoundError:
            raise ApiError(404, "rig_not_found", f"no rig with id {self.rig_id!r}") from None
        layout = load_layout(self.capture.layout)
        k, captured = base.num_points, self.capture.num_points
        counts = " or ".join(map(str, layout.counts))
        if not layout.drives(k):
            raise ApiError(
                422,
                "layout_mismatch",
                f"layout {layout.name} gives {counts} feature points but rig {self.rig_id!r} "
                f"has {k}",
            )
        if not layout.drives(captured):
            raise ApiError(
                422,
                "wrong_point_count",
                f"the capture has {captured} feature points; layout {layout.name} gives {counts}",
            )
        # A capture of more points than a rig of the layout's earlier version (the iris
        # centres after its 24) keeps them: the performer's rig is fitted on all of them,
        # its first k the character's (fit_performer, which refuses fewer than k).
        points = self.capture.points
        # VRM presets the performer did not make, from the ARKit shapes they did.
        composed = composed_captures(base.names, points)
        if self.shared_only:
            known = {NEUTRAL, *base.names}
            points = {name: p for name, p in points.items() if name in known}
        points = {**points, **composed}
        rig = fit_performer(base, points, noise=self.capture.noise)
        used = shared_names(base, points)
        skipped = [name for name in base.names[1:] if name not in used]
        return rig, skipped, [name for name in rig.names if name in composed]


async def _fit_and_store(
    request: Request, rig_id: str, performer: str, capture: Capture, by: str, *, refit: bool
) -> tuple[dict[str, Any], bool]:
    store = request.app.state.store
    job = _PerformerFit(store, rig_id, capture, shared_only=refit)
    # A capture (at most max_capture_bytes, parsed already): the small lane.
    rig, skipped, composed = await run_fit(request, job, size=0)
    new_id = performer_rig_id(rig_id, performer)
    created = await anyio.to_thread.run_sync(store.put_rig, new_id, rig)
    log.info(
        "performer rig fitted",
        extra={
            "event": "performer.fitted",
            "rig": new_id,
            "examples": rig.num_examples,
            "noise": capture.noise,
            "noise_source": capture.noise_source,
            "by": by,
        },
    )
    described = {
        "id": new_id,
        **rig.summary(),
        "performer": performer,
        "character": rig_id,
        "skipped": skipped,
        # VRM presets not captured, composed from the captured ARKit shapes.
        "composed": composed,
        # The landmark noise the rig was fitted with ("noise", from rig.summary) and where
        # it came from: the capture's own, or measured from its held frames (how many).
        "noise_source": capture.noise_source,
        "held_frames": capture.held_frames,
        # The fit's warnings (nearly coinciding expressions) go to the performer, who can
        # redo one of them.
        "warnings": list(rig.fit_report.get("warnings", [])),
    }
    return described, created


@router.put(
    "/rigs/{rig_id}/performer/{performer}",
    summary="Fit rig {rig_id}@{performer} from a performer's captured expressions",
    status_code=201,
    openapi_extra={
        "requestBody": {
            "content": {"application/json": {}, "application/msgpack": {}},
            "required": True,
        }
    },
)
async def put_performer(
    request: Request, rig_id: str, performer: str, principal: Performer
) -> JSONResponse:
    _check_rig_id(rig_id)
    _check_performer(performer)
    check_performer(principal, performer)
    with fit_slot(request, principal):
        data = await read_body(request, request.app.state.settings.max_capture_bytes)
        capture = await anyio.to_thread.run_sync(
            parse_capture, data, request.headers.get("content-type")
        )
        described, created = await _fit_and_store(
            request, rig_id, performer, capture, principal.name, refit=False
        )
    profile = PerformerProfile(performer=performer, rig=rig_id, capture=capture)
    await anyio.to_thread.run_sync(_profiles(request).put, profile)
    return JSONResponse(described, status_code=201 if created else 200)


async def _profile(request: Request, performer: str, principal: Principal) -> PerformerProfile:
    _check_performer(performer)
    check_performer(principal, performer)
    try:
        return await anyio.to_thread.run_sync(_profiles(request).get, performer)
    except ProfileNotFoundError:
        raise ApiError(
            404, "performer_not_found", f"no performer profile named {performer!r}"
        ) from None
    except ValueError as exc:
        raise _profile_error(performer, exc) from None


@router.get("/performers/{performer}", summary="Describe a performer's profile")
async def get_performer(request: Request, performer: str, principal: Performer) -> dict[str, Any]:
    return (await _profile(request, performer, principal)).summary()


@router.post(
    "/performers/{performer}/refit",
    summary="Fit rig {rig}@{performer} from the performer's profile, onto another character",
    status_code=201,
)
async def refit_performer(
    request: Request,
    performer: str,
    principal: Performer,
    rig: Annotated[str, Query(max_length=64, description="the character to refit onto")],
) -> JSONResponse:
    _check_rig_id(rig)
    profile = await _profile(request, performer, principal)
    with fit_slot(request, principal):
        described, created = await _fit_and_store(
            request, rig, performer, profile.capture, principal.name, refit=True
        )
    return JSONResponse(described, status_code=201 if created else 200)


@router.delete("/performers/{performer}", summary="Delete a performer's profile", status_code=204)
async def delete_performer(request: Request, performer: str, principal: Performer) -> Response:
    _check_performer(performer)
    check_performer(principal, performer)
    try:
        await anyio.to_thread.run_sync(_profiles(request).delete, performer)
    except ProfileNotFoundError:
        raise ApiError(
            404, "performer_not_found", f"no performer profile named {performer!r}"
        ) from None
    log.info(
        "performer deleted",
        extra={"event": "performer.deleted", "performer": performer, "by": principal.name},
    )
    return Response(status_code=204)

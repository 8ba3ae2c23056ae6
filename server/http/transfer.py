"""Characters with only a neutral: ``PUT /v1/characters/{id}?expressions=transfer`` as a job.

The upload is read and checked at once (character, markers, vertex bound: 4xx before any
job exists), then answered 202 with a job record; ICT-FaceKit's ARKit shapes are carried
onto the face mesh by deformation transfer (``facecast.rig.transfer``) in the app's
transfer thread (scipy releases the GIL; one job per server, the ``storage.jobs`` slot),
written into the GLB as morph targets, and the rig is fitted on the generic ARKit set and
stored as any character. ``GET /v1/characters/{id}/job`` follows it.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import secrets
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor
from pathlib import Path
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from facecast.rig import fit
from facecast.rig.characters.character import character_example_set, load_character
from facecast.rig.errors import RigError
from facecast.rig.sources.ict import locate_ict
from facecast.rig.transfer import (
    SourceExpressions,
    TransferPlan,
    ict_source_expressions,
    plan_transfer,
    with_transferred_expressions,
)

from ..errors import ApiError, StoreClosedError
from ..guards.auth import READ_ROLES, Principal, requires
from ..heap import upload as upload_heap
from ..settings import Settings
from ..storage.archive import ArchiveError, ArchiveLimits
from ..storage.characters import character_view, pack_character
from ..storage.jobs import FINISHED
from ..storage.rig_store import RIG_ID_PATTERN, RigStore, valid_rig_id
from .character_upload import (
    character_record,
    check_character_size,
    gltf_limits,
    pairing_view,
    read_character_upload,
)
from .rigs import archive_limits, fit_slot, read_body, run_fit

__all__ = ["router", "start_transfer"]

log = logging.getLogger("facecast.server.http.transfer")

router = APIRouter(prefix="/v1", tags=["characters"])

Reader = Annotated[Principal, Depends(requires(*READ_ROLES))]


class _Interrupted(Exception):
    """The server began to stop while the job ran."""


class _Superseded(Exception):
    """The character was deleted or replaced while the job ran (its record says so)."""


#: ``app.state``'s key of a callable a transfer job calls with a stage's name as it enters
#: it ("transfer", "fit", "store"; before it changes anything in that stage). None in
#: service: it is the tests' seam to hold a job at a stage, with no sleeps.
STAGE_HOOK = "transfer_stage_hook"


def _store(request: Request) -> RigStore:
    store: RigStore = request.app.state.store
    return store


@functools.lru_cache(maxsize=1)
def _source(archive: Path) -> SourceExpressions:
    """ICT's ARKit set, read once per process (~12 MB; a second to build)."""
    return ict_source_expressions(archive)


def _source_path(settings: Settings) -> Path:
    """The ICT-FaceKit archive the settings name, or 503 ``transfer_unavailable``."""
    given = settings.transfer_source.strip()
    archive = None
    if given.lower() != "off":
        try:
            archive = locate_ict(given) if given else locate_ict()
        except (OSError, ValueError, RigError):
            archive = None
    if archive is None or not Path(archive).is_file():
        raise ApiError(
            503,
            "transfer_unavailable",
            "this server has no expressions to transfer (ICT-FaceKit's, setting "
            "transfer_source); make them with `facecast expressions CHARACTER -o FOLDER` "
            "where ICT-FaceKit is, and upload the character with its morph targets",
        )
    return Path(archive)


def transfer_available(settings: Settings) -> bool:
    """Whether this server can transfer expressions (``transfer_source`` found): what an
    upload with none may be told to ask for."""
    try:
        _source_path(settings)
    except ApiError:
        return False
    return True


def _as_upload(run: Callable[[int], None], slot: int) -> None:
    """``run(slot)`` in glibc's upload mode (heap.py): a job's arrays are an upload's."""
    with upload_heap():
        run(slot)


def _names(text: str | None) -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ApiError(422, "unknown_expression", "names: give at least one ARKit name")
    return names


async def start_transfer(
    request: Request,
    rig_id: str,
    principal: Principal,
    options: dict[str, Any],
    *,
    markers: str | None,
    names: str | None,
    rights_holder: bool = False,
) -> JSONResponse:
    """Check the upload, record a queued job and start it: 202 with the record.

    ``rights_holder``: kept in the stored character's record (``character_record``)."""
    settings: Settings = request.app.state.settings
    store = _store(request)
    archive = _source_path(settings)
    wanted = _names(names)
    with fit_slot(request, principal):  # bounds the bodies held, as for every upload
        slot = await anyio.to_thread.run_sync(store.jobs.claim)
        if slot is None:
            raise ApiError(
                503,
                "transfer_busy",
                "a deformation transfer is already running on this server (one at a time); "
                "retry when it is done",
                headers={"Retry-After": "30"},
            )
        try:
            data = await read_body(request, settings.max_upload_bytes)
            prepare = _Prepare(archive_limits(settings), store.scratch, archive, settings)
            try:
                plan, source = await run_fit(
                    request, lambda: prepare(data, markers, wanted), size=len(data)
                )
            except ArchiveError as exc:
                raise ApiError(exc.status, exc.code, str(exc)) from None
            now = time.time()
            record: dict[str, Any] = {
                "id": rig_id,
                "job": secrets.token_hex(8),
                "state": "queued",
                "stage": None,
                "progress": {"done": 0, "total": len(plan.names)},
                "expressions": list(plan.names),
                "correspondence": plan.method,
                "vertices": plan.vertices,
                "created": now,
                "updated": now,
                "error": None,
                "result": None,
            }
            await anyio.to_thread.run_sync(store.jobs.write, rig_id, record)
            job = _TransferJob(
                rig_id, record["job"], plan, source, options, store,
                request.app.state.transfer_cancel, getattr(request.app.state, STAGE_HOOK, None),
                rights_holder=rights_holder,
            )  # fmt: skip
            executor: Executor = request.app.state.transfer_executor
            # The job allocates as an upload does (heap.py), for its minutes.
            future = executor.submit(_as_upload, job.run, slot)
            # Cancelled before it ran (the server stopping): the slot is still this one's.
            future.add_done_callback(lambda f: f.cancelled() and store.jobs.release(slot))
        except BaseException:
            store.jobs.release(slot)
            raise
    log.info(
        "transfer queued",
        extra={
            "event": "character.transfer_queued",
            "rig": rig_id,
            "expressions": len(plan.names),
            "vertices": plan.vertices,
            "correspondence": plan.method,
            "by": principal.name,
        },
    )
    return JSONResponse(
        record, status_code=202, headers={"Location": f"/v1/characters/{rig_id}/job"}
    )


@router.get("/characters/{rig_id}/job", summary="A character's deformation transfer job")
async def get_job(request: Request, rig_id: str, _: Reader) -> dict[str, Any]:
    if not valid_rig_id(rig_id):
        raise ApiError(400, "invalid_rig_id", f"rig id {rig_id[:80]!r} must match {RIG_ID_PATTERN}")
    store = _store(request)
    record = await anyio.to_thread.run_sync(store.jobs.read, rig_id)
    # Nobody holds the slot, yet the record says it runs: its process died. (A job writes
    # its end before it lets go of the slot, so the record is read again under that rule.)
    if (
        record is not None
        and record.get("state") not in FINISHED
        and await anyio.to_thread.run_sync(store.jobs.slot_free)
    ):
        job = str(record.get("job"))
        interrupted = {
            "state": "failed",
            "updated": time.time(),
            "error": {
                "code": "interrupted",
                "message": "the server stopped while the job ran; upload it again",
            },
        }
        await anyio.to_thread.run_sync(lambda: store.jobs.update(rig_id, job, interrupted))
        record = await anyio.to_thread.run_sync(store.jobs.read, rig_id)
    if record is None:
        raise ApiError(
            404,
            "no_job",
            f"no transfer job for {rig_id!r} (none was started with "
            "PUT /v1/characters/{id}?expressions=transfer, or the character was deleted or "
            "replaced since, or the record was pruned)",
        )
    return record


class _Prepare:
    """Read the upload and plan the transfer (a fit thread): every 4xx before the 202."""

    def __init__(
        self, limits: ArchiveLimits, scratch: Path, archive: Path, settings: Settings
    ) -> None:
        self.limits = limits
        self.scratch = scratch
        self.archive = archive
        self.gltf = gltf_limits(settings)
        self.max_vertices = settings.max_transfer_vertices
        self.max_faces = settings.max_transfer_faces
        self.max_bytes = settings.max_character_bytes

    def __call__(
        self, data: bytes, markers: str | None, names: list[str] | None
    ) -> tuple[TransferPlan, SourceExpressions]:
        character, found = read_character_upload(data, self.limits, self.scratch, self.gltf)
        check_character_size(character, self.max_bytes)
        if found is not None and markers is not None:
            raise ApiError(
                422,
                "markers_conflict",
                "markers=auto and a markers.txt in the archive: keep the one you mean",
            )
        given: Any = found if found is not None else markers
        source = _source(self.archive)
        plan = plan_transfer(
            character,
            source,
            markers=given,
            names=names,
            max_vertices=self.max_vertices,
            max_faces=self.max_faces,
            label="the uploaded character",
        )
        # The job's file grows by its morph targets (float32 xyz a vertex and expression,
        # an accessor each): checked at the size it will be stored at, before the 202.
        check_character_size(
            character, self.max_bytes, adding=len(plan.names) * (plan.vertices * 12 + 256)
        )
        return plan, source


class _TransferJob:
    """Transfer, write the morph targets, fit and store; the record follows (a thread)."""

    def __init__(
        self,
        rig_id: str,
        job: str,
        plan: TransferPlan,
        source: SourceExpressions,
        options: dict[str, Any],
        store: RigStore,
        cancel: threading.Event,
        stage_hook: Callable[[str], object] | None = None,
        *,
        rights_holder: bool = False,
    ) -> None:
        self.rig_id = rig_id
        self.stage_hook = stage_hook
        self.rights_holder = rights_holder
        self.job = job
        self.plan = plan
        self.source = source
        self.options = options
        self.store = store
        self.cancel = cancel
        self.done = 0

    def _update(self, **changes: Any) -> None:
        """Change the record, or raise ``_Superseded`` when it is no longer this job's
        running one (the character deleted or replaced: the record says so already)."""
        if not self.store.jobs.update(self.rig_id, self.job, {**changes, "updated": time.time()}):
            raise _Superseded

    def _enter(self, stage: str) -> None:
        if self.cancel.is_set():
            raise _Interrupted
        self._update(state="running", stage=stage)
        if self.stage_hook is not None:
            self.stage_hook(stage)

    def _step(self, count: int) -> None:
        self.done += count
        if self.cancel.is_set():
            raise _Interrupted
        total = len(self.plan.names)
        self._update(progress={"done": self.done, "total": total})

    def _end(self, **changes: Any) -> None:
        # A cancelled record keeps its reason; a closed store (the server stopped) is
        # read as interrupted by the free slot.
        with contextlib.suppress(_Superseded, StoreClosedError):
            self._update(**changes)

    def run(self, slot: int) -> None:
        try:
            self._run()
        except _Superseded:
            log.info(
                "transfer cancelled",
                extra={"event": "character.transfer_cancelled", "rig": self.rig_id},
            )
        except StoreClosedError:
            pass  # the server stopped under it: the free slot marks the record interrupted
        except RigError as exc:
            self._end(state="failed", error={"code": exc.code, "message": exc.message})
        except _Interrupted:
            self._end(
                state="failed",
                error={"code": "interrupted", "message": "the server stopped; upload it again"},
            )
        except Exception as exc:  # logged once here; the record says what went wrong
            log.exception(
                "transfer failed",
                extra={"event": "character.transfer_failed", "rig": self.rig_id},
            )
            self._end(
                state="failed",
                error={"code": "internal_error", "message": f"{type(exc).__name__}"},
            )
        finally:
            self.store.jobs.release(slot)

    def _run(self) -> None:
        started = time.perf_counter()
        self._enter("transfer")
        glb, generated = with_transferred_expressions(self.plan, self.source, progress=self._step)
        transferred = time.perf_counter()
        self._enter("fit")
        character = load_character(glb, label="the character with its transferred expressions")
        example_set, report = character_example_set(character, displaced=True)
        rig = fit(example_set, **self.options)
        record = character_record(character, rights_holder=self.rights_holder)
        packed = pack_character(character.glb, record)
        self._enter("store")
        # Checked and stored in one step (the store's change lock): a character deleted
        # or uploaded anew since keeps what it has now, and the record says why.
        created = self.store.put_job_result(self.rig_id, self.job, rig, packed)
        if created is None:
            raise _Superseded
        stored = self.store.character(self.rig_id, with_glb=False)
        result = {
            "id": self.rig_id,
            "created": created,
            **rig.summary(),
            "warnings": list(rig.fit_report.get("warnings", [])),
            "pairing": pairing_view(report),
            "character": character_view(self.rig_id, rig.names, stored),
            "transfer": {
                "expressions": list(generated.names[1:]),
                "correspondence": generated.correspondence.method,
                "residual": generated.correspondence.residual,
                "seconds": {
                    **{k: round(v, 3) for k, v in generated.seconds.items()},
                    "total": round(transferred - started, 3),
                    "fit": round(time.perf_counter() - transferred, 3),
                },
            },
        }
        self._end(state="done", stage=None, result=result)
        log.info(
            "character transferred",
            extra={
                "event": "character.transferred",
                "rig": self.rig_id,
                "expressions": len(generated.names) - 1,
                "seconds": round(time.perf_counter() - started, 3),
            },
        )

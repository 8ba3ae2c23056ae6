"""Transfer job records: one JSON file per character under ``<rigs_dir>/.jobs``, and the
server-wide transfer slot.

A record is written whole (``write_atomically``) by the job as it goes; every worker
process reads the same files, so ``GET /v1/characters/{id}/job`` answers wherever it
lands. Bounded: a character's record goes with the character (``RigStore`` removes it on
delete and replace) and finished records beyond ``max_records`` are pruned. The slot is
an ``flock`` on ``.jobs/transfer.lock``: the kernel drops it when its process dies, so a
record still "running" while nobody holds the slot was interrupted. Blocking calls: run
them in a thread.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..names import valid_rig_id
from .atomic import write_atomically

__all__ = ["FINISHED", "JOBS_DIR", "JobStore"]

#: Under the rig directory.
JOBS_DIR = ".jobs"
#: States a job ends in; "queued" and "running" are the others.
FINISHED = frozenset({"done", "failed"})
_SUFFIX = ".json"
_LOCK = "transfer.lock"


class JobStore:
    """Job records in ``directory`` (``<rigs_dir>/.jobs``), temp files in ``scratch()``."""

    def __init__(self, directory: Path, *, scratch: Callable[[], Path], max_records: int) -> None:
        self.directory = Path(directory)
        self._scratch = scratch
        self.max_records = max_records

    def _path(self, rig_id: str) -> Path:
        if not valid_rig_id(rig_id):
            raise ValueError(f"invalid rig id {rig_id!r}")
        return self.directory / f"{rig_id}{_SUFFIX}"

    def read(self, rig_id: str) -> dict[str, Any] | None:
        """The record of ``rig_id``'s job, or None (none, or unreadable)."""
        try:
            record = json.loads(self._path(rig_id).read_bytes())
        except (FileNotFoundError, ValueError):
            return None
        return record if isinstance(record, dict) else None

    def write(self, rig_id: str, record: dict[str, Any]) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        data = json.dumps(record, separators=(",", ":"), allow_nan=False).encode()
        write_atomically(self.directory, self._path(rig_id).name, data, scratch=self._scratch())
        if record.get("state") in FINISHED:
            self.prune()

    def update(
        self, rig_id: str, job: str, changes: dict[str, Any], *, unfinished: bool = False
    ) -> bool:
        """Apply ``changes`` to the record if it is still job ``job``'s; whether it was.

        A record deleted or replaced meanwhile (the character deleted, or uploaded again)
        is left alone: the job's result is no longer wanted. ``unfinished``: only while
        the record is not yet done or failed (a reader marking a dead job must not
        overwrite the end a live one wrote just before it let go of the slot).
        """
        record = self.read(rig_id)
        if record is None or record.get("job") != job:
            return False
        if unfinished and record.get("state") in FINISHED:
            return False
        self.write(rig_id, {**record, **changes})
        return True

    def remove(self, rig_id: str) -> bool:
        """Delete ``rig_id``'s record; whether there was one."""
        try:
            self._path(rig_id).unlink()
        except FileNotFoundError:
            return False
        return True

    def prune(self) -> None:
        """Delete finished records beyond the newest ``max_records`` (by last update)."""
        finished = []
        for path in self.directory.glob(f"*{_SUFFIX}"):
            with contextlib.suppress(OSError, ValueError):
                record = json.loads(path.read_bytes())
                if isinstance(record, dict) and record.get("state") in FINISHED:
                    finished.append((float(record.get("updated", 0.0)), path.name, path))
        finished.sort(reverse=True)
        for _, _, path in finished[self.max_records :]:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()

    # -- the one transfer slot ----------------------------------------------------------
    def claim(self) -> int | None:
        """The fd holding the server's transfer slot, or None when a job holds it."""
        self.directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.directory / _LOCK, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        return fd

    @staticmethod
    def release(fd: int) -> None:
        os.close(fd)  # closing the only fd of the open file drops its flock

    def slot_free(self) -> bool:
        """Whether no job holds the slot now (in this process or any other)."""
        fd = self.claim()
        if fd is None:
            return False
        self.release(fd)
        return True

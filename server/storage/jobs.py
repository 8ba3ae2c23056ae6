"""Transfer job records: one JSON file per character under ``<rigs_dir>/.jobs``, and the
server-wide transfer slot.

A record is written whole (``write_atomically``) by the job as it goes; every worker
process reads the same files, so ``GET /v1/characters/{id}/job`` answers wherever it
lands. Bounded: a character's record goes with the character (``RigStore`` removes it on
delete and replace: a job still running is marked ``cancelled`` instead, saying why) and
finished records beyond ``max_records`` are pruned. The slot is an ``flock`` on
``.jobs/transfer.lock``: the kernel drops it when its process dies, so a record still
"running" while nobody holds the slot was interrupted. Every change of a record, and every
change of a character (``RigStore``'s stores and deletes), happens under ``locked()``, an
``flock`` on ``.jobs/changes.lock``: a job checks that its record is still its own and
unfinished and stores its result in one step, so a DELETE or a replace always wins.
Blocking calls: run them in a thread.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..names import valid_rig_id
from .atomic import write_atomically

__all__ = ["CANCELLED", "FINISHED", "JOBS_DIR", "JobStore"]

#: Under the rig directory.
JOBS_DIR = ".jobs"
#: A job whose character was deleted or replaced while it ran: its result is dropped.
CANCELLED = "cancelled"
#: States a job ends in; "queued" and "running" are the others.
FINISHED = frozenset({"done", "failed", CANCELLED})
_SUFFIX = ".json"
_LOCK = "transfer.lock"
_CHANGES_LOCK = "changes.lock"


class JobStore:
    """Job records in ``directory`` (``<rigs_dir>/.jobs``), temp files in ``scratch()``."""

    def __init__(self, directory: Path, *, scratch: Callable[[], Path], max_records: int) -> None:
        self.directory = Path(directory)
        self._scratch = scratch
        self.max_records = max_records
        self._held = threading.local()  # this thread's depth inside ``locked()``

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the store's change lock (all processes); re-entrant within a thread."""
        depth = getattr(self._held, "depth", 0)
        if depth:
            self._held.depth = depth + 1
            try:
                yield
            finally:
                self._held.depth = depth
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.directory / _CHANGES_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            self._held.depth = 1
            try:
                yield
            finally:
                self._held.depth = 0
        finally:
            os.close(fd)  # drops the flock

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

    def update(self, rig_id: str, job: str, changes: dict[str, Any]) -> bool:
        """Apply ``changes`` to the record if it is still job ``job``'s and unfinished;
        whether it was.

        A record deleted, replaced or cancelled meanwhile (the character deleted, or
        uploaded again) is left alone: the job's result is no longer wanted. A finished
        record never changes again (a reader marking a dead job must not overwrite the end
        a live one wrote just before it let go of the slot).
        """
        with self.locked():
            if not self.is_running(rig_id, job):
                return False
            record = self.read(rig_id)
            assert record is not None  # is_running, under the lock
            self.write(rig_id, {**record, **changes})
            return True

    def is_running(self, rig_id: str, job: str) -> bool:
        """Whether ``rig_id``'s record is job ``job``'s and unfinished (hold ``locked()``
        for the answer to stay true)."""
        record = self.read(rig_id)
        return (
            record is not None and record.get("job") == job and record.get("state") not in FINISHED
        )

    def settle(self, rig_id: str, *, deleted: bool) -> bool:
        """The character ``rig_id`` is being deleted (or replaced): a running job's record
        becomes ``cancelled`` with the reason, a finished one goes; whether there was one.

        Callers hold ``locked()`` around this and the change itself.
        """
        with self.locked():
            record = self.read(rig_id)
            if record is None or record.get("state") in FINISHED:
                return self.remove(rig_id)
            what = "deleted" if deleted else "replaced"
            self.write(
                rig_id,
                {
                    **record,
                    "state": CANCELLED,
                    "stage": None,
                    "updated": time.time(),
                    "error": {
                        "code": f"character_{what}",
                        "message": f"the character was {what} while the job ran; its result "
                        "was dropped",
                    },
                },
            )
            return True

    def remove(self, rig_id: str) -> bool:
        """Delete ``rig_id``'s record; whether there was one."""
        with self.locked():
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

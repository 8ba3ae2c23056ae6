"""The rig store: fitted rigs as ``<id>.rig`` files in one directory, with an in-memory cache.

Writes are atomic (temp file, fsync, rename, fsync dir) so a crash leaves the old or the
new rig; every read re-stats, so other worker processes' changes are seen. Temp files
(rig writes, unpacked uploads) live in the store's scratch directory, which a later
start cleans. Blocking calls: run them in a thread, never on the event loop.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import secrets
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from facecast.protocol import Limits
from facecast.rig.errors import RigFileError
from facecast.rig.io.gltf import export_glb
from facecast.rig.rigfile import rig_from_bytes

from ..errors import RigNotFoundError, StoreClosedError
from ..names import (
    NAME_PATTERN,
    PERFORMER_SEPARATOR,
    RIG_ID_PATTERN,
    performer_rig_id,
    valid_name,
    valid_rig_id,
)
from .atomic import fsync_directory, write_atomically
from .characters import CHARACTER_SUFFIX, PackedCharacter, StoredCharacter, unpack_character
from .jobs import JOBS_DIR, JobStore

if TYPE_CHECKING:
    from facecast.rig.rig import Rig

__all__ = [
    "NAME_PATTERN",
    "PERFORMER_SEPARATOR",
    "RIG_ID_PATTERN",
    "RigInfo",
    "RigNotFoundError",
    "RigStore",
    "StoreClosedError",
    "check_servable",
    "fsync_directory",
    "performer_rig_id",
    "valid_name",
    "valid_rig_id",
    "write_atomically",
]

SUFFIX = ".rig"
#: Under the rig directory: one folder per live store (process), holding its temp files.
SCRATCH_DIR = ".scratch"
#: In each such folder, a file its store holds an exclusive ``flock`` on while it lives:
#: the kernel drops the lock when the process dies, kill -9 included, so any store that
#: can take the lock knows the folder is a dead one's leftovers.
_LOCK_NAME = ".lock"
#: Temp files of facecast versions that wrote them beside the rigs; removed at start-up
#: once older than this (they cannot be told from a live writer's otherwise).
_TEMP_PREFIX = ".tmp-"
_STALE_TEMP_SECONDS = 3600.0
#: A scratch folder without its lock file is being created, or its creator died doing so.
_UNLOCKED_GRACE_SECONDS = 60.0
#: Removals of the scratch folder at close, for a thread still writing into it.
_CLOSE_TRIES = 5


def check_servable(rig: Rig, limits: Limits, source: str) -> None:
    """Raise ``RigFileError`` (``rig_exceeds_limits``) for a rig the protocol cannot carry.

    A rig is only worth storing if its ``ready`` and results fit PROTOCOL.md §7 as every
    client decodes it: K <= max_points, V <= max_vertices, M <= max_names, and every
    example name at most max_string characters.
    """
    problems = []
    if rig.num_points > limits.max_points:
        problems.append(f"K={rig.num_points} feature points (max_points {limits.max_points})")
    if rig.num_vertices > limits.max_vertices:
        problems.append(f"V={rig.num_vertices} vertices (max_vertices {limits.max_vertices})")
    if rig.num_examples > limits.max_names:
        problems.append(f"M={rig.num_examples} examples (max_names {limits.max_names})")
    long = [name for name in rig.names if len(name) > limits.max_string]
    if long:
        problems.append(
            f"{len(long)} example name(s) over {limits.max_string} characters "
            f"(the first: {long[0][:40]!r}...)"
        )
    if problems:
        raise RigFileError(
            f"{source} cannot be streamed: " + "; ".join(problems) + " (PROTOCOL.md §7)",
            code="rig_exceeds_limits",
        )


@dataclass(frozen=True)
class RigInfo:
    id: str
    size: int
    modified: float  # POSIX seconds


@dataclass
class _Entry:
    key: tuple[int, int, int]  # (inode, size, mtime_ns): changes on every replace
    rig: Rig
    glb: bytes | None = None


class RigStore:
    """Rig files in ``directory``; ``cache_size`` loaded rigs kept per process.

    ``max_rig_bytes`` bounds a rig file's unpacked size; ``jobs`` holds transfer job
    records (``max_job_records`` finished ones), a character's settled when the character
    is deleted or replaced (``JobStore.settle``). Thread-safe; a rig id must satisfy ``valid_rig_id`` (callers check it first and
    answer with their own error; here an invalid id is a ``ValueError``).
    """

    def __init__(
        self,
        directory: Path,
        *,
        cache_size: int = 16,
        max_rig_bytes: int = 1 << 30,
        max_job_records: int = 64,
    ) -> None:
        self.directory = Path(directory)
        self.cache_size = cache_size
        self.max_rig_bytes = max_rig_bytes
        self._cache: OrderedDict[str, _Entry] = OrderedDict()
        self._lock = threading.Lock()
        #: What a stored rig must fit: the protocol's limits, as every client decodes.
        self.limits = Limits()
        self._scratch: Path | None = None
        self._scratch_lock: int | None = None  # the fd holding the scratch folder's flock
        self._closed = False
        self.jobs = JobStore(
            self.directory / JOBS_DIR, scratch=lambda: self.scratch, max_records=max_job_records
        )

    # -- lifecycle ----------------------------------------------------------------------
    def open(self) -> None:
        """Create the directory if needed and remove what killed processes left behind.

        Every scratch folder no live store holds (partial rig writes, unpacked uploads of
        a process killed mid-request) goes, at once; legacy ``.tmp-*`` files after an hour.
        """
        with self._lock:
            self._closed = False
        self.directory.mkdir(parents=True, exist_ok=True)
        now = time.time()
        for path in self.directory.glob(f"{_TEMP_PREFIX}*"):
            with contextlib.suppress(OSError):
                if now - path.stat().st_mtime > _STALE_TEMP_SECONDS:
                    path.unlink()
        root = self.directory / SCRATCH_DIR
        root.mkdir(exist_ok=True)
        for folder in root.iterdir():
            if folder != self._scratch:
                _remove_if_abandoned(folder, now)
        _ = self.scratch

    def close(self) -> None:
        """Remove this store's scratch folder and release it (at shutdown).

        Closed for good: ``scratch`` then raises ``StoreClosedError``, so work the server
        abandons (a parse, a transfer job: daemon threads) can neither make a new scratch
        folder nor write through one. One such thread may still be writing into the old
        folder as it goes: removed again until it is gone (a few tries).
        """
        with self._lock:
            scratch, fd = self._scratch, self._scratch_lock
            self._scratch = self._scratch_lock = None
            self._closed = True
        if scratch is not None:
            for _ in range(_CLOSE_TRIES):
                shutil.rmtree(scratch, ignore_errors=True)
                if not scratch.exists():
                    break
        if fd is not None:
            os.close(fd)

    @property
    def scratch(self) -> Path:
        """This store's own folder for temp files (created, and locked, on first use);
        ``StoreClosedError`` once the store is closed."""
        with self._lock:
            if self._closed:
                raise StoreClosedError("the rig store is closed: the server is stopping")
            if self._scratch is None:
                self._scratch, self._scratch_lock = _claim_scratch(self.directory / SCRATCH_DIR)
            return self._scratch

    def check_readable(self) -> None:
        """Raise ``OSError`` unless the directory can be listed and written."""
        if not self.directory.is_dir():
            raise FileNotFoundError(f"rig directory {self.directory} does not exist")
        if not os.access(self.directory, os.R_OK | os.W_OK | os.X_OK):
            raise PermissionError(f"rig directory {self.directory} is not readable and writable")
        next(iter(os.scandir(self.directory)), None)

    # -- queries ------------------------------------------------------------------------
    def list(self) -> list[RigInfo]:
        infos = []
        with os.scandir(self.directory) as entries:
            for entry in entries:
                name = entry.name
                if not name.endswith(SUFFIX) or name.startswith("."):
                    continue
                rig_id = name[: -len(SUFFIX)]
                if not valid_rig_id(rig_id):
                    continue
                try:
                    st = entry.stat()
                except FileNotFoundError:  # deleted while listing
                    continue
                infos.append(RigInfo(rig_id, st.st_size, st.st_mtime))
        infos.sort(key=lambda info: info.id)
        return infos

    def exists(self, rig_id: str) -> bool:
        return self._path(rig_id).is_file()

    def get(self, rig_id: str) -> Rig:
        """The loaded rig, from the cache unless the file changed since it was loaded."""
        return self._load(rig_id).rig

    def get_bytes(self, rig_id: str) -> bytes:
        try:
            return self._path(rig_id).read_bytes()
        except FileNotFoundError:
            raise RigNotFoundError(rig_id) from None

    def glb(self, rig_id: str) -> bytes:
        """The target mesh with every example as a morph target, built once per rig version."""
        entry = self._load(rig_id)
        if entry.glb is None:
            rig = entry.rig
            m, v = rig.num_examples, rig.num_vertices
            entry.glb = export_glb(
                rig.target_neutral,
                rig.target_faces,
                rig.target_deltas.reshape(m, v, 3),
                list(rig.names),
            )
        return entry.glb

    # -- changes ------------------------------------------------------------------------
    def put_bytes(self, rig_id: str, data: bytes) -> tuple[Rig, bool]:
        """Validate ``data`` as a rig file and store it; returns ``(rig, created)``.

        Raises ``RigFileError`` (nothing written) when ``data`` is not a valid rig, or
        one the protocol cannot carry (``check_servable``).
        """
        rig = rig_from_bytes(data, source=f"rig {rig_id!r}", max_bytes=self.max_rig_bytes)
        check_servable(rig, self.limits, f"rig {rig_id!r}")
        with self.jobs.locked():
            self.jobs.settle(rig_id, deleted=False)
            self._remove_character(rig_id)
            created = self._write(rig_id, data)
        return rig, created

    def put_rig(self, rig_id: str, rig: Rig, *, character: PackedCharacter | None = None) -> bool:
        """Store a fitted rig, with its character file or without one; returns whether the id is new.

        ``character`` (``characters.pack_character``'s bytes) is written first, then
        the rig, each atomically; without one, a character the id had is removed, so a
        rig never shows another rig's file. The id's transfer job is settled (a finished
        one's record goes, a running one is cancelled: the character was replaced).
        Raises ``RigFileError`` (nothing written) for a rig the protocol cannot carry.
        """
        check_servable(rig, self.limits, f"rig {rig_id!r}")
        with self.jobs.locked():
            self.jobs.settle(rig_id, deleted=False)
            return self._store(rig_id, rig, character)

    def put_job_result(
        self, rig_id: str, job: str, rig: Rig, character: PackedCharacter
    ) -> bool | None:
        """Store transfer job ``job``'s rig and character if its record is still its own
        and running; whether the id is new, or None (deleted or replaced meanwhile:
        nothing written). Check and store are one step under the change lock, so a DELETE
        or a replace is either seen here or comes after, and wins either way.
        """
        check_servable(rig, self.limits, f"rig {rig_id!r}")
        with self.jobs.locked():
            if not self.jobs.is_running(rig_id, job):
                return None
            return self._store(rig_id, rig, character)

    def _store(self, rig_id: str, rig: Rig, character: PackedCharacter | None) -> bool:
        if character is None:
            self._remove_character(rig_id)
        else:
            write_atomically(
                self.directory, f"{rig_id}{CHARACTER_SUFFIX}", character, scratch=self.scratch
            )
        return self._write(rig_id, rig.write)  # array by array: no copy of the rig

    def character(self, rig_id: str, *, with_glb: bool = True) -> StoredCharacter | None:
        """The character stored beside rig ``rig_id``; ``None`` when it has none or it is unreadable.

        ``with_glb=False``: its record only (``characters.unpack_character``).
        """
        self._path(rig_id)  # validates the id
        try:
            fh = (self.directory / f"{rig_id}{CHARACTER_SUFFIX}").open("rb")
        except FileNotFoundError:
            return None
        with fh:
            try:
                return unpack_character(fh, with_glb=with_glb)
            except ValueError:
                return None

    def open_character(self, rig_id: str) -> tuple[StoredCharacter, BinaryIO, int] | None:
        """The character's record (``glb`` empty), its file open at the GLB and the GLB's
        size, for streaming; ``None`` as ``character``. The caller closes the file; a
        replace meanwhile leaves it reading the version it opened."""
        self._path(rig_id)  # validates the id
        try:
            fh = (self.directory / f"{rig_id}{CHARACTER_SUFFIX}").open("rb")
        except FileNotFoundError:
            return None
        try:
            stored = unpack_character(fh, with_glb=False)
            size = os.fstat(fh.fileno()).st_size - fh.tell()
        except (ValueError, OSError):
            fh.close()
            return None
        return stored, fh, size

    def open_rig_file(self, rig_id: str) -> tuple[BinaryIO, int]:
        """The rig file open for streaming and its size; ``RigNotFoundError``."""
        try:
            fh = self._path(rig_id).open("rb")
        except FileNotFoundError:
            raise RigNotFoundError(rig_id) from None
        return fh, os.fstat(fh.fileno()).st_size

    def delete(self, rig_id: str) -> None:
        """Delete the rig, its character and its transfer job record (a job still running
        is cancelled: its record says so, and its result is never stored);
        ``RigNotFoundError`` when there was none of rig and record."""
        path = self._path(rig_id)
        with self.jobs.locked():
            had_job = self.jobs.settle(rig_id, deleted=True)
            try:
                path.unlink()
            except FileNotFoundError:
                if not had_job:
                    raise RigNotFoundError(rig_id) from None
            self._remove_character(rig_id)
            fsync_directory(self.directory)
        with self._lock:
            self._cache.pop(rig_id, None)

    # -- internals ----------------------------------------------------------------------
    def _path(self, rig_id: str) -> Path:
        if not valid_rig_id(rig_id):
            raise ValueError(f"invalid rig id {rig_id!r}")
        return self.directory / f"{rig_id}{SUFFIX}"

    def _remove_character(self, rig_id: str) -> None:
        self._path(rig_id)  # validates the id
        with contextlib.suppress(FileNotFoundError):
            (self.directory / f"{rig_id}{CHARACTER_SUFFIX}").unlink()

    def _write(self, rig_id: str, data: bytes | Callable[[BinaryIO], None]) -> bool:
        self._path(rig_id)  # validates the id
        return write_atomically(self.directory, f"{rig_id}{SUFFIX}", data, scratch=self.scratch)

    def _load(self, rig_id: str) -> _Entry:
        path = self._path(rig_id)
        try:
            fh = path.open("rb")
        except FileNotFoundError:
            raise RigNotFoundError(rig_id) from None
        with fh:
            # fstat on the open file: the key describes exactly the bytes read below,
            # even if another process replaces the file meanwhile.
            st = os.fstat(fh.fileno())
            key = (st.st_ino, st.st_size, st.st_mtime_ns)
            with self._lock:
                entry = self._cache.get(rig_id)
                if entry is not None and entry.key == key:
                    self._cache.move_to_end(rig_id)
                    return entry
            data = fh.read()
        rig = rig_from_bytes(data, source=f"rig {rig_id!r}", max_bytes=self.max_rig_bytes)
        # A file put in the directory by hand is held to what an upload is.
        check_servable(rig, self.limits, f"rig {rig_id!r}")
        entry = _Entry(key, rig)
        with self._lock:
            self._cache[rig_id] = entry
            self._cache.move_to_end(rig_id)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return entry


def _claim_scratch(root: Path) -> tuple[Path, int]:
    """A new scratch folder under ``root`` and the fd holding the flock on its lock file.

    The lock file is created and locked under a temporary name, then renamed into place,
    so a lock file that can be seen is already held while its process lives.
    """
    root.mkdir(parents=True, exist_ok=True)
    folder = root / f"{os.getpid()}-{secrets.token_hex(6)}"
    folder.mkdir()
    pending = folder / f".pending-{secrets.token_hex(4)}"
    fd = os.open(pending, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.rename(pending, folder / _LOCK_NAME)
    return folder, fd


def _remove_if_abandoned(folder: Path, now: float) -> None:
    """Delete a scratch folder whose store is gone (its lock free); keep live ones."""
    try:
        fd = os.open(folder / _LOCK_NAME, os.O_RDONLY)
    except NotADirectoryError:
        with contextlib.suppress(OSError):
            folder.unlink()
        return
    except FileNotFoundError:
        with contextlib.suppress(OSError):
            if now - folder.stat().st_mtime > _UNLOCKED_GRACE_SECONDS:
                shutil.rmtree(folder, ignore_errors=True)
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return  # its store is alive
        shutil.rmtree(folder, ignore_errors=True)
    finally:
        os.close(fd)

"""The rig store: fitted rigs as ``<id>.rig`` files in one directory, with an in-memory cache.

Writes are atomic (temp file, fsync, rename, fsync dir) so a crash leaves the old or the
new rig; every read re-stats, so other worker processes' changes are seen. Blocking
calls: run them in a thread, never on the event loop.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from facecast.rig.rig import Rig

__all__ = [
    "NAME_PATTERN",
    "PERFORMER_SEPARATOR",
    "RIG_ID_PATTERN",
    "RigInfo",
    "RigNotFoundError",
    "RigStore",
    "fsync_directory",
    "performer_rig_id",
    "valid_name",
    "valid_rig_id",
    "write_atomically",
]

#: A plain rig id, and a performer's name.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
#: Joins a character's rig id and a performer's name into the id of the rig fitted on that
#: performer's own expressions (``ict@alice``; see server/SERVER.md, "Performers").
PERFORMER_SEPARATOR = "@"
RIG_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}(@[A-Za-z0-9][A-Za-z0-9._-]{0,63})?$"
_RIG_ID = re.compile(RIG_ID_PATTERN)
_NAME = re.compile(NAME_PATTERN)
SUFFIX = ".rig"
_TEMP_PREFIX = ".tmp-"
#: Temp files older than this at start-up are leftovers of a killed writer.
_STALE_TEMP_SECONDS = 3600.0


class RigNotFoundError(LookupError):
    def __init__(self, rig_id: str) -> None:
        super().__init__(f"no rig with id {rig_id!r}")
        self.rig_id = rig_id


def valid_rig_id(rig_id: str) -> bool:
    """A plain id (``ict``) or a performer rig's (``ict@alice``)."""
    # fullmatch: ``$`` alone would accept a trailing newline.
    return _RIG_ID.fullmatch(rig_id) is not None


def valid_name(name: str) -> bool:
    """A plain rig id or a performer's name: no separator."""
    return _NAME.fullmatch(name) is not None


def performer_rig_id(rig_id: str, performer: str) -> str:
    """The id of ``rig_id`` refitted on ``performer``'s expressions (both plain names)."""
    if not (valid_name(rig_id) and valid_name(performer)):
        raise ValueError(f"not plain names: {rig_id!r}, {performer!r}")
    return f"{rig_id}{PERFORMER_SEPARATOR}{performer}"


def write_atomically(directory: Path, name: str, data: bytes) -> bool:
    """Write ``directory / name`` whole or not at all; returns whether it is new.

    Temp file, fsync, rename, fsync of the directory: a crash leaves the old file or the
    new one, and concurrent writers of one name each replace whole files (last one wins).
    """
    path = directory / name
    existed = path.exists()
    temp = directory / f"{_TEMP_PREFIX}{name}-{secrets.token_hex(6)}"
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            temp.unlink()
        raise
    fsync_directory(directory)
    return not existed


def fsync_directory(directory: Path) -> None:
    """Make a rename or unlink in ``directory`` durable (else a power cut could lose it)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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

    ``max_rig_bytes`` bounds a rig file's unpacked size. Thread-safe; a rig id must satisfy ``valid_rig_id`` (callers check it first and
    answer with their own error; here an invalid id is a ``ValueError``).
    """

    def __init__(
        self, directory: Path, *, cache_size: int = 16, max_rig_bytes: int = 1 << 30
    ) -> None:
        self.directory = Path(directory)
        self.cache_size = cache_size
        self.max_rig_bytes = max_rig_bytes
        self._cache: OrderedDict[str, _Entry] = OrderedDict()
        self._lock = threading.Lock()

    # -- lifecycle ----------------------------------------------------------------------
    def open(self) -> None:
        """Create the directory if needed and remove stale temp files of killed writers."""
        self.directory.mkdir(parents=True, exist_ok=True)
        now = time.time()
        for path in self.directory.glob(f"{_TEMP_PREFIX}*"):
            with contextlib.suppress(OSError):
                if now - path.stat().st_mtime > _STALE_TEMP_SECONDS:
                    path.unlink()

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
            from facecast.rig.gltf import export_glb

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

        Raises ``RigFileError`` (nothing written) when ``data`` is not a valid rig.
        """
        from facecast.rig.rigfile import rig_from_bytes

        rig = rig_from_bytes(data, source=f"rig {rig_id!r}", max_bytes=self.max_rig_bytes)
        created = self._write(rig_id, data)
        return rig, created

    def put_rig(self, rig_id: str, rig: Rig) -> bool:
        """Store a fitted rig; returns whether the id is new."""
        return self._write(rig_id, rig.to_bytes())

    def delete(self, rig_id: str) -> None:
        path = self._path(rig_id)
        try:
            path.unlink()
        except FileNotFoundError:
            raise RigNotFoundError(rig_id) from None
        fsync_directory(self.directory)
        with self._lock:
            self._cache.pop(rig_id, None)

    # -- internals ----------------------------------------------------------------------
    def _path(self, rig_id: str) -> Path:
        if not valid_rig_id(rig_id):
            raise ValueError(f"invalid rig id {rig_id!r}")
        return self.directory / f"{rig_id}{SUFFIX}"

    def _write(self, rig_id: str, data: bytes) -> bool:
        self._path(rig_id)  # validates the id
        return write_atomically(self.directory, f"{rig_id}{SUFFIX}", data)

    def _load(self, rig_id: str) -> _Entry:
        from facecast.rig.rigfile import rig_from_bytes

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
        entry = _Entry(
            key, rig_from_bytes(data, source=f"rig {rig_id!r}", max_bytes=self.max_rig_bytes)
        )
        with self._lock:
            self._cache[rig_id] = entry
            self._cache.move_to_end(rig_id)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return entry

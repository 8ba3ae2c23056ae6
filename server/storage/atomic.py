"""Files written whole or not at all, for every store under the rig directory.

A temp file in the writer's scratch folder, fsync, rename, fsync of the directory; no
knowledge of what the bytes are.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO

__all__ = ["fsync_directory", "write_atomically"]


def write_atomically(
    directory: Path,
    name: str,
    data: bytes | Sequence[bytes] | Callable[[BinaryIO], None],
    *,
    scratch: Path,
) -> bool:
    """Write ``directory / name`` whole or not at all (``data``, its parts one after the
    other, or what a function writes to the open file: a rig written array by array, not
    copied into bytes first); returns whether it is new.

    Temp file in ``scratch`` (a rig store's scratch folder, on the same file system, so
    the rename stays atomic and a writer killed mid-write leaves nothing the next start
    does not remove), fsync, rename, fsync of the directory: a crash leaves the old file
    or the new one, and concurrent writers of one name each replace whole files (last one
    wins).
    """
    path = directory / name
    existed = path.exists()
    temp = scratch / f"{name}-{secrets.token_hex(6)}"
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(data):
                data(fh)
            else:
                for part in (data,) if isinstance(data, bytes) else data:
                    fh.write(part)
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

"""Safe extraction of uploaded example-set archives (zip, tar, tar.gz) into a folder.

Rejects absolute paths, ``..``, links and devices, too many members, and too many
(actually read, not declared) uncompressed bytes or too high a compression ratio. No HTTP.
"""

from __future__ import annotations

import gzip
import io
import stat
import tarfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from _typeshed import WriteableBuffer


from ..errors import ArchiveError

__all__ = ["ArchiveError", "ArchiveLimits", "extract_archive", "find_example_root"]

_CHUNK = 1 << 16
#: Longest path component (bytes of UTF-8): NAME_MAX of every common file system.
MAX_NAME_BYTES = 255
#: Longest member path (bytes of UTF-8) below the destination: far under PATH_MAX (4096)
#: whatever the destination's own path, and ample for any example set.
MAX_PATH_BYTES = 1024
#: Below this many extracted bytes the ratio check is off: tar's block padding alone
#: makes small, legitimate archives compress far beyond any sane bomb threshold.
_RATIO_FLOOR = 1 << 20


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int
    max_extracted_bytes: int
    max_compression_ratio: float


class _Budget:
    """Counts bytes actually extracted against the size and ratio limits."""

    def __init__(self, limits: ArchiveLimits, archive_size: int) -> None:
        self.limits = limits
        self.archive_size = max(archive_size, 1)
        self.extracted = 0
        self.members = 0

    def member(self) -> None:
        self.members += 1
        if self.members > self.limits.max_members:
            raise ArchiveError(
                413,
                "archive_too_many_members",
                f"archive has more than {self.limits.max_members} members",
            )

    def consume(self, n: int) -> None:
        self.extracted += n
        if self.extracted > self.limits.max_extracted_bytes:
            raise ArchiveError(
                413,
                "archive_too_large",
                f"archive unpacks to more than {self.limits.max_extracted_bytes} bytes",
            )
        ratio = self.extracted / self.archive_size
        if self.extracted > _RATIO_FLOOR and ratio > self.limits.max_compression_ratio:
            raise ArchiveError(
                413,
                "archive_ratio",
                f"archive expands more than {self.limits.max_compression_ratio:g}x "
                "(a compression bomb?)",
            )


def _safe_relative(name: str) -> PurePosixPath | None:
    """The member's path relative to the destination, ``None`` for the root itself.

    Raises ``ArchiveError`` for any name that could land outside the destination.
    """
    bad = (
        not name
        or "\x00" in name
        or "\\" in name
        or name.startswith("/")
        or (len(name) >= 2 and name[1] == ":")  # C:foo, a drive on Windows-made archives
    )
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if bad or ".." in parts:
        raise ArchiveError(
            400, "unsafe_archive_member", f"archive member {name[:80]!r} has an unsafe path"
        )
    encoded = [p.encode("utf-8", "surrogateescape") for p in parts]
    if any(len(p) > MAX_NAME_BYTES for p in encoded) or len(b"/".join(encoded)) > MAX_PATH_BYTES:
        raise ArchiveError(
            400,
            "archive_member_name_too_long",
            f"archive member {name[:80]!r}... has a path over {MAX_PATH_BYTES} bytes or a name "
            f"over {MAX_NAME_BYTES}",
        )
    return PurePosixPath(*parts) if parts else None


def _conflict(relative: PurePosixPath) -> ArchiveError:
    return ArchiveError(
        400,
        "archive_member_conflict",
        f"archive member {str(relative)[:80]!r} clashes with another: a file and a folder "
        "of the same name",
    )


def _make_dir(dest: Path, relative: PurePosixPath) -> None:
    try:
        dest.joinpath(*relative.parts).mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        # "x" is a file and "x/" or "x/y/" wants it as a folder.
        raise _conflict(relative) from None


def _write_member(dest: Path, relative: PurePosixPath, source: IO[bytes], budget: _Budget) -> None:
    if relative.parent.parts:
        _make_dir(dest, relative.parent)
    target = dest.joinpath(*relative.parts)
    if target.is_dir():
        raise _conflict(relative)
    try:
        # "x" (O_EXCL): a member twice is refused, never silently overwritten.
        out = target.open("xb")
    except FileExistsError:
        raise ArchiveError(
            400, "duplicate_archive_member", f"archive member {str(relative)[:80]!r} twice"
        ) from None
    with out:
        while chunk := source.read(_CHUNK):
            budget.consume(len(chunk))
            out.write(chunk)


def _extract_zip(data: bytes, dest: Path, budget: _Budget) -> None:
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise ArchiveError(400, "bad_archive", f"not a readable zip archive ({exc})") from None
    with archive:
        infos = archive.infolist()
        if len(infos) > budget.limits.max_members:
            budget.members = len(infos) - 1
            budget.member()
        for info in infos:
            budget.member()
            mode = info.external_attr >> 16
            kind = stat.S_IFMT(mode)
            relative = _safe_relative(info.filename)
            if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise ArchiveError(
                    400,
                    "unsafe_archive_member",
                    f"archive member {info.filename!r} is a link or device, not a file",
                )
            if info.is_dir() or kind == stat.S_IFDIR:
                if relative is not None:
                    _make_dir(dest, relative)
                continue
            if relative is None:
                raise ArchiveError(400, "unsafe_archive_member", "archive member with no name")
            try:
                with archive.open(info) as source:
                    _write_member(dest, relative, source, budget)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                raise ArchiveError(
                    400, "bad_archive", f"archive member {info.filename!r} is corrupt ({exc})"
                ) from None


class _LimitedReader(io.RawIOBase):
    """A decompressed stream that refuses to yield more than the budget allows.

    tar skips unwanted members by reading through them, so the decompressed stream
    itself must be bounded, not only the bytes we write.
    """

    def __init__(self, raw: io.BufferedIOBase, budget: _Budget, slack: int) -> None:
        self.raw = raw
        self.budget = budget
        self.read_total = 0
        self.limit = budget.limits.max_extracted_bytes + slack

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: WriteableBuffer) -> int:
        view = memoryview(buffer).cast("B")
        data = self.raw.read(min(len(view), _CHUNK))
        self.read_total += len(data)
        if self.read_total > self.limit:
            raise ArchiveError(
                413,
                "archive_too_large",
                f"archive unpacks to more than {self.budget.limits.max_extracted_bytes} bytes",
            )
        ratio = self.read_total / self.budget.archive_size
        if self.read_total > _RATIO_FLOOR and ratio > self.budget.limits.max_compression_ratio:
            raise ArchiveError(
                413,
                "archive_ratio",
                f"archive expands more than {self.budget.limits.max_compression_ratio:g}x "
                "(a compression bomb?)",
            )
        view[: len(data)] = data
        return len(data)


def _extract_tar(data: bytes, dest: Path, budget: _Budget, compressed: bool) -> None:
    raw = gzip.GzipFile(fileobj=io.BytesIO(data)) if compressed else io.BytesIO(data)
    # Headers and padding: two 512-byte blocks per member plus the end-of-archive blocks.
    slack = 1024 * (budget.limits.max_members + 1) + 20480
    stream = io.BufferedReader(_LimitedReader(raw, budget, slack))
    try:
        with tarfile.open(fileobj=stream, mode="r|") as archive:
            for member in archive:
                budget.member()
                relative = _safe_relative(member.name)
                if member.isdir():
                    if relative is not None:
                        _make_dir(dest, relative)
                    continue
                if not member.isreg():
                    raise ArchiveError(
                        400,
                        "unsafe_archive_member",
                        f"archive member {member.name!r} is a link or device, not a file",
                    )
                if relative is None:
                    raise ArchiveError(400, "unsafe_archive_member", "archive member with no name")
                source = archive.extractfile(member)
                if source is None:  # pragma: no cover - isreg() members always have data
                    continue
                _write_member(dest, relative, source, budget)
    except (tarfile.TarError, gzip.BadGzipFile, zlib.error, EOFError) as exc:
        raise ArchiveError(400, "bad_archive", f"not a readable tar archive ({exc})") from None


def extract_archive(data: bytes, dest: Path, limits: ArchiveLimits) -> None:
    """Extract a zip, tar or tar.gz archive held in ``data`` into the empty folder ``dest``.

    Raises
    ------
    ArchiveError
        415 ``unsupported_archive`` for anything else; 400 ``bad_archive`` /
        ``unsafe_archive_member``; 413 ``archive_too_large`` / ``archive_ratio`` /
        ``archive_too_many_members`` when a limit is crossed (checked while extracting).
    """
    budget = _Budget(limits, len(data))
    if data[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        _extract_zip(data, dest, budget)
    elif data[:2] == b"\x1f\x8b":
        _extract_tar(data, dest, budget, compressed=True)
    elif data[257:262] == b"ustar":
        _extract_tar(data, dest, budget, compressed=False)
    else:
        raise ArchiveError(415, "unsupported_archive", "body is not a zip, tar or tar.gz archive")


def find_example_root(dest: Path) -> Path:
    """The folder holding ``facecast.toml``: ``dest`` itself or its single subfolder."""
    if (dest / "facecast.toml").is_file():
        return dest
    children = [p for p in dest.iterdir() if not p.name.startswith(".")]
    if len(children) == 1 and (children[0] / "facecast.toml").is_file():
        return children[0]
    raise ArchiveError(
        422,
        "bad_example_set",
        "archive has no facecast.toml at its top level or in its single top folder",
    )

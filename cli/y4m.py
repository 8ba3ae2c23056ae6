"""YUV4MPEG2 (.y4m) video files, read frame by frame as raw planar 8-bit YUV.

The header is validated up front and every frame located before any is read; frames are
returned as their bytes, never converted to RGB here (``facecast track`` hands them to
Chromium, which converts them as it converts its camera's frames). Reads only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

from facecast.errors import FacecastError

__all__ = ["ACCEPTED", "Y4MError", "Y4MVideo", "open_y4m"]

_MAGIC = b"YUV4MPEG2"
#: A header or a frame header longer than this is not a Y4M file.
MAX_HEADER_BYTES = 4096
#: Frame sizes beyond this are refused (16384 x 16384 would be 400 MB a frame at 4:2:0).
MAX_SIDE = 8192
#: Y4M colour spaces read (the ``C`` tag; none means 420jpeg) -> the planar layout, as
#: WebCodecs names it, and the chroma planes' subsampling (x, y).
ACCEPTED: dict[str, tuple[str, int, int]] = {
    "420jpeg": ("I420", 2, 2),
    "420paldv": ("I420", 2, 2),
    "420mpeg2": ("I420", 2, 2),
    "420": ("I420", 2, 2),
    "422": ("I422", 2, 1),
    "444": ("I444", 1, 1),
}
_ACCEPTED_TEXT = (
    "facecast track reads YUV4MPEG2 (.y4m) video, 8-bit 4:2:0, 4:2:2 or 4:4:4 (C420jpeg, "
    "C420paldv, C420mpeg2, C420, C422, C444); convert others with, e.g., "
    "ffmpeg -i VIDEO -pix_fmt yuv420p OUT.y4m"
)


class Y4MError(FacecastError, ValueError):
    """Not a Y4M video this reader takes, or a damaged one; ``code`` says which."""

    code: str = "bad_video"

    def __init__(self, message: str, *, code: str = "bad_video") -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True, eq=False)
class Y4MVideo:
    """A located Y4M file: its geometry, rate and where each frame's bytes start.

    Attributes
    ----------
    format : str
        The frames' planar layout as WebCodecs names it: ``I420``, ``I422`` or ``I444``.
    colour : str
        The file's ``C`` tag (``420jpeg`` when absent).
    frame_bytes : int
        Bytes of one frame's Y, U and V planes.
    offsets : tuple of int
        File offset of each frame's first byte of Y.
    """

    path: Path
    width: int
    height: int
    fps: float
    format: str
    colour: str
    frame_bytes: int
    offsets: tuple[int, ...]

    @property
    def num_frames(self) -> int:
        return len(self.offsets)

    def read(self, index: int) -> bytes:
        """Frame ``index``'s planes (Y, then U, then V), ``frame_bytes`` long."""
        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} of {self.num_frames}")
        with self.path.open("rb") as handle:
            handle.seek(self.offsets[index])
            data = handle.read(self.frame_bytes)
        if len(data) != self.frame_bytes:  # the file changed since it was located
            raise Y4MError(f"{self.path}: frame {index} is truncated", code="truncated_video")
        return data


def _parse_fps(value: str, path: Path) -> float:
    try:
        num, _, den = value.partition(":")
        rate = Fraction(int(num), int(den or "1"))
    except (ValueError, ZeroDivisionError):
        raise Y4MError(f"{path}: frame rate F{value} is not N:D") from None
    if not (rate > 0 and math.isfinite(float(rate))):
        raise Y4MError(f"{path}: frame rate F{value} must be positive")
    return float(rate)


def _parse_header(line: bytes, path: Path) -> tuple[int, int, float, str]:
    fields = line.decode("ascii", errors="replace").split()[1:]
    tags = {field[0]: field[1:] for field in fields if field}
    try:
        width, height = int(tags["W"]), int(tags["H"])
    except (KeyError, ValueError):
        raise Y4MError(f"{path}: the Y4M header needs W and H: {line[:200]!r}") from None
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise Y4MError(f"{path}: frame size {width} x {height} outside 1..{MAX_SIDE}")
    fps = _parse_fps(tags.get("F", "25:1"), path)  # a Y4M without F: 25 fps, as ffmpeg reads it
    colour = tags.get("C", "420jpeg")
    if colour not in ACCEPTED:
        raise Y4MError(
            f"{path}: Y4M colour space C{colour} is not supported; {_ACCEPTED_TEXT}",
            code="unsupported_video",
        )
    return width, height, fps, colour


def open_y4m(path: str | Path) -> Y4MVideo:
    """Validate ``path``'s header and locate every frame.

    Raises
    ------
    Y4MError
        ``bad_video`` when the file is not Y4M (the message names what is accepted),
        ``unsupported_video`` for a colour space not read here, ``truncated_video`` for
        a frame cut short or a frame header missing, ``empty_video`` for no frames.
    FileNotFoundError
        When ``path`` does not exist.
    """
    path = Path(path)
    size = path.stat().st_size
    with path.open("rb") as handle:
        header = handle.readline(MAX_HEADER_BYTES)
        if not header.startswith(_MAGIC + b" ") or not header.endswith(b"\n"):
            raise Y4MError(f"{path}: not a YUV4MPEG2 video; {_ACCEPTED_TEXT}")
        width, height, fps, colour = _parse_header(header, path)
        layout, sx, sy = ACCEPTED[colour]
        chroma = -(-width // sx) * -(-height // sy)
        frame_bytes = width * height + 2 * chroma
        offsets: list[int] = []
        position = len(header)
        while position < size:
            handle.seek(position)
            line = handle.readline(MAX_HEADER_BYTES)
            if not (line.startswith(b"FRAME") and line.endswith(b"\n")):
                raise Y4MError(
                    f"{path}: no FRAME header at byte {position} (frame {len(offsets)})",
                    code="truncated_video",
                )
            start = position + len(line)
            if start + frame_bytes > size:
                raise Y4MError(
                    f"{path}: frame {len(offsets)} is truncated ({size - start} of "
                    f"{frame_bytes} bytes)",
                    code="truncated_video",
                )
            offsets.append(start)
            position = start + frame_bytes
    if not offsets:
        raise Y4MError(f"{path}: the video has no frames", code="empty_video")
    return Y4MVideo(path, width, height, fps, layout, colour, frame_bytes, tuple(offsets))

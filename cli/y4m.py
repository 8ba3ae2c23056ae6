"""YUV4MPEG2 (.y4m) video files, read frame by frame as raw planar 8-bit YUV, and written.

The header is validated up front (every number in it) and every frame wanted located
before any is read; frames are
returned as their bytes, never converted to RGB here (``facecast track`` hands them to
Chromium, which converts them as it converts its camera's frames). ``Y4MWriter`` writes
RGB frames as 4:2:0 in the colour space the tracker tags them with (BT.601, limited
range), for rendered test videos.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from types import TracebackType

import numpy as np
import numpy.typing as npt

from facecast.errors import FacecastError

__all__ = [
    "ACCEPTED",
    "MAX_FPS",
    "MAX_NUMBER",
    "MAX_SIDE",
    "Y4MError",
    "Y4MVideo",
    "Y4MWriter",
    "open_y4m",
    "rgb_to_i420",
]

_MAGIC = b"YUV4MPEG2"
#: A header or a frame header longer than this is not a Y4M file.
MAX_HEADER_BYTES = 4096
#: Frame sizes beyond this are refused: what ``facecast track``'s Chromium page takes.
#: Measured (issue 31, 2026-12-04, 2-core VM under load): 4096^2 tracks, 5120^2 tracked
#: once in 285 s, 6144^2 did not end in 400 s, and at 8192^2 the page's process died
#: after 87-117 s (Playwright's TargetClosedError).
MAX_SIDE = 4096
#: The largest number of a header's N:D (frame rate, pixel aspect): a 32-bit int's, as
#: ffmpeg reads them.
MAX_NUMBER = 2**31 - 1
#: Frame rates above this are refused (no camera or encoder makes one).
MAX_FPS = 1000
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


def _number(text: str, what: str, path: Path, *, most: int = MAX_NUMBER) -> int:
    """A header number: 1 to ``most``, plain ASCII digits (no sign, no ``_``, no spaces:
    ``int`` takes all three, and any length up to Python's digit limit)."""
    if not (text.isascii() and text.isdigit() and len(text) <= len(str(most))):
        raise Y4MError(f"{path}: {what} {text[:40]!r} is not a whole number 1..{most}")
    value = int(text)
    if not 1 <= value <= most:
        raise Y4MError(f"{path}: {what} {value} is outside 1..{most}")
    return value


def _parse_fps(value: str, path: Path) -> float:
    num, colon, den = value.partition(":")
    if not colon:
        raise Y4MError(f"{path}: frame rate F{value[:40]} is not N:D")
    rate = Fraction(
        _number(num, "frame rate numerator", path), _number(den, "frame rate denominator", path)
    )
    if rate > MAX_FPS:
        raise Y4MError(f"{path}: frame rate F{value} is over {MAX_FPS} frames a second")
    return float(rate)


def _parse_header(line: bytes, path: Path) -> tuple[int, int, float, str]:
    fields = line.decode("ascii", errors="replace").split()[1:]
    tags = {field[0]: field[1:] for field in fields if field}
    if "W" not in tags or "H" not in tags:
        raise Y4MError(f"{path}: the Y4M header needs W and H: {line[:200]!r}")
    width = _number(tags["W"], "width W", path, most=MAX_SIDE)
    height = _number(tags["H"], "height H", path, most=MAX_SIDE)
    fps = _parse_fps(tags.get("F", "25:1"), path)  # a Y4M without F: 25 fps, as ffmpeg reads it
    if "A" in tags and tags["A"] not in ("0:0", ""):
        aspect_num, colon, aspect_den = tags["A"].partition(":")
        if not colon:
            raise Y4MError(f"{path}: pixel aspect A{tags['A'][:40]} is not N:D")
        _number(aspect_num, "pixel aspect numerator", path)
        _number(aspect_den, "pixel aspect denominator", path)
    colour = tags.get("C", "420jpeg")
    if colour not in ACCEPTED:
        raise Y4MError(
            f"{path}: Y4M colour space C{colour} is not supported; {_ACCEPTED_TEXT}",
            code="unsupported_video",
        )
    return width, height, fps, colour


def open_y4m(path: str | Path, *, max_frames: int | None = None) -> Y4MVideo:
    """Validate ``path``'s header and locate every frame, or the first ``max_frames``
    (the rest of the file is then never read, nor checked).

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
        while position < size and (max_frames is None or len(offsets) < max_frames):
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


def rgb_to_i420(rgb: npt.ArrayLike) -> bytes:
    """An (H, W, 3) RGB image (uint8, or float in [0, 1]) -> I420 planes (Y, U, V) as bytes.

    BT.601 with limited range (Y in 16..235, U and V in 16..240): the colour space
    ``facecast track`` tags frames with (``TRACK_COLOR_SPACE``). Chroma is averaged over
    each 2 x 2 block; H and W must be even.
    """
    image = np.asarray(rgb)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] % 2 or image.shape[1] % 2:
        raise Y4MError(f"frames must be (H, W, 3) with H and W even, got {image.shape}")
    if image.dtype == np.uint8:
        x = image.astype(np.float64) / 255.0
    else:
        x = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    luma = 0.299 * r + 0.587 * g + 0.114 * b
    planes = [16.0 + 219.0 * luma]
    for chroma in ((b - luma) / 1.772, (r - luma) / 1.402):  # each in [-0.5, 0.5]
        h, w = chroma.shape
        block = chroma.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
        planes.append(128.0 + 224.0 * block)
    return b"".join(np.clip(p + 0.5, 0, 255).astype(np.uint8).tobytes() for p in planes)


class Y4MWriter:
    """Writes RGB frames to a 4:2:0 Y4M file (``rgb_to_i420``); a context manager.

    ``open_y4m`` reads the result back with ``format`` I420 and the given ``fps``.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE) or width % 2 or height % 2:
            raise Y4MError(f"frame size {width} x {height}: even sides in 2..{MAX_SIDE}")
        rate = Fraction(fps).limit_denominator(1001)
        if not rate > 0:
            raise Y4MError(f"frame rate must be positive, got {fps}")
        self.path = Path(path)
        self.width, self.height = width, height
        self.frames = 0
        self._handle = self.path.open("wb")
        self._handle.write(
            f"YUV4MPEG2 W{width} H{height} F{rate.numerator}:{rate.denominator} Ip A1:1 "
            "C420mpeg2 XCOLORRANGE=LIMITED\n".encode("ascii")
        )

    def write(self, rgb: npt.ArrayLike) -> None:
        """Append one (height, width, 3) RGB frame."""
        shape = np.shape(rgb)
        if shape != (self.height, self.width, 3):
            raise Y4MError(f"frame {self.frames}: expected shape {(self.height, self.width, 3)}, "
                           f"got {shape}")  # fmt: skip
        self.write_i420(rgb_to_i420(rgb))

    def write_i420(self, planes: bytes) -> None:
        """Append one frame already converted (``rgb_to_i420``'s bytes): a caller writing
        the same image again converts it once."""
        size = self.width * self.height * 3 // 2
        if len(planes) != size:
            raise Y4MError(f"frame {self.frames}: expected {size} bytes of I420, got {len(planes)}")
        self._handle.write(b"FRAME\n")
        self._handle.write(planes)
        self.frames += 1

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> Y4MWriter:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

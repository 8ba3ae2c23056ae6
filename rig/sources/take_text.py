"""What the recorded-take readers share: the bound on a take's frames, opening its text, its fps.

Used by livelink_csv.py and mediapipe_ndjson.py; it must not parse either format.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

from ..errors import InputError

__all__ = ["MAX_TAKE_FRAMES", "check_fps", "open_text"]

#: Frames a take may hold (30 minutes at 60 fps); more is refused, not truncated.
MAX_TAKE_FRAMES = 108_000


def open_text(path: Path, what: str) -> io.TextIOWrapper:
    try:
        return path.open("r", encoding="utf-8-sig", newline="")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found", code="missing_file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, expected a {what}", code="missing_file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})", code="missing_file") from None


def check_fps(fps: float) -> float:
    value = float(fps)
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"fps must be positive and finite, got {fps}", code="bad_animation")
    return value

"""Live Link Face CSV takes -> source animations (the app's take export).

Streams the file line by line with bounded memory and names the line at fault in every
error; it must not fit, clone or touch the network.

Live Link Face CSV (the app's take export): a header ``Timecode,BlendShapeCount,`` then
one column per ARKit blendshape in PascalCase (``EyeBlinkLeft`` ... ``TongueOut``, any
order, matched case-insensitively), then optionally ``HeadYaw,HeadPitch,HeadRoll,
LeftEyeYaw,...,RightEyeRoll``. ``Timecode`` is ``HH:MM:SS:FF`` or ``HH:MM:SS:FF.fff``:
``FF`` frames at the take's frame rate and ``.fff`` a fraction of a frame, so a row plays
at ``h*3600 + m*60 + s + (FF + 0.fff) / fps`` seconds (timestamps start at 0 with the
first row; a timecode wrapping past midnight continues).
"""

from __future__ import annotations

import csv
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .animation import SourceAnimation
from .source_rig import ARKIT_NAMES, HEAD_POSE_NAMES, NUM_ARKIT, SourceRig
from .take_text import MAX_TAKE_FRAMES, check_fps, open_text

__all__ = ["LiveLinkTake", "livelink_csv_animation", "parse_timecode", "read_livelink_csv"]

_TIMECODE = re.compile(r"^\s*(\d{1,2}):(\d{2}):(\d{2})[:;](\d{1,3})(?:\.(\d+))?\s*$")
_DAY = 24 * 3600.0


def parse_timecode(text: str, fps: float) -> float:
    """Seconds of a ``HH:MM:SS:FF[.fff]`` timecode at ``fps`` frames per second.

    Raises
    ------
    InputError
        ``bad_timecode`` for anything else, or a frame number not below ``fps``.
    """
    match = _TIMECODE.match(text)
    if match is None:
        raise InputError(
            f"timecode {text!r} is not HH:MM:SS:FF or HH:MM:SS:FF.fff", code="bad_timecode"
        )
    hours, minutes, seconds, frames = (int(g) for g in match.groups()[:4])
    fraction = float("0." + match.group(5)) if match.group(5) else 0.0
    if minutes >= 60 or seconds >= 60 or frames >= math.ceil(fps):
        raise InputError(f"timecode {text!r} is out of range at {fps:g} fps", code="bad_timecode")
    return hours * 3600.0 + minutes * 60.0 + seconds + (frames + fraction) / fps


@dataclass(eq=False)
class LiveLinkTake:
    """A Live Link Face take as read from its CSV.

    Attributes
    ----------
    weights : (F, 52) float64
        ARKit weights in ``ARKIT_NAMES`` order.
    head : (F, 9) float64 or None
        ``HEAD_POSE_NAMES`` values (radians) when the CSV has all nine columns.
    timestamps : (F,) float64
        Seconds from the first row.
    fps : float
    """

    weights: np.ndarray
    head: np.ndarray | None
    timestamps: np.ndarray
    fps: float

    @property
    def num_frames(self) -> int:
        return int(self.weights.shape[0])


def _csv_columns(header: list[str], where: str) -> tuple[int, list[int], list[int] | None]:
    """(timecode column, column of each ARKit weight, columns of the head values or None)."""
    lower = [h.strip().lower() for h in header]
    seen: dict[str, int] = {}
    for i, name in enumerate(lower):
        if name in seen:
            raise InputError(
                f"{where} line 1: column {header[i].strip()!r} appears twice", code="bad_csv"
            )
        seen[name] = i
    if "timecode" not in seen:
        raise InputError(f"{where} line 1: no Timecode column", code="missing_column")
    weight_cols = []
    for name in ARKIT_NAMES:
        if name.lower() not in seen:
            pascal = name[0].upper() + name[1:]
            raise InputError(
                f"{where} line 1: no {pascal} column (a Live Link Face CSV has the 52 ARKit "
                "blendshape columns)",
                code="missing_column",
            )
        weight_cols.append(seen[name.lower()])
    head_present = [n.lower() in seen for n in HEAD_POSE_NAMES]
    head_cols = [seen[n.lower()] for n in HEAD_POSE_NAMES] if all(head_present) else None
    return seen["timecode"], weight_cols, head_cols


def read_livelink_csv(
    path: str | os.PathLike[str], *, fps: float = 60.0, max_frames: int = MAX_TAKE_FRAMES
) -> LiveLinkTake:
    """Read a Live Link Face CSV take.

    Parameters
    ----------
    path : path-like
    fps : float
        The take's frame rate (the app records at 60 by default; 30 is a setting): the
        unit of the timecode's frame field.
    max_frames : int
        More rows than this is an error (``too_many_frames``).

    Raises
    ------
    InputError
        Naming the line: missing columns, a row with the wrong number of fields, a value
        that is not a number (``bad_csv``), NaN or Inf (``non_finite``), a bad or
        backwards timecode (``bad_timecode``), an empty take.
    """
    path = Path(path)
    fps = check_fps(fps)
    with open_text(path, "CSV file") as handle:
        reader = csv.reader(handle)
        try:
            header = next(reader, None)
            if header is None or not any(h.strip() for h in header):
                raise InputError(f"{path}: empty file, expected a CSV header", code="bad_csv")
            time_col, weight_cols, head_cols = _csv_columns(header, str(path))
            wanted = np.asarray(weight_cols + (head_cols or []))
            values: list[np.ndarray] = []
            times: list[float] = []
            previous = None
            offset = 0.0
            for row in reader:
                line = reader.line_num
                if not row or not any(cell.strip() for cell in row):
                    continue
                if len(row) != len(header):
                    raise InputError(
                        f"{path} line {line}: {len(row)} fields, the header has {len(header)}",
                        code="wrong_column_count",
                    )
                if len(values) >= max_frames:
                    raise InputError(
                        f"{path} line {line}: more than {max_frames} frames", code="too_many_frames"
                    )
                try:
                    stamp = parse_timecode(row[time_col], fps)
                except InputError as exc:
                    raise InputError(f"{path} line {line}: {exc.message}", code=exc.code) from None
                if previous is not None and stamp + offset < previous:
                    if previous - (stamp + offset) > _DAY / 2:
                        offset += _DAY  # the take ran past midnight
                    else:
                        raise InputError(
                            f"{path} line {line}: timecode {row[time_col].strip()} is earlier "
                            "than the row before",
                            code="bad_timecode",
                        )
                previous = stamp + offset
                times.append(previous)
                values.append(_row_numbers(row, wanted, header, path, line))
        except csv.Error as exc:
            raise InputError(
                f"{path} line {reader.line_num}: malformed CSV ({exc})", code="bad_csv"
            ) from None
        except UnicodeDecodeError:
            raise InputError(f"{path}: not UTF-8 text", code="bad_csv") from None
    if not values:
        raise InputError(f"{path}: the take has no frames", code="bad_csv")
    table = np.stack(values)
    stamps = np.asarray(times)
    return LiveLinkTake(
        weights=table[:, :NUM_ARKIT],
        head=table[:, NUM_ARKIT:] if head_cols is not None else None,
        timestamps=stamps - stamps[0],
        fps=fps,
    )


def _row_numbers(
    row: list[str], columns: np.ndarray, header: list[str], path: Path, line: int
) -> np.ndarray:
    out = np.empty(columns.size)
    for j, col in enumerate(columns):
        cell = row[col].strip()
        try:
            out[j] = float(cell)
        except ValueError:
            raise InputError(
                f"{path} line {line}: column {header[col].strip()} is {cell!r}, not a number",
                code="bad_csv",
            ) from None
        if not math.isfinite(out[j]):
            raise InputError(
                f"{path} line {line}: column {header[col].strip()} is {cell}", code="non_finite"
            )
    return out


def livelink_csv_animation(
    path: str | os.PathLike[str],
    source_rig: SourceRig,
    *,
    fps: float = 60.0,
    head_pose: bool = False,
) -> SourceAnimation:
    """A Live Link Face CSV take as feature points, through ``source_rig``.

    Parameters
    ----------
    head_pose : bool
        Rotate each frame's points by the take's head yaw/pitch/roll (needs the head
        columns; ``missing_column`` otherwise). Off: the head stays still.

    Returns
    -------
    SourceAnimation
        ``points`` (F, K, 3) = ``source_rig.points(weights)``, ``timestamps`` from the
        timecodes, ``fps``.
    """
    take = read_livelink_csv(path, fps=fps)
    head = None
    if head_pose:
        if take.head is None:
            raise InputError(
                f"{path}: head pose asked for, but the CSV has no HeadYaw/HeadPitch/HeadRoll "
                "columns",
                code="missing_column",
            )
        head = take.head[:, :3]
    points = source_rig.points(take.weights, head=head)
    return SourceAnimation(points=points, fps=take.fps, timestamps=take.timestamps)

"""Markers: the (source vertex, target vertex) pairs an artist gives, read and checked.

A markers file is ``source_vertex target_vertex`` a line (0-based); `check_markers` says
what to fix in a set of pairs before any correspondence is fitted with them.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import MarkerError

__all__ = ["MAX_VERTEX_INDEX", "MIN_MARKERS", "check_markers", "read_markers"]

#: Markers needed at least: three points not on a line fix the similarity that first
#: places the source on the target. A face needs more to be fitted well (around 20:
#: eye and mouth corners, lids, nose, brows, chin, ear roots).
MIN_MARKERS = 3
#: The largest vertex index a markers file may name (the largest int32): no mesh a
#: glTF can carry (indices are at most uint32) has more, and every index then fits int64.
MAX_VERTEX_INDEX = 2**31 - 1


def read_markers(path: str | os.PathLike[str]) -> np.ndarray:
    """(N, 2) int64 marker pairs from a text file: ``source_vertex target_vertex`` a line.

    0-based vertex indices, separated by spaces or a comma; ``#`` starts a comment, and
    blank lines are skipped.

    Raises
    ------
    MarkerError
        Missing or unreadable file, a line that is not two integers (with its number),
        an index below 0 or above ``MAX_VERTEX_INDEX`` (``marker_out_of_range``).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MarkerError(f"{path}: marker file not found", code="missing_file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MarkerError(f"{path}: cannot read the marker file ({exc})") from None
    pairs: list[tuple[int, int]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c for c in re.split(r"[\s,]+", line) if c]
        try:
            values = [int(c) for c in cells]
        except ValueError:
            values = []
        if len(values) != 2:
            raise MarkerError(
                f"{path}, line {number}: expected two vertex indices "
                f"'source_vertex target_vertex', got {raw.strip()!r}"
            )
        if not all(0 <= v <= MAX_VERTEX_INDEX for v in values):
            # int64 holds no more; a mesh with as many vertices cannot be loaded anyway.
            raise MarkerError(
                f"{path}, line {number}: vertex index out of range [0, {MAX_VERTEX_INDEX}] "
                f"in {raw.strip()[:80]!r}",
                code="marker_out_of_range",
            )
        pairs.append((values[0], values[1]))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def check_markers(
    markers: npt.ArrayLike, num_source: int, num_target: int, *, source: np.ndarray | None = None
) -> np.ndarray:
    """Markers as (N, 2) int64, or a ``MarkerError`` saying what to fix.

    Each source vertex and each target vertex may be named once; at least ``MIN_MARKERS``
    pairs, whose source vertices (when ``source`` (Vs, 3) is given) do not lie on a line.
    """
    try:
        pairs = np.asarray(markers)
    except (TypeError, ValueError, OverflowError) as exc:
        raise MarkerError(f"markers: not an array ({exc})") from None
    if pairs.size and (
        pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer)
    ):
        raise MarkerError(f"markers: expected (N, 2) integer pairs, got {pairs.shape}")
    pairs = pairs.reshape(-1, 2).astype(np.int64)
    if len(pairs) < MIN_MARKERS:
        raise MarkerError(
            f"markers: {len(pairs)} given, at least {MIN_MARKERS} needed (about 20 spread "
            "over the face fit best: eye and mouth corners, nose tip, brows, chin)",
            code="too_few_markers",
        )
    for column, (count, what) in enumerate(((num_source, "source"), (num_target, "target"))):
        bad = (pairs[:, column] < 0) | (pairs[:, column] >= count)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise MarkerError(
                f"markers: pair {row} names {what} vertex {pairs[row, column]}, outside "
                f"[0, {count}) (0-based vertex indices of the {what} mesh)",
                code="marker_out_of_range",
            )
        unique, counts = np.unique(pairs[:, column], return_counts=True)
        if counts.max() > 1:
            raise MarkerError(
                f"markers: {what} vertex {unique[np.argmax(counts)]} is named "
                f"{counts.max()} times; each vertex may be a marker once",
                code="repeated_marker",
            )
    if source is not None:
        spread = np.linalg.svd(source[pairs[:, 0]] - source[pairs[:, 0]].mean(axis=0),
                               compute_uv=False)  # fmt: skip
        if spread[1] <= 1e-6 * max(spread[0], np.finfo(float).tiny):
            raise MarkerError(
                "markers: the source markers lie on a line; add markers off it (eye corners "
                "and the chin with the nose tip)",
                code="collinear_markers",
            )
    return pairs

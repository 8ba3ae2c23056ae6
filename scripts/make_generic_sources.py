"""Write facecast's generic ARKit source set (rig/characters/generic_arkit/) from ICT-FaceKit.

Run once from the repository (``.venv/bin/python scripts/make_generic_sources.py``); the
output is committed as package data. Reads ../shared/data/ict-facekit (or $FACECAST_ICT).
"""

from __future__ import annotations

import io
import sys
import zipfile
from pathlib import Path

import numpy as np

from facecast.rig.sources.ict import (
    DEFAULT_LANDMARKS,
    ICT_FILE,
    locate_ict,
    stable_positions,
)
from facecast.rig.sources.source_rig import arkit_from_ict

OUT = Path(__file__).resolve().parents[1] / "rig" / "characters" / "generic_arkit" / "points.npz"


def generic_arrays(archive: Path) -> dict[str, np.ndarray]:
    """The set's arrays: names, points (M, 20, 3) cm, landmarks, stable positions."""
    with np.load(archive, allow_pickle=False) as ict:
        neutral = ict["neutral"].astype(np.float64)
        feature = ict["landmarks68"][list(DEFAULT_LANDMARKS)].astype(np.int64)
        names = [str(n) for n in ict["expression_names"]]
        shapes = ict["expressions"][:, feature, :].astype(np.float64)
    arkit_names, points = arkit_from_ict(names, neutral[feature], shapes)
    stable = stable_positions(DEFAULT_LANDMARKS)
    assert stable is not None
    return {
        "names": np.asarray(arkit_names, dtype=str),
        "points": points,
        "landmarks68": np.asarray(DEFAULT_LANDMARKS, dtype=np.int64),
        "stable_points": np.asarray(stable, dtype=np.int64),
    }


def write_npz(arrays: dict[str, np.ndarray], path: Path) -> None:
    """An .npz whose bytes depend on the arrays only (fixed zip dates), so a rerun diffs clean."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key, value in arrays.items():
            buffer = io.BytesIO()
            np.save(buffer, value, allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, buffer.getvalue())


def main() -> int:
    archive = locate_ict()
    if archive is None:
        print(f"no {ICT_FILE}: set FACECAST_ICT or put ../shared/data/ict-facekit beside the repo")
        return 1
    arrays = generic_arrays(archive)
    write_npz(arrays, OUT)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes, {len(arrays['names'])} examples)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

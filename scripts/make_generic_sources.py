"""Write facecast's generic ARKit source set (rig/characters/generic_arkit/) from ICT-FaceKit.

Run once from the repository (``.venv/bin/python scripts/make_generic_sources.py``); the
output is committed as package data. Reads ../shared/data/ict-facekit (or $FACECAST_ICT).

The points are ICT's 24 default landmarks of its generic face making each ARKit shape,
with the eyes as facecast's tracker sees them (``with_tracked_eyes``): the generic face is
rendered making each shape (``bench webcam``'s key clips and camera, its head swaying
1.5 degrees, its eyeballs turned 35 degrees a unit of eye-look weight, ARKit's own scale:
README, option (y)), tracked by the /perform page's pipeline (``facecast track``, headless
Chromium), and each held shape's lid points and the layout's two iris centres are taken
from it (README, option (z)). ``--tracked NPZ`` reuses a ``facecast track`` output of that
video (written beside it by ``--keep DIR``).
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from facecast.cli.bench.facevideo import ARKIT_GAZE_DEGREES, head_scene, write_video
from facecast.cli.track import track_video
from facecast.rig.evaluation.webcam import captured_keys, ict_performer, key_clips
from facecast.rig.sources.ict import (
    DEFAULT_LANDMARKS,
    ICT_FILE,
    ict_regions,
    locate_ict,
    stable_positions,
)
from facecast.rig.sources.ict_arkit import with_tracked_eyes
from facecast.rig.sources.layouts import load_layout
from facecast.rig.sources.source_rig import arkit_from_ict

OUT = Path(__file__).resolve().parents[1] / "rig" / "characters" / "generic_arkit" / "points.npz"


#: The generic face's camera: the webcam benchmark's defaults (ARKit's scale of gaze).
FPS, SWAY_DEGREES, GAZE_DEGREES = 30.0, 1.5, ARKIT_GAZE_DEGREES


def tracked_keys(archive: Path, tracked: Path | None, keep: Path | None) -> dict[str, np.ndarray]:
    """ICT's generic face making each ARKit shape (the neutral too), tracked: {name: (L, 3)}.
    ``tracked``: a ``facecast track`` output of that video, else it is rendered and tracked
    (kept in ``keep``)."""
    face = ict_performer(archive, identity=None)
    clips = key_clips(face.names)
    if tracked is None:
        folder = keep or Path(tempfile.mkdtemp(prefix="facecast-generic-"))
        folder.mkdir(parents=True, exist_ok=True)
        regions, landmarks68 = ict_regions(archive)
        video = write_video(folder / "generic-face-keys.y4m",
                            head_scene(face, regions, landmarks68), face, clips.activations,
                            fps=FPS, sway_degrees=SWAY_DEGREES, gaze_degrees=GAZE_DEGREES)  # fmt: skip
        tracked = track_video(video).save(folder / "generic-face-keys.npz")
    with np.load(tracked) as data:
        points, found = data["points"].astype(np.float64), data["found"].astype(bool)
    if len(points) != len(clips.activations):
        raise SystemExit(
            f"{tracked}: {len(points)} frames, the clips have {len(clips.activations)}"
        )
    keys, _ = captured_keys(points, clips, found)
    return keys


def generic_arrays(archive: Path, seen: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The set's arrays: names, points (M, 26, 3) cm, landmarks68 (-1 past the 24
    landmarks: the iris centres), stable positions, and ``tracked``: ``seen``, the generic
    face's tracked keys by name (``tracked_keys``) the eyes are taken from (M, 26, 3, the
    tracker's face frame), kept so that the suite checks the set against ICT without
    rendering and tracking 724 frames."""
    with np.load(archive, allow_pickle=False) as ict:
        neutral = ict["neutral"].astype(np.float64)
        feature = ict["landmarks68"][list(DEFAULT_LANDMARKS)].astype(np.int64)
        names = [str(n) for n in ict["expression_names"]]
        shapes = ict["expressions"][:, feature, :].astype(np.float64)
    arkit_names, exact = arkit_from_ict(names, neutral[feature], shapes)
    missing = [n for n in arkit_names if n not in seen]
    if missing:
        raise SystemExit(f"the tracker lost the generic face in {missing}")
    tracked = np.stack([np.asarray(seen[n], dtype=np.float64) for n in arkit_names])
    features = load_layout().feature_names[: len(DEFAULT_LANDMARKS)]
    eyes = [i for i, name in enumerate(features) if "_lid" in name]
    points = with_tracked_eyes(exact, tracked, eyes)
    stable = stable_positions(DEFAULT_LANDMARKS)
    assert stable is not None
    extra = points.shape[1] - len(DEFAULT_LANDMARKS)
    return {
        "names": np.asarray(arkit_names, dtype=str),
        "points": points,
        "landmarks68": np.asarray([*DEFAULT_LANDMARKS, *[-1] * extra], dtype=np.int64),
        "stable_points": np.asarray(stable, dtype=np.int64),
        "tracked": tracked,
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--tracked", type=Path, help="facecast track's .npz of the generic face's video"
    )
    parser.add_argument("--keep", type=Path, help="keep the video and its tracked points here")
    args = parser.parse_args()
    archive = locate_ict()
    if archive is None:
        print(f"no {ICT_FILE}: set FACECAST_ICT or put ../shared/data/ict-facekit beside the repo")
        return 1
    arrays = generic_arrays(archive, tracked_keys(archive, args.tracked, args.keep))
    write_npz(arrays, OUT)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes, {len(arrays['names'])} examples)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

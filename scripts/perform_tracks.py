"""Track `facecast bench webcam`'s kept videos with `facecast perform`'s tracker (MediaPipe).

Run by the perform venv's interpreter (MediaPipe needs numpy < 2), then score the points
with the benchmark in the main venv:

    .venv-perform/bin/python scripts/perform_tracks.py DIR
    .venv/bin/facecast bench webcam --videos DIR --backend mediapipe

Every ``*.y4m`` in DIR (the take, the key clips, the eyes clip that a ``bench webcam
--videos DIR`` run rendered there) is tracked frame by frame with
``facecast.cli.facetrack.FaceTracker``, and its points are written where the benchmark
looks for kept points (``<video>-mediapipe-k<K>.npz``: ``points`` (F, K, 3), NaN where no
face was found, and ``found`` (F,)). Videos whose points are there already are skipped.
README, "The eyes clip", option (o).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from facecast.cli.facetrack import FaceTracker, VideoSource

#: The name ``bench webcam --backend`` takes for these points.
BACKEND = "mediapipe"


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not Path(argv[0]).is_dir():
        print(__doc__, file=sys.stderr)
        return 2
    for video in sorted(Path(argv[0]).glob("*.y4m")):
        # A tracker a video: the iris model's crops follow the last frames of one face.
        with FaceTracker(max_faces=1) as tracker:
            k = tracker.layout.num_features
            out = video.with_name(f"{video.stem}-{BACKEND}-k{k}.npz")
            if out.is_file():
                continue
            started = time.perf_counter()
            points, found = [], []
            with VideoSource(str(video)) as source:
                for rgb in source.frames():
                    tracked = tracker.track(rgb)
                    found.append(tracked.points is not None)
                    points.append(tracked.points if found[-1] else np.full((k, 3), np.nan))
            partial = out.with_name(out.name + ".partial.npz")
            np.savez(partial, points=np.asarray(points, np.float32), found=np.asarray(found))
            partial.replace(out)
            seconds = time.perf_counter() - started
            print(f"{video.name}: {sum(found)} of {len(found)} frames, {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

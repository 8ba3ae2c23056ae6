"""``facecast track``: a recorded video -> the /perform page's feature points, every frame.

The command line of ``facecast.cli.track.track_video`` (the page's own tracker in headless
Chromium); writes the .npz ``facecast clone`` reads. It publishes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers

#: Exit status when --require-face is given and no frame has a face.
NO_FACE_EXIT = 3


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "track",
        help="track the face in every frame of a video, as /perform does",
        description=(
            "Run the /perform page's own face tracker (BlazeFace + FaceMesh on TensorFlow.js "
            "WebAssembly, in headless Chromium) on every frame of a YUV4MPEG2 (.y4m) video and "
            "write the layout's feature points as /perform publishes them: an .npz with "
            "points (F, K, 3) float32 (NaN where no face was found), found (F,) and fps. "
            "`facecast clone RIG POINTS.npz -o out.glb` then puts the performance on any rig "
            "fitted for the layout."
        ),
    )
    parser.add_argument("video", metavar="VIDEO", help="a .y4m video (8-bit 4:2:0, 4:2:2, 4:4:4)")
    parser.add_argument("-o", "--output", required=True, metavar="POINTS.npz")
    parser.add_argument(
        "--backend", default="wasm", help="TensorFlow.js backend: wasm (default), webgl, cpu"
    )
    parser.add_argument(
        "--frames", type=int, default=None, metavar="N", help="track only the first N frames"
    )
    parser.add_argument(
        "--require-face",
        action="store_true",
        help=f"exit with status {NO_FACE_EXIT} when no frame has a face (the .npz is written)",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from facecast.cli.track import track_video
    from facecast.cli.y4m import Y4MError

    output = Path(args.output)
    if output.suffix.lower() != ".npz":
        raise CommandError(f"{output}: the output is an .npz (POINTS.npz)")
    if not output.parent.exists():
        raise CommandError(f"{output.parent}: no such folder for {output.name}")
    if not Path(args.video).is_file():
        raise CommandError(f"{args.video}: no such video file")
    try:
        result = track_video(
            args.video, backend=args.backend, max_frames=args.frames, progress=not args.quiet
        )
    except Y4MError as exc:
        raise CommandError(str(exc)) from None
    result.save(output)
    found = int(result.found.sum())
    print(
        f"tracked {result.num_frames} frames ({result.num_frames / result.fps:.1f} s at "
        f"{result.fps:g} fps) on {result.backend} in {result.seconds:.1f} s "
        f"({result.num_frames / max(result.seconds, 1e-9):.1f} frames/s; the model "
        f"{result.model_ms:.0f} ms a frame): a face in {found}; "
        f"wrote {output}"
    )
    if found == 0:
        print(
            f"facecast track: no face was found in any of the {result.num_frames} frames",
            file=sys.stderr,
        )
        if args.require_face:
            return NO_FACE_EXIT
    return 0

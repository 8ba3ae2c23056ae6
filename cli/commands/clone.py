"""``facecast clone``: run a source animation through a rig and write the cloned animation.

Batched, vectorised evaluation with a progress bar, after the take's points are smoothed
in time (``facecast.rig.smoothing``: RTS on a rig fitted with noise); the file formats
belong to ``facecast.rig.sources.animation.write_clone_output``, and it must not fit anything.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.commands._animation import add_source_arguments, load_animation, write_cloned
from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy and the rig load when the command runs, not for --help
    import numpy as np

    from facecast.cli.commands import Subparsers
    from facecast.rig import Rig
    from facecast.rig.smoothing import SmoothedTake

BATCH = 256
# Above this many bytes of cloned vertices an .npz keeps only the weights (the rig and
# the weights give the vertices back), so a long performance cannot exhaust memory.
MAX_NPZ_VERTEX_BYTES = 1 << 30
# The engine's (facecast.rig.smoothing.SMOOTHING_CHOICES, rig.filters.KALMAN_ACCELERATION),
# written out so that --help does not load numpy; a test keeps them equal.
SMOOTHING_CHOICES = ("auto", "rts", "kalman", "none")
KALMAN_ACCELERATION = 480.0


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "clone",
        help="clone a source animation onto a rig's target",
        description=(
            "Compute blend weights for every frame of a source animation and write the "
            "target's animation: .npz (weights and vertices), .glb (morph targets + "
            "animation) or a folder of OBJ frames, by the output's extension. On a rig fitted "
            "with --noise the source points are first smoothed in time by a Rauch-Tung-Striebel "
            "smoother (the live Kalman default's offline twin: less noise, no lag)."
        ),
    )
    parser.add_argument("rig", metavar="RIG", help="a rig file written by 'facecast fit'")
    add_source_arguments(
        parser,
        source_help="source animation: .npz (points or vertices), .npy points, a folder of OBJ "
        "frames, a Live Link Face .csv take (with --source-rig), a MediaPipe .ndjson, or "
        "'demo' (the procedural performance, for a rig fitted on 'demo' or on the generic "
        "ARKit set: a character file)",
        source_rig_help="ARKit-named source shapes that turn a Live Link Face CSV's blendshape "
        "weights into feature points: 'generic' (facecast's generic ARKit set, "
        "rig/characters/generic_arkit/points.npz, for a rig fitted from a character file), an "
        "example-set folder from 'facecast import', or ICT's npz",
    )
    parser.add_argument(
        "-o", "--output", required=True, metavar="OUT", help=".npz, .glb, or a folder"
    )
    parser.add_argument(
        "--align", action="store_true", help="remove head pose from each frame first"
    )
    parser.add_argument(
        "--seconds", type=float, default=12.0, help="length of the 'demo' source (default 12)"
    )
    parser.add_argument(
        "--smoothing", choices=SMOOTHING_CHOICES, default="auto",
        help="temporal smoothing of the source points: 'rts' (the fixed-interval smoother: "
        "each frame from the whole take, then the rig regularised for the noise it leaves), "
        "'kalman' (the live, causal filter), 'none'; default 'auto': rts on a rig fitted "
        "with --noise (its sigma the measurement noise), else none",
    )  # fmt: skip
    parser.add_argument(
        "--acceleration", type=float, metavar="A",
        help="the smoother's process noise: acceleration std in units of the rig's noise per "
        "s^2 (default: rts reads it off the take, most likely value; kalman "
        f"{KALMAN_ACCELERATION:g}, the live default)",
    )  # fmt: skip
    parser.set_defaults(func=run)


def clone_frames(
    rig: Rig, points: np.ndarray, *, align: bool = False, with_vertices: bool = True,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """Weights (F, M) and, optionally, vertices (F, V, 3) float32, BATCH frames at a time."""
    import numpy as np
    from tqdm import tqdm

    frames = points.shape[0]
    weights = np.empty((frames, rig.num_examples))
    vertices = np.empty((frames, rig.num_vertices, 3), dtype=np.float32) if with_vertices else None
    starts = range(0, frames, BATCH)
    bar = tqdm(
        starts, total=len(starts), unit="batch", desc="cloning", disable=not progress,
        leave=False,
    )  # fmt: skip
    for start in bar:
        stop = min(start + BATCH, frames)
        weights[start:stop] = rig.weights(points[start:stop], align=align)
        if vertices is not None:
            rig.blend(weights[start:stop], out=vertices[start:stop])
    return weights, vertices


def run(args: argparse.Namespace) -> int:
    from facecast.rig import load_rig
    from facecast.rig.errors import FitError, InputError
    from facecast.rig.smoothing import smooth_take

    if not Path(args.rig).exists():
        raise CommandError(f"{args.rig}: no such rig file")
    output = Path(args.output)
    if not output.parent.exists():
        raise CommandError(f"{output.parent}: no such folder for {output.name}")
    rig = load_rig(args.rig)
    animation = load_animation(
        args.source,
        num_points=rig.num_points,
        feature_indices=lambda: rig.feature_indices,
        source_rig=args.source_rig,
        seconds=args.seconds,
    )
    frames = animation.num_frames
    suffix = output.suffix.lower()
    vertex_bytes = frames * rig.num_vertices * 3 * 4
    with_vertices = suffix == ".npz" and vertex_bytes <= MAX_NPZ_VERTEX_BYTES
    if suffix == ".npz" and not with_vertices:
        print(f"note: {vertex_bytes / 1e9:.1f} GB of vertices; the .npz keeps the weights only")
    started = time.perf_counter()
    try:
        take = smooth_take(
            rig, animation.points, animation.times, smoothing=args.smoothing,
            acceleration=args.acceleration,
        )  # fmt: skip
    except (InputError, FitError) as exc:
        raise CommandError(f"--smoothing {args.smoothing}: {exc}") from None
    weights, vertices = clone_frames(
        take.rig, take.points, align=args.align, with_vertices=with_vertices,
        progress=frames > 4 * BATCH,
    )  # fmt: skip
    elapsed = time.perf_counter() - started
    written = write_cloned(output, rig, weights, vertices, animation.fps)
    rate = frames / elapsed if elapsed > 0 else float("inf")
    smoothed = _smoothing_note(rig, take)
    print(
        f"cloned {frames} frames ({frames / animation.fps:.1f} s at {animation.fps:g} fps, "
        f"{smoothed}) in {elapsed * 1e3:.1f} ms ({rate:.0f} frames/s); wrote {written}"
    )
    return 0


def _smoothing_note(rig: Rig, take: SmoothedTake) -> str:
    """How the take was smoothed, for the summary line."""
    if take.method == "none" or take.acceleration is None:
        return "not smoothed"
    fitted = float(rig.fit_report.get("noise", 0.0))
    low, high = float(take.acceleration.min()), float(take.acceleration.max())
    if take.method == "kalman":
        return f"Kalman-filtered: noise {fitted:g}, acceleration {low:g} noise/s^2"
    spread = f"{low:.0f}" if low == high else f"{low:.0f}-{high:.0f}"
    return (
        f"RTS-smoothed: noise {fitted:g}, acceleration {spread} noise/s^2, rig regularised "
        f"for the {take.noise:.3g} left"
    )

"""``facecast clone``: run a source animation through a rig and write the cloned animation.

Batched, vectorised evaluation with a progress bar; the file formats belong to
``facecast.rig.animation.write_clone_output``, and it must not fit anything.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

BATCH = 256
# Above this many bytes of cloned vertices an .npz keeps only the weights (the rig and
# the weights give the vertices back), so a long performance cannot exhaust memory.
MAX_NPZ_VERTEX_BYTES = 1 << 30


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "clone",
        help="clone a source animation onto a rig's target",
        description=(
            "Compute blend weights for every frame of a source animation and write the "
            "target's animation: .npz (weights and vertices), .glb (morph targets + "
            "animation) or a folder of OBJ frames, by the output's extension."
        ),
    )
    parser.add_argument("rig", metavar="RIG", help="a rig file written by 'facecast fit'")
    parser.add_argument(
        "source",
        metavar="SOURCE",
        help="source animation: .npz (points or vertices), .npy points, a folder of OBJ "
        "frames, a Live Link Face .csv take (with --source-rig), a MediaPipe .ndjson, or "
        "'demo' (the procedural performance; for a rig fitted on 'demo')",
    )
    parser.add_argument(
        "--source-rig",
        metavar="PATH",
        help="ARKit-named source shapes that turn a Live Link Face CSV's blendshape weights "
        "into feature points (an example-set folder from 'facecast import', or ICT's npz)",
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
    parser.set_defaults(func=run)


def load_animation(spec: str, rig, *, seconds: float = 12.0, source_rig=None):
    """The source animation named on the command line, checked against the rig's K."""
    from facecast.client.cli import CommandError

    if spec == "demo":
        from facecast.rig.demo import demo_animation

        animation = demo_animation(seconds, with_vertices=False)
    else:
        from facecast.rig.animation import load_source_animation

        if not Path(spec).exists():
            raise CommandError(f"{spec}: no such file or folder (the source animation)")
        animation = load_source_animation(
            spec,
            feature_indices=rig.feature_indices,
            num_points=rig.num_points,
            source_rig=source_rig,
        )
    if animation.num_points != rig.num_points:
        raise CommandError(
            f"{spec}: {animation.num_points} feature points per frame, the rig expects "
            f"{rig.num_points}"
        )
    return animation


def clone_frames(rig, points, *, align: bool = False, with_vertices: bool = True, progress=True):
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
    from facecast.client.cli import CommandError
    from facecast.rig import load_rig
    from facecast.rig.animation import write_clone_output

    if not Path(args.rig).exists():
        raise CommandError(f"{args.rig}: no such rig file")
    output = Path(args.output)
    if not output.parent.exists():
        raise CommandError(f"{output.parent}: no such folder for {output.name}")
    rig = load_rig(args.rig)
    animation = load_animation(args.source, rig, seconds=args.seconds, source_rig=args.source_rig)
    frames = animation.num_frames
    suffix = output.suffix.lower()
    vertex_bytes = frames * rig.num_vertices * 3 * 4
    with_vertices = suffix == ".npz" and vertex_bytes <= MAX_NPZ_VERTEX_BYTES
    if suffix == ".npz" and not with_vertices:
        print(f"note: {vertex_bytes / 1e9:.1f} GB of vertices; the .npz keeps the weights only")
    started = time.perf_counter()
    weights, vertices = clone_frames(
        rig, animation.points, align=args.align, with_vertices=with_vertices,
        progress=frames > 4 * BATCH,
    )  # fmt: skip
    elapsed = time.perf_counter() - started
    written = write_clone_output(
        output,
        weights=weights,
        vertices=vertices,
        names=rig.names,
        neutral=rig.target_neutral,
        faces=rig.target_faces,
        deltas=rig.target_deltas,
        fps=animation.fps,
    )
    rate = frames / elapsed if elapsed > 0 else float("inf")
    print(
        f"cloned {frames} frames ({frames / animation.fps:.1f} s at {animation.fps:g} fps) "
        f"in {elapsed * 1e3:.1f} ms ({rate:.0f} frames/s); wrote {written}"
    )
    return 0

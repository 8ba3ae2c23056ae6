"""Animation files for the commands that clone: SOURCE in, cloned results out.

SOURCE's arguments and loading serve clone, stream and publish; the writers serve clone,
stream and watch. No server requests here: a command that must ask the server for
feature indices passes a function that does.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy and the rig load when a command runs, not for --help
    import numpy as np

    from facecast.rig import Rig
    from facecast.rig.sources.animation import SourceAnimation

#: --source-rig's help in the commands that leave its full description to 'facecast clone'.
SOURCE_RIG_HELP = (
    "ARKit-named source shapes for a Live Link Face CSV take: 'generic' (facecast's own "
    "generic ARKit set, for a character uploaded as a file) or a path (see 'facecast clone')"
)


def add_source_arguments(
    parser: argparse.ArgumentParser, *, source_help: str, source_rig_help: str = SOURCE_RIG_HELP
) -> None:
    """The SOURCE positional and ``--source-rig``, which `load_animation` reads."""
    parser.add_argument("source", metavar="SOURCE", help=source_help)
    parser.add_argument("--source-rig", metavar="PATH", help=source_rig_help)


def load_animation(
    spec: str,
    *,
    num_points: int,
    feature_indices: Callable[[], np.ndarray | None],
    source_rig: str | None = None,
    seconds: float = 12.0,
    expected_by: str = "the rig expects",
) -> SourceAnimation:
    """The source animation ``spec`` names, checked to have ``num_points`` points a frame.

    Parameters
    ----------
    spec : str
        A file or folder ``load_source_animation`` reads, or ``'demo'`` (the procedural
        performance, ``seconds`` long, on the demo rig's points when ``num_points`` is
        theirs, else on the generic ARKit set's: ``facecast.rig.demo.arkit``).
    feature_indices : callable
        Returns the rig's feature indices (or None); called only for a file source, as
        mesh sources need them and getting them may mean asking the server.
    expected_by : str
        Who wants ``num_points``, as the error for a mismatch says it.
    """

    if spec == "demo":
        animation = _demo_performance(num_points, seconds, expected_by)
    else:
        from facecast.rig.sources.loading import load_source_animation

        if not Path(spec).exists():
            raise CommandError(f"{spec}: no such file or folder (the source animation)")
        animation = load_source_animation(
            spec,
            feature_indices=feature_indices(),
            num_points=num_points,
            source_rig=source_rig,
        )
    if animation.num_points != num_points:
        raise CommandError(
            f"{spec}: {animation.num_points} feature points per frame, {expected_by} {num_points}"
        )
    return animation


def _demo_performance(num_points: int, seconds: float, expected_by: str) -> SourceAnimation:
    """The demo performance on the points a rig of ``num_points`` takes: the procedural
    demo's 21 (the demo rig), or the generic ARKit set's 26 (a character uploaded as a
    file), or their first 24 or 20 (an ICT-FaceKit import, a rig fitted before the layout
    grew): the same performance acted as ARKit weights."""
    from dataclasses import replace

    from facecast.rig.characters.generic import generic_sources
    from facecast.rig.demo import DEMO_FEATURE_NAMES, arkit_demo_animation, demo_animation
    from facecast.rig.sources.layouts import load_layout

    generic = generic_sources().points.shape[1]
    if num_points == len(DEMO_FEATURE_NAMES):
        return demo_animation(seconds, with_vertices=False)
    if num_points == generic:
        return arkit_demo_animation(seconds)
    if load_layout().takes_first(generic, num_points):
        # A rig fitted on the layout's earlier version (an ICT-FaceKit import's 24 points):
        # the first of the set's points, as /perform sends it.
        animation = arkit_demo_animation(seconds)
        return replace(animation, points=animation.points[:, :num_points])
    raise CommandError(
        f"demo: the demo performance comes on the demo rig's {len(DEMO_FEATURE_NAMES)} points "
        f"and on the generic ARKit set's {generic} (characters uploaded as files), "
        f"{expected_by} {num_points}: give the rig's own source animation instead"
    )


def write_cloned(
    path: str | Path, rig: Rig, weights: np.ndarray, vertices: np.ndarray | None, fps: float
) -> Path:
    """Write weights (F, M) and optional vertices (F, V, 3) cloned onto ``rig``'s target."""
    from facecast.rig.sources.animation import write_clone_output

    return write_clone_output(
        path,
        weights=weights,
        vertices=vertices,
        names=rig.names,
        neutral=rig.target_neutral,
        faces=rig.target_faces,
        deltas=rig.target_deltas,
        fps=fps,
    )


def write_results(path: str | Path, rig: Rig, output: str, values: np.ndarray, fps: float) -> Path:
    """Write a server's results, weights or vertices as ``output`` says, like `write_cloned`."""
    if output == "weights":
        return write_cloned(path, rig, values, None, fps)
    from facecast.client.streaming import weights_from_vertices

    return write_cloned(path, rig, weights_from_vertices(rig, values), values, fps)

"""``facecast expressions``: key-expressions for a neutral-only character, by deformation transfer.

Reads the target neutral and the markers, hands them to ``facecast.rig.transfer`` and
writes the example-set folder it returns; it must not compute anything itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "expressions",
        help="make a neutral-only character's key-expressions by deformation transfer",
        description=(
            "Transfer ICT-FaceKit's ARKit-named expressions onto a target neutral (Sumner & "
            "Popovic 2004) and write an example-set folder ready for `facecast fit`: "
            "facecast.toml, source/<name>.csv (ICT's 24 feature points) and target/<name>.obj "
            "(the target's own topology). A target sharing ICT's face topology needs no "
            "markers; any other needs --markers: a file, or auto for a fit without them. Needs ICT-FaceKit ($FACECAST_ICT or "
            "../shared/data/ict-facekit). A target example already in the folder is kept "
            "unless --overwrite; nothing is written on failure."
        ),
    )
    parser.add_argument(
        "target",
        metavar="TARGET_NEUTRAL",
        help="the character's neutral: .obj, .glb, .gltf or .vrm",
    )
    parser.add_argument(
        "-o", "--output", required=True, metavar="EXAMPLES", help="example-set folder to write"
    )
    parser.add_argument(
        "--markers",
        metavar="FILE|auto",
        help="correspondence markers: 'source_vertex target_vertex' a line (0-based; source "
        "vertices of ICT's face area, [0, 9409)); at least 3, about 20 spread over the face. "
        "'auto': none, ICT's face fitted to the target by closest points alone (the target "
        "facing +z with y up, as ICT does; landmarks within about 1.5 mm on ICT's identities)",
    )
    markers = parser.add_mutually_exclusive_group()
    markers.add_argument(
        "--marker-weight",
        type=float,
        default=0.01,
        metavar="M",
        help="after the first step, pull the markers to their places with M x the closest-point "
        "weight (default 0.01: forgives markers up to half an edge off their place)",
    )
    markers.add_argument(
        "--hold-markers",
        action="store_true",
        help="hold the markers exactly in every step, as the paper does",
    )
    add_solve_arguments(parser)
    parser.add_argument(
        "--names", nargs="+", metavar="NAME", help="ARKit names to make (default: all 51)"
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace target examples already in the folder"
    )
    parser.add_argument(
        "--ict", metavar="PATH",
        help="ICT-FaceKit folder or .npz (default: $FACECAST_ICT or ../shared/data/ict-facekit)",
    )  # fmt: skip
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def add_solve_arguments(parser: argparse.ArgumentParser) -> None:
    """--still F | --paper-solve, --no-lid-contact (here and in ``facecast bench transfer``)."""
    solve = parser.add_mutually_exclusive_group()
    solve.add_argument(
        "--still", type=float, default=0.01, metavar="F",
        help="hold the target points whose source point moves less than F x the expression's "
        "largest motion (default 0.01), so what an expression leaves still does not drift",
    )  # fmt: skip
    solve.add_argument(
        "--paper-solve", action="store_true",
        help="the paper's solve instead: one factorisation for every expression, nothing held "
        "but one vertex per piece (faster; the still parts drift; no lid contact)",
    )  # fmt: skip
    parser.add_argument(
        "--no-lid-contact", action="store_true",
        help="do not pull the blinks' lids together where the source's lids meet (by default "
        "a wider eye's lids meet as the source's do, where the target's lids are meshed at "
        "least as finely as the source's)",
    )  # fmt: skip


def lid_contact_names(args: argparse.Namespace) -> tuple[str, ...]:
    """The expressions whose lids are pulled together: the blinks, or none."""
    from facecast.rig.transfer.contact import LID_CONTACT

    return () if args.no_lid_contact else LID_CONTACT


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from facecast.rig.sources.ict import locate_ict
    from facecast.rig.transfer import (
        CorrespondenceWeights,
        check_mesh,
        check_still,
        ict_source_expressions,
        read_markers,
        read_target_mesh,
        transfer_expressions,
        write_expression_set,
    )

    # The inputs first (cheap, and their errors say what to fix), then the source.
    if not Path(args.target).is_file():
        raise CommandError(f"{args.target}: no such file (the target neutral mesh)")
    vertices, faces = check_mesh(*read_target_mesh(args.target), what=str(args.target))
    markers = args.markers
    if markers is not None and markers != "auto":
        markers = read_markers(markers)
    still = check_still(None if args.paper_solve else args.still)
    archive = None
    if args.ict is None or Path(args.ict).exists():
        archive = locate_ict(args.ict) if args.ict else locate_ict()
    if archive is None:
        raise CommandError(
            "ICT-FaceKit not found: its expressions are the source this command transfers. "
            "Set FACECAST_ICT to the folder holding ict_facekit.npz, pass --ict PATH, or place "
            "it in ../shared/data/ict-facekit (see that folder's README for the conversion)"
        )
    source = ict_source_expressions(archive)
    count = len(args.names) if args.names else len(source.names) - 1
    with tqdm(total=count, unit="expr", desc="transferring", disable=args.quiet) as bar:
        generated = transfer_expressions(
            source, vertices, faces, markers=markers, names=args.names, progress=bar.update,
            weights=CorrespondenceWeights(
                marker_weight=None if args.hold_markers else args.marker_weight
            ),
            still=still, lid_contact=lid_contact_names(args),
        )  # fmt: skip
    written = write_expression_set(
        args.output,
        generated,
        overwrite=args.overwrite,
        comment=(
            f"made by facecast expressions from {Path(args.target).name}: ICT-FaceKit's "
            "ARKit shapes moved onto it by deformation transfer (Sumner & Popovic 2004)"
        ),
    )
    seconds = generated.seconds
    how = {
        "identity": "same topology (identity)",
        "markers": "markers + closest points",
        "automatic": "automatic (closest points, no markers)",
    }[generated.correspondence.method]
    if generated.correspondence.method != "identity":
        how += f", residual {generated.correspondence.residual:.3g} edges"
    print(
        f"correspondence: {how}; {len(generated.correspondence.pairs)} triangle pairs, "
        f"{int(generated.correspondence.vertex_map.getnnz(axis=1).astype(bool).sum())} of "
        f"{vertices.shape[0]} target vertices reached"
    )
    once = generated.factorizations == 1
    print(
        f"cost: correspondence {seconds['correspondence']:.2f} s, "
        + (
            f"factor {seconds['factor']:.2f} s ({generated.unknowns} unknowns, once), "
            if once
            else f"set-up {seconds['factor']:.2f} s ({generated.unknowns} unknowns), "
        )
        + f"solve {seconds['solve']:.2f} s ({1e3 * seconds['solve'] / max(1, count):.0f} ms "
        + ("per expression)" if once else "per expression, each factoring what it moves)")
    )
    kept = f", kept {len(written.kept)} already there: {', '.join(written.kept)}"
    print(
        f"{written.folder}: wrote {len(written.written)} expression(s)"
        + (kept * bool(written.kept))
    )
    print(f"next: facecast fit {written.folder} -o character.rig")
    return 0

"""``facecast fit``: fit a rig from an example set and report how well it is determined.

Loads, fits, prints the fit report and writes the rig file; the numbers come from
``facecast.rig.fit`` and it must not compute any of its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from collections.abc import Sequence

    from facecast.cli.commands import Subparsers
    from facecast.rig.characters.character_model import PairingReport
    from facecast.rig.examples import ExampleSet

# The engine's kernel names (facecast.rig.radial.KERNELS), spelled out so --help does
# not import numpy; a test keeps the two equal.
KERNEL_CHOICES = ("bspline", "gaussian", "thin_plate", "linear")


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "fit",
        help="fit a rig from an example set",
        description=(
            "Fit the cardinal weight functions of an example set (Kim 2003, ch. 3) and write "
            "the rig file. Prints the PCA spectrum, the radial and hyperplane systems' "
            "condition numbers, the noise gain (and the landmark noise that moves the weights "
            "0.05 RMS, with a warning when it is far below any tracker's) and, per example, its "
            "nearest neighbour in parameter space."
        ),
    )
    parser.add_argument(
        "examples",
        metavar="EXAMPLES",
        help="a folder with facecast.toml, an .npz example set, a character (.glb, .gltf or "
        ".vrm: paired with facecast's generic ARKit source set, or with --source), or the word "
        "'demo' for the built-in procedural set",
    )
    parser.add_argument("-o", "--output", required=True, metavar="RIG", help="rig file to write")
    parser.add_argument(
        "--source",
        metavar="FOLDER",
        help="for a character: the folder of source examples (point files or meshes, named "
        "by expression) instead of facecast's generic ARKit set",
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="SIGMA",
        help="expected landmark noise (std per coordinate, source units); 0 = exact "
        "interpolation, the default for an example set; a character paired with the generic "
        "ARKit set is fitted by default for a live tracker's noise, 0.035 cm with --clamp "
        "unit (facecast.rig.characters.generic.CHARACTER_FIT_DEFAULTS, the same as "
        "PUT /v1/characters/{id}; docs/characters.md)",
    )
    parser.add_argument(
        "--pca-threshold",
        type=float,
        default=None,
        metavar="T",
        help="drop principal axes with eigenvalue below T times the largest (default: keep "
        "every axis above the points' float32 resolution)",
    )
    parser.add_argument(
        "--kernel", choices=KERNEL_CHOICES, default="bspline", help="radial cross-section"
    )
    parser.add_argument(
        "--clamp",
        choices=("none", "nonneg", "unit"),
        default=None,
        help="bound the non-neutral weights to >= 0 or [0, 1] (the nearest bounded weights in "
        "the metric of the examples; with --noise, the MAP weights under a sparsity prior); "
        "default nonneg with --noise, none without (a character on the generic ARKit set "
        "without --noise: unit)",
    )
    parser.add_argument(
        "--sparsity",
        type=float,
        default=None,
        metavar="S",
        help="with --clamp and --noise: exponential prior on the bounded weights, expecting "
        "a frame's non-neutral weights to add up to 1/S (default 0, the plain projection; "
        "real takes carry many small weights at once)",
    )
    parser.add_argument(
        "--stable-points",
        metavar="I,J,K",
        help="feature-point positions (0-based, among the K) that head-pose alignment fits "
        "the head's motion on: expressions must barely move them, so no jaw or lips (default: "
        "the example set's [source] stable_points, else all K, which the report flags)",
    )
    parser.add_argument(
        "--align-scale", action="store_true", help="head-pose alignment also removes scale"
    )
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(func=run)


def _stable_points(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        values = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise CommandError(
            f"--stable-points: expected comma-separated integers, got {text!r}"
        ) from None
    if len(values) < 3:
        raise CommandError("--stable-points: need at least 3 indices")
    return values


def load_character_examples(path: Path) -> tuple[ExampleSet, PairingReport]:
    """A character file's example set with the generic ARKit set, and its pairing report."""
    from facecast.rig.characters.character import load_character
    from facecast.rig.characters.character_examples import character_example_set

    character = load_character(path, label=path.name)
    return character_example_set(character, label=path.name)


def load_examples(spec: str, source: str | None = None) -> ExampleSet:
    """The example set named on the command line: a path, or ``demo``."""

    if spec == "demo":
        from facecast.rig.demo import demo_example_set

        return demo_example_set()
    from facecast.rig.characters.loaders import load_example_set

    path = Path(spec)
    if not path.exists():
        raise CommandError(f"{spec}: no such file or folder (expected an example set or 'demo')")
    if source is not None and not Path(source).exists():
        raise CommandError(f"{source}: no such folder (--source)")
    return load_example_set(path, source=source)


def _spectrum(eigenvalues: list[float], kept: int) -> str:
    top = eigenvalues[0] if eigenvalues and eigenvalues[0] > 0 else 1.0
    shown = [f"{e / top:.2g}" for e in eigenvalues[:12]]
    more = f" ... ({len(eigenvalues)} in all)" if len(eigenvalues) > 12 else ""
    return f"{', '.join(shown)}{more}  (relative to {top:.4g}; kept {kept})"


def format_report(report: dict[str, Any], names: Sequence[str]) -> str:
    lines = [
        f"examples M = {report['num_examples']}, feature points K = {report['num_points']}, "
        f"target vertices V = {report['num_vertices']}",
        f"kernel {report['kernel']}, noise {report['noise']:g}, "
        f"PCA threshold {report['pca_threshold']:g}",
        f"PCA eigenvalues: {_spectrum(report['eigenvalues'], report['components_kept'])}",
        f"radial system condition number: {report['condition_number']:.4g}",
        *_hyperplane_line(report),
        f"noise gain (RMS weight change per unit landmark noise): {report['noise_gain']:.4g}",
        *_tolerance_line(report),
        *_bounds_line(report),
        *_pose_lines(report),
        "identifiability (nearest other example, distance in parameter space):",
    ]
    order = sorted(range(len(names)), key=lambda i: report["nearest_distance"][i])
    width = max(len(n) for n in names) + 2
    for i in order:
        snr = report["separation_snr"][i]
        snr_text = "" if snr in (None, float("inf")) else f"  ({snr:.3g} noise std)"
        lines.append(
            f"  {names[i]:<{width}} -> {report['nearest_name'][i]:<{width}}"
            f"{report['nearest_distance'][i]:.4g}{snr_text}"
        )
    lines.append(f"fit time: {report['fit_seconds'] * 1e3:.1f} ms")
    return "\n".join(lines)


def _hyperplane_line(report: dict[str, Any]) -> list[str]:
    # Rig files fitted before the hyperplanes' conditioning was reported lack it.
    if report.get("hyperplane_condition_number") is None:
        return []
    return [
        f"hyperplane system [1, p] condition number: {report['hyperplane_condition_number']:.4g}"
    ]


def _tolerance_line(report: dict[str, Any]) -> list[str]:
    from facecast.rig.fit import NOISE_WEIGHT_CHANGE

    tolerance = report.get("noise_tolerance")
    if tolerance is None or tolerance == float("inf"):
        return []
    return [
        f"  landmark noise that moves the weights {NOISE_WEIGHT_CHANGE:g} RMS: {tolerance:.3g} "
        f"(feature points' extent {report.get('feature_extent', 0.0):.3g})"
    ]


def _pose_lines(report: dict[str, Any]) -> list[str]:
    from facecast.rig.pose import POSE_REFINE_MAX_CONDITION

    # Rig files fitted before head-pose refinement was reported lack the keys.
    if "pose_condition" not in report:
        return []
    stable = report.get("stable_points")
    if stable is None:
        line = (
            f"head-pose alignment (align): on all {report['num_points']} feature points - the "
            "example set names no stable points, so jaw and lip motion will first be taken "
            "for head motion (give --stable-points)"
        )
    else:
        line = f"head-pose alignment (align): on stable points {', '.join(map(str, stable))}"
    condition = report["pose_condition"]
    if condition == float("inf") or condition > POSE_REFINE_MAX_CONDITION:
        refine = (
            "  then no pose refinement: the examples leave too few directions of the feature "
            "points free to tell head motion from expression (add feature points)"
        )
    else:
        refine = (
            "  then refined against the examples' span (rigid motions' condition number "
            f"{condition:.4g})"
        )
    return [line, refine]


def _bounds_line(report: dict[str, Any]) -> list[str]:
    if report.get("clamp") is None:
        return []
    return [
        f"bounded weights: {report['clamp']}, sparsity prior {report.get('sparsity', 0.0):g} "
        f"(penalty {report.get('sparsity_penalty', 0.0):.4g})"
    ]


def run(args: argparse.Namespace) -> int:

    from facecast.rig import fit
    from facecast.rig.characters.character_examples import character_fit_options

    output = Path(args.output)
    if not output.parent.exists():
        raise CommandError(f"{output.parent}: no such folder for the rig file {output.name}")
    path = Path(args.examples)
    pairing = None
    if path.suffix.lower() in (".glb", ".gltf", ".vrm") and args.source is None:
        if not path.is_file():
            raise CommandError(f"{args.examples}: no such file")
        examples, pairing = load_character_examples(path)
        if not args.json:
            print("\n".join(pairing.lines()))
        options = character_fit_options({"noise": args.noise, "clamp": args.clamp})
    else:
        examples = load_examples(args.examples, args.source)
        options = {"noise": 0.0 if args.noise is None else args.noise, "clamp": args.clamp}
    with warnings.catch_warnings():
        # fit's IdentifiabilityWarnings are in the report, printed below once each.
        warnings.simplefilter("ignore")
        rig = fit(
            examples,
            pca_threshold=args.pca_threshold,
            noise=options["noise"],
            kernel=args.kernel,
            clamp=options.get("clamp"),
            sparsity=args.sparsity,
            stable_points=_stable_points(args.stable_points),
            align_scale=args.align_scale,
        )
    rig.save(output)
    report = rig.fit_report
    if args.json:
        from facecast.cli.report import json_safe

        payload = {"rig": str(output), "checksum": rig.checksum, "fit_report": report}
        if pairing is not None:
            payload["pairing"] = pairing.to_dict()
        print(json.dumps(json_safe(payload), indent=1))
    else:
        print(format_report(report, rig.names))
        for message in report["warnings"]:
            print(f"warning: {message}", file=sys.stderr)
        print(f"wrote {output} ({output.stat().st_size / 1e6:.1f} MB, {rig.checksum[:12]})")
    return 0

"""``facecast eval``: reproduce the thesis's experiments (ch. 4) and compare with peers.

Builds the data set (procedural demo, ICT-FaceKit, or files), calls
``facecast.rig.evaluation.evaluate.evaluate`` and presents its report; it must not compute errors itself.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from facecast.cli.commands.fit import load_examples
from facecast.cli.errors import CommandError

from .fit import KERNEL_CHOICES

if TYPE_CHECKING:  # numpy and the rig load when the command runs, not for --help
    from collections.abc import Callable

    import numpy as np

    from facecast.cli.commands import Subparsers
    from facecast.rig.examples import ExampleSet
    from facecast.rig.sources.animation import SourceAnimation

    #: Frame indices (n,) -> the source meshes' vertices (n, Vs, 3) and their faces.
    SourceFrames = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

DEFAULT_NOISE = 0.01  # cm: about a tenth of a millimetre of landmark jitter
PICTURE_TIMES = 4


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="measure cloning error and speed against peers (thesis ch. 4)",
        description=(
            "Clone an animation whose ideal result is known and report the thesis's eq. 4.1 "
            "error per axis, RMS and max vertex error, for rigs of several settings and for "
            "plain and non-negative least-squares weights, on clean and on noisy feature "
            "points; then the timing table (thesis Table 4.4). Data: --demo (procedural), "
            "--ict (ICT-FaceKit; truth = the target's expression mixes), --take CSV (a real "
            "Live Link Face take on ICT-FaceKit), or EXAMPLES SOURCE [--truth FILE]."
        ),
    )
    parser.add_argument("examples", metavar="EXAMPLES", nargs="?", help="an example set")
    parser.add_argument("source", metavar="SOURCE", nargs="?", help="a source animation")
    parser.add_argument("--truth", metavar="FILE", help="ideal target frames (F, V, 3): "
                        ".npy, or .npz with 'vertices'")  # fmt: skip
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--demo", action="store_true", help="use the procedural demo")
    group.add_argument(
        "--ict", nargs="?", const="", metavar="PATH",
        help="use ICT-FaceKit (default: $FACECAST_ICT or ../shared/data/ict-facekit)",
    )  # fmt: skip
    group.add_argument(
        "--take", metavar="CSV",
        help="a real Live Link Face CSV take driving ICT-FaceKit's ARKit-named shapes; the "
        "truth is the same weights on another ICT identity (--identity, default person01)",
    )  # fmt: skip
    parser.add_argument("--identity", metavar="PERSON", help="ICT target identity (person00...)")
    parser.add_argument(
        "--estimate-noise", action="store_true",
        help="estimate the landmark noise from the input's stillest half second and add the "
        "bounded rig fitted with it",
    )  # fmt: skip
    parser.add_argument(
        "--noise", type=float, default=DEFAULT_NOISE, metavar="SIGMA",
        help=f"std of the noise added to the source points (default {DEFAULT_NOISE}; 0 = "
        "clean only)",
    )  # fmt: skip
    parser.add_argument(
        "--kernels", nargs="+", choices=KERNEL_CHOICES, default=list(KERNEL_CHOICES),
        help="kernels to compare (default: all)",
    )  # fmt: skip
    parser.add_argument("--seconds", type=float, default=10.0, help="animation length (demo/ICT)")
    parser.add_argument("--fps", type=float, default=60.0, help="frame rate (demo/ICT)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the animation and noise")
    parser.add_argument("--no-timing", action="store_true", help="skip the timing table")
    parser.add_argument(
        "--smoothing",
        metavar="MIN_CUTOFF,BETA",
        default="2.0,2.0",
        help="one-euro filter settings for the jitter table shown with --noise (default 2,2, "
        "the protocol's smoothing defaults)",
    )
    parser.add_argument(
        "--temporal", action="store_true",
        help="with --noise: jitter, error and lag of one-euro and Kalman filters and of the "
        "offline RTS smoother at several settings (a table; a plot with --plots)",
    )  # fmt: skip
    parser.add_argument("--json", metavar="FILE", help="write the full report as JSON")
    parser.add_argument("--plots", metavar="DIR", help="write PNG plots into DIR")
    parser.set_defaults(func=run)


@dataclass
class _Data:
    """What an experiment needs: examples, source points, truth, and pictures' sources."""

    name: str
    examples: ExampleSet
    animation: SourceAnimation
    truth: np.ndarray | None
    source_frames: SourceFrames | None = None


def _demo(args: argparse.Namespace) -> _Data:
    from facecast.rig.demo import (
        demo_activations,
        demo_animation,
        demo_example_set,
        demo_target_frames,
    )

    seed = 7 if args.seed == 0 else args.seed  # 7 is the demo's own default performance
    examples = demo_example_set()
    animation = demo_animation(args.seconds, args.fps, with_vertices=bool(args.plots), seed=seed)
    truth = demo_target_frames(demo_activations(args.seconds, args.fps, seed=seed))

    def source_frames(indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        vertices, faces = animation.source_vertices, examples.source_faces
        assert vertices is not None and faces is not None  # with_vertices; the demo's meshes
        return vertices[indices], faces

    return _Data("demo", examples, animation, truth, source_frames if args.plots else None)


def _ict(args: argparse.Namespace) -> _Data:
    from facecast.rig.sources.ict import (
        ict_animation,
        ict_example_set,
        ict_target_frames,
        locate_ict,
    )

    archive = locate_ict(args.ict or None)
    if archive is None:
        raise CommandError(
            "ICT-FaceKit not found: pass --ict PATH or set FACECAST_ICT "
            "(looked in ../shared/data/ict-facekit)"
        )
    examples = ict_example_set(archive, identity=args.identity)
    activations, animation = ict_animation(
        examples, seconds=args.seconds, fps=args.fps, seed=args.seed
    )
    truth = ict_target_frames(examples, activations)

    def source_frames(indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        src, faces = examples.source_vertices, examples.source_faces
        assert src is not None and faces is not None  # ICT's example set keeps its meshes
        deltas = (src[1:] - src[0]).reshape(len(src) - 1, -1)
        frames = src[0].reshape(-1) + activations[indices, 1:] @ deltas
        return frames.reshape(len(indices), -1, 3), faces

    name = "ict" if args.identity is None else f"ict ({args.identity})"
    return _Data(name, examples, animation, truth, source_frames)


def _take(args: argparse.Namespace) -> _Data:
    from facecast.rig.evaluation.takes import take_experiment
    from facecast.rig.sources.animation import SourceAnimation
    from facecast.rig.sources.ict import locate_ict
    from facecast.rig.sources.ict_arkit import ARKIT_TARGET_IDENTITY, arkit_example_set
    from facecast.rig.sources.trackers import read_livelink_csv

    archive = locate_ict(args.ict or None)
    if archive is None:
        raise CommandError(
            "ICT-FaceKit not found (a take drives its shapes): set FACECAST_ICT or place it "
            "in ../shared/data/ict-facekit"
        )
    if not Path(args.take).is_file():
        raise CommandError(f"{args.take}: no such file (a Live Link Face CSV take)")
    identity = args.identity or ARKIT_TARGET_IDENTITY
    examples = arkit_example_set(archive, identity=identity)
    livelink = read_livelink_csv(args.take)
    experiment = take_experiment(examples, livelink.weights, livelink.fps)
    animation = SourceAnimation(points=experiment.points, fps=livelink.fps)
    return _Data(f"take {Path(args.take).name} -> ICT {identity}", examples, animation,
                 experiment.truth)  # fmt: skip


def _estimated_noise(args: argparse.Namespace, data: _Data) -> tuple[float, tuple[int, int]]:
    """Sigma from the stillest half second of the input the rigs see (noisy if --noise)."""
    import numpy as np

    from facecast.rig.noise import estimate_noise, still_segment

    points = data.animation.points
    if args.noise > 0:
        # The same noise evaluate adds (same seed, same draw).
        points = points + np.random.default_rng(args.seed).normal(0.0, args.noise, points.shape)
    window = max(2, min(len(points), round(0.5 * data.animation.fps)))
    start, stop = still_segment(points, window)
    return estimate_noise(points[start:stop]), (start, stop)


def _files(args: argparse.Namespace) -> _Data:
    import numpy as np

    from facecast.rig.sources.loading import load_source_animation

    if args.examples is None or args.source is None:
        raise CommandError("give EXAMPLES and SOURCE, or --demo, or --ict")
    examples = load_examples(args.examples)
    if not Path(args.source).exists():
        raise CommandError(f"{args.source}: no such file or folder (the source animation)")
    animation = load_source_animation(
        args.source, feature_indices=examples.feature_indices, num_points=examples.num_points
    )
    truth = None
    if args.truth is not None:
        path = Path(args.truth)
        if not path.is_file():
            raise CommandError(f"{path}: no such truth file")
        try:
            if path.suffix.lower() == ".npz":
                with np.load(path, allow_pickle=False) as archive:
                    truth = archive["vertices"]
            else:
                truth = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy/zipfile raise many types on a bad file
            raise CommandError(f"{path}: not a readable truth file ({exc})") from None
    return _Data(Path(args.examples).name, examples, animation, truth)


def _write_plots(folder: Path, data: _Data, report: dict[str, Any], fps: float) -> list[Path]:

    import numpy as np

    from facecast.cli.report import plot_error_over_time, save_frames_picture
    from facecast.rig import fit

    written = []
    if report["errors"] is not None:
        written.append(plot_error_over_time(folder / "error_over_time.png", report, fps=fps))
    frames = data.animation.num_frames
    indices = np.unique(np.linspace(0, frames - 1, PICTURE_TIMES + 2).round().astype(int)[1:-1])
    if indices.size == 0:
        indices = np.array([0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = fit(data.examples, noise=report["noise"])
    cloned = rig.clone(data.animation.points[indices])
    faces = rig.target_faces
    sources = data.source_frames(indices) if data.source_frames is not None else None
    rows = []
    for n, index in enumerate(indices):
        t = f"t={index / fps:.2f} s"
        row = []
        if sources is not None:
            row.append((f"source {t}", sources[0][n], sources[1]))
        if data.truth is not None:
            row.append((f"truth {t}", np.asarray(data.truth[index]), faces))
        row.append((f"cloned {t}", cloned[n], faces))
        rows.append(row)
    written.append(
        save_frames_picture(
            folder / "frames.png", rows,
            title=f"{data.name}: rig noise={report['noise']:g}, clean input",
        )
    )  # fmt: skip
    return [w for w in written if w is not None]


def _smoothing(
    args: argparse.Namespace, data: _Data, truth: np.ndarray, report: dict[str, Any]
) -> dict[str, Any]:
    """Jitter of the noisy take cloned raw and through the one-euro filter (a table, printed)."""
    import numpy as np

    from facecast.rig import fit
    from facecast.rig.evaluation.evaluate import smoothing_report

    try:
        min_cutoff, beta = (float(v) for v in args.smoothing.split(","))
    except ValueError:
        raise CommandError(f"--smoothing must be MIN_CUTOFF,BETA, got {args.smoothing!r}") from None
    label = next(lbl for lbl, entry in report["methods"].items() if not entry.get("failed"))
    with warnings.catch_warnings():
        # The settings compared on purpose (the exact rig among them): their fit
        # warnings are in the report already.
        warnings.simplefilter("ignore")
        rig = fit(data.examples, **report["methods"][label]["settings"])
    clean = data.animation.points
    noisy = clean + np.random.default_rng(args.seed).normal(0.0, args.noise, size=clean.shape)
    table = smoothing_report(
        rig, clean, noisy, truth, fps=data.animation.fps, min_cutoff=min_cutoff, beta=beta
    )
    table["rig"] = label
    print(
        f"\njitter (RMS 2nd difference of the cloned vertices, % of diagonal per frame^2), {label}:"
    )
    print(f"  {'input':<10}{'jitter':>12}{'RMS error %':>14}")
    print(f"  {'truth':<10}{table['truth']['jitter']:>12.5f}{'':>14}")
    for name in ("clean", "noisy", "filtered"):
        row = table[name]
        print(f"  {name:<10}{row['jitter']:>12.5f}{row['rms_percent']:>14.4f}")
    print(
        f"  one-euro filter (min_cutoff {min_cutoff:g}, beta {beta:g}) on the noisy points: "
        f"jitter x{table['filtered']['jitter'] / max(table['noisy']['jitter'], 1e-300):.2f}"
    )
    return table


def _temporal(
    args: argparse.Namespace, data: _Data, truth: np.ndarray, plots: Path | None
) -> dict[str, Any]:
    """Jitter against lag of filtered noisy input, cloned by the default bounded noise rig."""
    import numpy as np

    from facecast.cli.report import plot_jitter_against_lag
    from facecast.rig import fit
    from facecast.rig.evaluation.temporal import best_under_one_frame, temporal_tradeoff

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the settings are chosen; fit's advice is printed
        rig = fit(data.examples, noise=args.noise, clamp="nonneg")
    clean = data.animation.points
    noisy = clean + np.random.default_rng(args.seed).normal(0.0, args.noise, size=clean.shape)
    table = temporal_tradeoff(rig, noisy, truth, fps=data.animation.fps, noise=args.noise)
    table["best_under_one_frame"] = best_under_one_frame(table)
    print(
        f"\ntemporal filters on the noisy points (noise {args.noise:g}), rig clamp=nonneg: "
        f"jitter (% of diagonal per frame^2; truth {table['truth_jitter']:.4f}), lag, errors"
    )
    print(
        f"  {'filter':<34}{'jitter':>9}{'lag, frames':>13}{'RMS error %':>13}"
        f"{'eq. 4.1 % x / y / z':>26}{'max axis':>10}"
    )
    for row in table["rows"]:
        eq41 = " / ".join(f"{row['eq41_percent'][axis]:.3f}" for axis in "xyz")
        print(
            f"  {row['label']:<34}{row['jitter']:>9.4f}{row['lag_frames']:>13.2f}"
            f"{row['rms_percent']:>13.4f}{eq41:>26}{row['eq41_max']:>10.3f}"
        )
    for family, row in table["best_under_one_frame"].items():
        print(f"  best {family} under one frame of lag: {row['label']}")
    raw = table["rows"][0]
    for row in table["rows"]:
        if row["family"] == "clone":
            print(
                f"  'facecast clone' default ({row['label']}): eq. 4.1 max axis "
                f"{row['eq41_max']:.3f} = {row['eq41_max'] / raw['eq41_max']:.3f} x per-frame "
                f"{raw['eq41_max']:.3f}; lag {row['lag_frames']:.2f} frames (per-frame "
                f"{raw['lag_frames']:.2f})"
            )
    if plots is not None:
        path = plot_jitter_against_lag(
            plots / "jitter_vs_lag.png", table,
            title=f"{data.name}: jitter against lag, noise {args.noise:g}",
        )  # fmt: skip
        print(f"wrote {path}", file=sys.stderr)
    return table


def run(args: argparse.Namespace) -> int:
    from facecast.cli.report import format_error_table, format_timing_table, write_json
    from facecast.rig.evaluation.evaluate import default_settings, evaluate

    if args.json is not None and not Path(args.json).parent.exists():
        raise CommandError(f"{Path(args.json).parent}: no such folder for --json")
    if args.plots is not None:
        Path(args.plots).mkdir(parents=True, exist_ok=True)
    if args.noise < 0:
        raise CommandError(f"--noise must be >= 0, got {args.noise}")
    if args.temporal and args.noise <= 0:
        raise CommandError("--temporal needs --noise above 0 (the filters smooth noisy points)")
    if args.demo:
        data = _demo(args)
    elif args.take is not None:
        data = _take(args)
    elif args.ict is not None:
        data = _ict(args)
    else:
        data = _files(args)
    print(
        f"{data.name}: M = {data.examples.num_examples} examples, K = "
        f"{data.examples.num_points} feature points, V = {data.examples.num_vertices} target "
        f"vertices, {data.animation.num_frames} frames",
        file=sys.stderr,
    )
    settings = default_settings(args.noise, args.kernels)
    estimated = None
    if args.estimate_noise:
        sigma, (start, stop) = _estimated_noise(args, data)
        fps = data.animation.fps
        estimated = {"sigma": sigma, "frames": [start, stop]}
        print(
            f"estimated landmark noise: sigma = {sigma:.4g} from the stillest frames "
            f"[{start}, {stop}) (t = {start / fps:.2f}-{stop / fps:.2f} s)",
            file=sys.stderr,
        )
        settings.append(
            {"clamp": "nonneg", "noise": sigma, "label": f"rig clamp=nonneg noise=est {sigma:.3g}"}
        )
    report = evaluate(
        data.examples,
        data.animation,
        data.truth,
        settings=settings,
        noise=args.noise,
        seed=args.seed,
        timing=not args.no_timing,
        series=bool(args.json or args.plots),
    )
    report["dataset"] = data.name
    report["fps"] = data.animation.fps
    report["estimated_noise"] = estimated
    print(format_error_table(report))
    for label, entry in report["methods"].items():
        if entry.get("failed"):
            print(f"note: {label} could not be fitted: {entry['failed']}", file=sys.stderr)
    if report["timing"] is not None:
        print()
        print(format_timing_table(report["timing"], num_examples=report["num_examples"]))
    if args.noise > 0 and data.truth is not None:
        report["smoothing"] = _smoothing(args, data, data.truth, report)
    if args.temporal:
        if data.truth is None:
            raise CommandError("--temporal needs a known truth (--demo, --ict, --take, --truth)")
        plots = None if args.plots is None else Path(args.plots)
        report["temporal"] = _temporal(args, data, data.truth, plots)
    if args.plots is not None:
        for path in _write_plots(Path(args.plots), data, report, data.animation.fps):
            print(f"wrote {path}", file=sys.stderr)
    if args.json is not None:
        print(f"wrote {write_json(args.json, report)}", file=sys.stderr)
    return 0

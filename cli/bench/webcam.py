"""``facecast bench webcam``: the webcam path measured against ground truth.

An ICT-FaceKit identity performs a real take's ARKit weights and, clip by clip, its
key-expressions, rendered as 640 x 480 camera video (``facecast.cli.bench.facevideo``);
``facecast track`` tracks both; the performer's own rig is fitted from the tracked keys as
the server fits it, the tracked take is cloned onto another identity, and every path is
scored against the known ideal clone (eq. 4.1 per axis, jitter) beside NNLS on the same
points and the same pipeline on the exact landmarks. It must not tune itself to the goals.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
import warnings
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from facecast.cli.bench.facevideo import ARKIT_GAZE_DEGREES, HeadScene, head_scene, write_video
from facecast.cli.errors import CommandError
from facecast.cli.report import write_json
from facecast.cli.track import Tracker, track_video
from facecast.rig import fit
from facecast.rig.errors import ExampleSetError
from facecast.rig.evaluation.evaluate import cloning_error
from facecast.rig.evaluation.eyes import EYES_IDENTITY, EyesClip, eyes_clip, eyes_rows
from facecast.rig.evaluation.takes import take_experiment
from facecast.rig.evaluation.webcam import (
    CLOSURE_LEVEL,
    GOAL_GENERIC_PERCENT,
    GOAL_PERSONAL_PERCENT,
    KEY_HOLD_FRAMES,
    KEY_RAMP_FRAMES,
    PERFORMER_IDENTITY,
    Performer,
    captured_keys,
    hold_last_found,
    ict_performer,
    key_clips,
    on_generic_set,
    source_on_neutral,
    superposition,
    webcam_rows,
)
from facecast.rig.filters import KalmanFilter
from facecast.rig.rebase import (
    REBASE_BLINK_CONTRAST,
    REBASE_BLINK_CONTRAST_GAZELESS,
    default_contrast,
)
from facecast.rig.sources.capture import robust_example
from facecast.rig.sources.ict import DEFAULT_LANDMARKS, ict_regions, locate_ict
from facecast.rig.sources.ict_arkit import ARKIT_TARGET_IDENTITY, arkit_example_set
from facecast.rig.sources.layouts import load_layout
from facecast.rig.sources.trackers import read_livelink_csv
from facecast.server.storage.profiles import held_noise

if TYPE_CHECKING:
    from facecast.rig.evaluation.takes import TakeExperiment
    from facecast.rig.evaluation.webcam import KeyClips
    from facecast.rig.examples import ExampleSet
    from facecast.rig.rig import Rig

#: The bundled real take (tests/data/livelink), BSD-2-Clause.
BUNDLED_TAKE = Path(__file__).resolve().parents[2] / "tests" / "data" / "livelink" / "llv_dao.csv"
#: Frame rate of the key clips' video (a calibration is filmed at camera rate).
KEY_FPS = 30.0
#: The paths scored, in the table's order; generic rows follow ``_generic_rigs``.
PERSONAL, NNLS = "personal", "nnls"
#: The eyes clip's live Kalman accelerations scored by default (noise units per s^2).
EYES_KALMAN = (480.0,)
#: ``--generic-neutral tracked``: frames of ICT's generic face at rest rendered and tracked,
#: and the first of them left out (the page's eye crops settle over 9 frames, eyelids.js).
GENERIC_NEUTRAL_FRAMES, GENERIC_NEUTRAL_SETTLE = 30, 10


@dataclass(frozen=True, eq=False)
class _Setup:
    """The experiment: performer, character, take, keys and the truth."""

    performer: Performer
    examples: ExampleSet  # the character's (ARKit-named, the target identity)
    experiment: TakeExperiment
    clips: KeyClips
    character: Rig  # the character's rig as imported (exact)
    generic: Rig  # the tracked generic rows' rig: the character on facecast's shipped source
    take_name: str
    performer_id: str
    target_id: str
    eyes_performer: Performer  # another identity: performs its keys, then the eyes clip
    eyes_id: str
    eyes: EyesClip


def _setup(args: argparse.Namespace) -> _Setup:

    archive = locate_ict(args.ict) if args.ict else locate_ict()
    if archive is None:
        raise CommandError(
            "ICT-FaceKit not found: pass --ict PATH or set FACECAST_ICT "
            "(looked in ../shared/data/ict-facekit)"
        )
    take_path = Path(args.take) if args.take else BUNDLED_TAKE
    if not take_path.is_file():
        raise CommandError(f"{take_path}: no such file (a Live Link Face CSV take)")
    performer_id = args.performer or PERFORMER_IDENTITY
    target_id = args.target or ARKIT_TARGET_IDENTITY
    if performer_id == target_id:
        raise CommandError(f"--performer and --target are both {performer_id}: the benchmark "
                           "clones one face onto another")  # fmt: skip
    eyes_id = args.eyes_performer or EYES_IDENTITY
    if eyes_id in (performer_id, target_id):
        raise CommandError(f"--eyes-performer {eyes_id} is the take's performer or the "
                           "target: the eyes clip is performed by another face")  # fmt: skip
    take = read_livelink_csv(take_path)
    weights = take.weights if args.frames is None else take.weights[: args.frames]
    if len(weights) < 3:
        raise CommandError(f"the take has {len(weights)} frames; at least 3 are needed")
    landmarks = DEFAULT_LANDMARKS if args.landmarks is None else tuple(args.landmarks)
    if landmarks != DEFAULT_LANDMARKS and not args.exact_only:
        raise CommandError("--landmarks needs --exact-only: the tracker gives the page's layout")
    try:
        examples = arkit_example_set(archive, identity=target_id, landmarks=landmarks)
    except ExampleSetError as error:
        raise CommandError(f"--landmarks: {error}") from None
    performer = ict_performer(archive, identity=performer_id, landmarks=landmarks)
    eyes_performer = ict_performer(archive, identity=eyes_id, landmarks=landmarks)
    clips = key_clips(
        performer.names,
        keys=args.keys,
        ramp=KEY_RAMP_FRAMES if args.ramp is None else args.ramp,
        hold=KEY_HOLD_FRAMES if args.hold is None else args.hold,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact ICT rig warns to fit with noise: known
        character = fit(examples)
        generic = (
            character
            if args.generic_neutral != "shipped"
            else fit(on_generic_set(examples, uploaded=args.as_uploaded))
        )
    return _Setup(
        performer=performer,
        examples=examples,
        experiment=take_experiment(examples, weights, take.fps),
        clips=clips,
        character=character,
        generic=generic,
        take_name=take_path.name,
        performer_id=performer_id,
        target_id=target_id,
        eyes_performer=eyes_performer,
        eyes_id=eyes_id,
        eyes=eyes_clip(eyes_performer.names, short=args.eyes_short),
    )


def _on_tracked_generic_neutral(setup: _Setup, args: argparse.Namespace, folder: Path) -> _Setup:
    """``setup`` with the character's source neutral as ``facecast track`` sees ICT's generic
    face at rest (rendered as the performers are; kept in ``folder``): the generic rows'
    source, each shape keeping ICT's own displacements (``webcam.source_on_neutral``)."""
    archive = locate_ict(args.ict) if args.ict else locate_ict()
    assert archive is not None  # _setup found it
    regions, landmarks68 = ict_regions(archive)
    face = ict_performer(archive, identity=None)
    rest = np.zeros((GENERIC_NEUTRAL_FRAMES, len(face.names)))
    gaze = f"-gaze{args.gaze_degrees:g}" if args.gaze_degrees else ""
    path = folder / f"generic-neutral{GENERIC_NEUTRAL_FRAMES}-sway{args.sway:g}{gaze}.y4m"
    scene = head_scene(face, regions, landmarks68)
    points, found = _render_and_track("generic neutral", path, scene, face, rest, KEY_FPS, args,
                                      {"videos": {}, "render_seconds": {}, "track_seconds": {}})  # fmt: skip
    held = points[GENERIC_NEUTRAL_SETTLE:][found[GENERIC_NEUTRAL_SETTLE:]]
    if len(held) < 3:
        raise CommandError("the tracker found no face in ICT's generic face at rest")
    neutral, _, _ = robust_example(held)
    examples = source_on_neutral(setup.examples, neutral)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact ICT rig warns to fit with noise: known
        character = fit(examples)
    return replace(setup, examples=examples, character=character, generic=character)


def _generic_rigs(
    setup: _Setup, noise: float, shipped: bool
) -> dict[str, tuple[Rig, float | None]]:
    """The generic path's rows: the character as ``facecast import`` + ``rigs put`` store it
    (exact), re-based as the page does (a ``calibrate`` carrying the held frames' noise),
    and, for comparison, exactly as a calibrate without noise did before; and the rig
    fitted with the measured noise, bounded, re-based exactly. With ``shipped`` (tracked
    landmarks: the shipped source has the layout's 26 points) the ``generic`` row is the
    character on facecast's shipped generic source and ``generic (ICT landmarks)`` the
    character on ICT's exact landmarks, the row before option (z)."""

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bounded = fit(setup.examples, noise=noise, clamp="nonneg")
    rows: dict[str, tuple[Rig, float | None]] = {"generic": (setup.character, noise)}
    if shipped and setup.generic is not setup.character:
        rows = {
            "generic": (setup.generic, noise),
            "generic (ICT landmarks)": (setup.character, noise),
        }
    return {
        **rows,
        "generic exact": (setup.character, None),
        "generic noise": (bounded, None),
    }


def _score_landmarks(
    setup: _Setup,
    take_points: np.ndarray,
    key_points: np.ndarray,
    key_found: np.ndarray | None,
    *,
    shipped: bool = False,
    kalman: tuple[float, ...] = EYES_KALMAN,
    contrast: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Every path on one kind of landmarks (exact or tracked): the rows and the capture,
    the generic rows' blinks read through ``contrast`` (--blink-contrast; None: the server's).

    And the personal and the generic path on the take's points through the live Kalman
    filter at each ``kalman`` acceleration (noise units per s^2, the held frames' noise),
    as a channel filters a publisher's frames with ``smoothing`` (PROTOCOL.md §5.1.1):
    rows ``"<path> live kalman <a>"``: at the default 480, what viewers of /perform and
    ``facecast perform`` get (their auto ``smoothing``; the filter does not depend on the
    noise, only on one being known)."""

    keys, held = captured_keys(key_points, setup.clips, key_found)
    noise, held_frames = held_noise(held)
    experiment = setup.experiment
    mix, residual, slow = superposition(
        take_points, keys, experiment.activations, setup.character.names
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fit's advice on the bounded rigs: chosen settings
        rows = webcam_rows(
            setup.character,
            experiment.truth,
            experiment.activations,
            take_points,
            keys,
            noise=noise,
            generic=(generic_rigs := _generic_rigs(setup, noise, shipped)),
            personal_also={"keys' mix": mix},
            contrast=contrast,
        )
        generic = generic_rigs["generic"]
        times = np.arange(len(take_points)) / experiment.fps
        flat = np.asarray(take_points, dtype=np.float64).reshape(len(take_points), -1)
        for acceleration in kalman:
            live = KalmanFilter(noise=noise, acceleration=acceleration * noise)
            filtered = live.filter_series(flat, times).reshape(np.shape(take_points))
            through = webcam_rows(setup.character, experiment.truth, experiment.activations,
                                  filtered, keys, noise=noise, generic={"generic": generic},
                                  contrast=contrast)  # fmt: skip
            for path in (PERSONAL, "generic"):
                rows[f"{path} live kalman {acceleration:g}"] = through[path]
    return {
        "superposition_rms": residual,
        "superposition_slow_rms": slow,
        "noise": noise,
        "held_frames": held_frames,
        "keys_captured": len(keys),
        "keys": len(setup.clips.names),
        "rows": rows,
    }


def _curve_text(contrast: tuple[float, float] | None, generic: Rig) -> str:
    """The blink curve the generic rows read the captured closed eyes through, for the
    header: --blink-contrast (as a client's calibrate ``blink_contrast`` asks), else the
    server's for each rig (``rebase.default_contrast``), which /perform and ``facecast
    perform`` get unless their performer sets one."""

    def text(curve: tuple[float, float]) -> str:
        return "–".join(f"{v:g}" for v in curve)

    if contrast is not None:
        return f"{text(contrast)} (--blink-contrast)"
    return (
        f"the server's for each rig ({text(REBASE_BLINK_CONTRAST)} with eye-look shapes, "
        f"{text(REBASE_BLINK_CONTRAST_GAZELESS)} without; the tracked generic rows' "
        f"{text(default_contrast(generic.names))})"
    )


def _eyes_filters(args: argparse.Namespace) -> dict[str, tuple[str, float | None]]:
    """The eyes clip's rows per path: live unfiltered (/perform's ``smoothing=off``),
    through the live Kalman filter at each --kalman acceleration (at 480 what /perform and
    ``facecast perform`` publish), and offline (``clone``'s RTS)."""
    filters: dict[str, tuple[str, float | None]] = {"live": ("none", None)}
    for acceleration in args.kalman or EYES_KALMAN:
        filters[f"live kalman {acceleration:g}"] = ("kalman", acceleration)
    filters["offline"] = ("rts", None)
    return filters


def _score_eyes(
    setup: _Setup,
    args: argparse.Namespace,
    points: np.ndarray,
    found: np.ndarray | None,
    *,
    shipped: bool = False,
    contrast: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """The eyes video's points (its keys, then the clip) scored per event on every path
    (the generic path's blinks through ``contrast``)."""
    split = len(setup.clips.activations)
    keys, held = captured_keys(
        points[:split], setup.clips, None if found is None else found[:split]
    )
    noise, _ = held_noise(held)
    clip_found = np.ones(len(points) - split, bool) if found is None else found[split:]
    if not clip_found.any():
        raise CommandError("the tracker found no face in the eyes clip's video")
    clip_points = hold_last_found(points[split:], clip_found)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fit's advice on the bounded rigs: chosen settings
        rows = eyes_rows(setup.character, setup.eyes, clip_points, keys, noise=noise,
                         fps=KEY_FPS, filters=_eyes_filters(args),
                         generic=setup.generic if shipped else None,
                         contrast=contrast)  # fmt: skip
    return {
        "performer": setup.eyes_id,
        "short": args.eyes_short,
        "noise": noise,
        "keys_captured": len(keys),
        "clip_frames": len(clip_points),
        "clip_found": int(clip_found.sum()),
        "rows": rows,
    }


def _print_eyes(title: str, scored: dict[str, Any]) -> None:
    print(
        f"\neyes clip{' (short: not scores to compare)' if scored['short'] else ''}, {title}: "
        f"performed by ICT {scored['performer']} ({scored['clip_frames']} "
        f"frames at {KEY_FPS:g} fps, {scored['keys_captured']} keys captured); blink peaks "
        "per eye as a share of the truth (min, mean), winks' own eye (min) and other eye "
        "(max; truth 1 and 0), gaze holds seen in the right direction and how shut the eyes "
        "read on them (the blinks' mean over the four holds; truth 0), jaw + "
        "smile as % of the truth, and the goals passed (b w g c)"
    )
    print(f"  {'path':<26}{'blink min':>10}{'mean':>7}{'wink':>7}{'other':>7}{'gaze':>6}"
          f"{'shut':>6}{'jaw %':>7}{'smile %':>8}  goals")  # fmt: skip
    for label, row in scored["rows"].items():
        peaks = [v for blink in row["blinks"] for v in blink.values()]
        winks, gaze, combo = row["winks"], row["gaze"], row["combo"][0]
        right = sum(g["right"] for g in gaze)
        goals = " ".join("+" if ok else "-" for ok in row["goals"].values())
        print(
            f"  {label:<26}{min(peaks):>10.2f}{np.mean(peaks):>7.2f}"
            f"{min(w['peak'] for w in winks):>7.2f}{max(w['other'] for w in winks):>7.2f}"
            f"{right:>4}/{len(gaze)}{np.mean([g['shut'] for g in gaze]):>6.2f}"
            f"{100 * combo['jawOpen']:>7.0f}{100 * combo['smile']:>8.0f}"
            f"  {goals}"
        )


def _video_paths(folder: Path, args: argparse.Namespace, setup: _Setup) -> dict[str, Path]:
    """Where each video goes, named by everything its frames depend on (so a kept video
    is reused only for the same settings)."""
    clips = setup.clips
    ramp = clips.held[1][0] - clips.held[0][1] if len(clips.held) > 1 else 0
    hold = clips.held[0][1] - clips.held[0][0]
    gaze = f"-gaze{args.gaze_degrees:g}" if args.gaze_degrees else ""  # 0: the names as before
    face = f"{setup.performer_id}-sway{args.sway:g}{gaze}"
    take = f"{setup.take_name.rsplit('.', 1)[0]}-{len(setup.experiment.activations)}"
    performed = zlib.crc32(",".join(clips.names).encode())
    keys = f"keys{len(clips.names)}-{performed:08x}-ramp{ramp}-hold{hold}"
    eyes = f"eyes{len(setup.eyes.activations)}-{keys}-{setup.eyes_id}-sway{args.sway:g}{gaze}"
    return {
        "take": folder / f"{take}-{face}.y4m",
        "keys": folder / f"{keys}-{face}.y4m",
        "eyes": folder / f"{eyes}.y4m",
    }


def eyes_activations(setup: _Setup) -> np.ndarray:
    """The eyes video's weights: the eyes performer's key clips, then the eyes clip."""
    return np.concatenate([setup.clips.activations, setup.eyes.activations])


def _tracked(args: argparse.Namespace, setup: _Setup, folder: Path) -> dict[str, Any]:
    """Render the videos (unless kept from an earlier run) and track every frame of each:
    the take and the keys (unless --eyes-only), the eyes video (unless --no-eyes)."""

    archive = locate_ict(args.ict) if args.ict else locate_ict()
    assert archive is not None  # run() found it before anything was rendered
    regions, landmarks68 = ict_regions(archive)
    paths = _video_paths(folder, args, setup)
    plan: dict[str, tuple[Performer, np.ndarray, float]] = {}
    if not args.eyes_only:
        plan["take"] = (setup.performer, setup.experiment.activations, setup.experiment.fps)
        plan["keys"] = (setup.performer, setup.clips.activations, KEY_FPS)
    if not args.no_eyes:
        plan["eyes"] = (setup.eyes_performer, eyes_activations(setup), KEY_FPS)
    out: dict[str, Any] = {"videos": {}, "render_seconds": {}, "track_seconds": {}}
    # One browser for every video still to track (none when all were kept): its start and
    # the model's load once, not once a video (~3 CPU-s each; the points are the same).
    untracked = [name for name in plan if not _points_path(paths[name], args).is_file()]
    with Tracker(backend=args.backend) if untracked else contextlib.nullcontext() as tracker:
        for name, (performer, activations, fps) in plan.items():
            scene = head_scene(performer, regions, landmarks68)
            out[name] = _render_and_track(name, paths[name], scene, performer, activations,
                                          fps, args, out, tracker)  # fmt: skip
    return out


def _points_path(path: Path, args: argparse.Namespace) -> Path:
    """Where the points tracked from the video at ``path`` are kept. They are the layout's:
    its feature count in the name, so a layout that grew (20 -> 24 points) tracks the kept
    videos again instead of reading the old points."""
    k = load_layout().num_features
    return path.with_name(f"{path.stem}-{args.backend}-k{k}.npz")


def _render_and_track(
    name: str,
    path: Path,
    scene: HeadScene,
    performer: Performer,
    activations: np.ndarray,
    fps: float,
    args: argparse.Namespace,
    out: dict[str, Any],
    tracker: Tracker | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One video rendered (unless kept) and tracked (unless kept; in ``tracker`` when
    given): its points and found flags; the seconds each took go into ``out`` under
    ``name``."""
    points_path = _points_path(path, args)
    if not path.is_file():
        started = time.perf_counter()
        partial = path.with_name(path.name + ".partial")  # a cut-short run leaves no video
        write_video(partial, scene, performer, activations, fps=fps, sway_degrees=args.sway,
                    gaze_degrees=args.gaze_degrees)  # fmt: skip
        partial.replace(path)
        out["render_seconds"][name] = time.perf_counter() - started
    if points_path.is_file():
        with np.load(points_path) as kept:
            points, found = kept["points"], kept["found"]
    else:
        started = time.perf_counter()
        result = tracker.track(path) if tracker else track_video(path, backend=args.backend)
        out["track_seconds"][name] = time.perf_counter() - started
        partial = points_path.with_name(points_path.name + ".partial")
        result.save(partial).replace(points_path)
        points, found = result.points, result.found
    out["videos"][name] = str(path)
    return points.astype(np.float64), found.astype(bool)


def _row_text(label: str, row: dict[str, Any]) -> str:
    axes = row["eq41_percent"]
    worst = max(axes.values())
    return (
        f"  {label:<25}{axes['x']:>7.3f}{axes['y']:>8.3f}{axes['z']:>8.3f}{worst:>10.3f}"
        f"{row['jitter_percent']:>10.4f}{max(row['weight_rms'].values()):>12.3f}"
    )


def _print_table(title: str, scored: dict[str, Any]) -> None:
    print(
        f"\n{title}: {scored['keys_captured']} of {scored['keys']} keys captured, landmark "
        f"noise sigma = {scored['noise'] * 10:.3f} mm from {scored['held_frames']} held frames"
    )
    print(
        f"  {'path':<25}{'x':>7}{'y':>8}{'z':>8}{'max axis':>10}{'jitter':>10}{'worst w RMS':>12}"
    )
    for label, row in scored["rows"].items():
        print(_row_text(label, row))
    print(
        f"  the take's points lie {scored['superposition_rms'] * 10:.2f} mm RMS from the true "
        f"weights' mix of the captured keys ({scored['superposition_slow_rms'] * 10:.2f} mm "
        'of it slow: a 7-frame average); "personal on keys\' mix" clones that mix'
    )
    _print_closures(scored["rows"])


def _print_closures(rows: dict[str, Any]) -> None:
    """The take's real eye closures per path: each eye's peak shares (least-most) and r."""
    first = next(iter(rows.values()))["closures"]
    if not any(c["events"] for c in first.values()):
        return
    counts = ", ".join(f"{len(c['events'])} {name.removeprefix('eyeBlink').lower()}"
                       for name, c in first.items())  # fmt: skip
    print(
        f"  the take's eye closures (its true eyeBlink at least {CLOSURE_LEVEL}, the real "
        f"performer's: {counts}): each eye's peak as a share of the truth (least-most), and r"
    )
    for label, row in rows.items():
        cells = []
        for name, c in row["closures"].items():
            shares = [e["share"] for e in c["events"]]
            r = "-" if c["correlation"] is None else f"{c['correlation']:.2f}"
            span = f"{min(shares):.2f}-{max(shares):.2f}" if shares else "none"
            cells.append(f"{name.removeprefix('eyeBlink').lower()} {span} r {r}")
        print(f"  {label:<25}" + "   ".join(cells))


def _print_by_name(title: str, scored: dict[str, Any]) -> None:
    rows = scored["rows"]
    labels = list(rows)
    widths = [max(10, len(label)) + 2 for label in labels]
    print(f"\nRMS weight error per ARKit name, {title}:")
    print(f"  {'name':<20}" + "".join(f"{lab:>{w}}" for lab, w in zip(labels, widths, strict=True)))
    for name in next(iter(rows.values()))["weight_rms"]:
        cells = (rows[lab]["weight_rms"][name] for lab in labels)
        print(f"  {name:<20}" + "".join(f"{c:>{w}.3f}" for c, w in zip(cells, widths, strict=True)))


def _take_goals(rows: dict[str, Any], kalman: tuple[float, ...]) -> dict[str, dict[str, Any]]:
    """Issue 34's take goals on the rows viewers get (the live filter at the first of
    ``kalman``): per path the row, its worst axis, the goal and whether it is met."""
    goals = {}
    for path, goal in ((PERSONAL, GOAL_PERSONAL_PERCENT), ("generic", GOAL_GENERIC_PERCENT)):
        row = f"{path} live kalman {kalman[0]:g}"
        figure = _max_axis(rows[row])
        goals[path] = {"row": row, "figure": figure, "goal": goal, "pass": figure <= goal}
    return goals


def _max_axis(row: dict[str, Any]) -> float:
    return float(max(row["eq41_percent"].values()))


def run(args: argparse.Namespace) -> int:

    if args.json is not None and not Path(args.json).parent.exists():
        raise CommandError(f"{Path(args.json).parent}: no such folder for --json")
    if args.frames is not None and args.frames < 3:
        raise CommandError(f"--frames must be at least 3, got {args.frames}")
    if not (0.0 <= args.sway <= 10.0):
        raise CommandError(f"--sway must lie in [0, 10] degrees, got {args.sway}")
    if args.gaze_degrees is None:
        args.gaze_degrees = ARKIT_GAZE_DEGREES
    if not (0.0 <= args.gaze_degrees <= 45.0):
        raise CommandError(f"--gaze-degrees must lie in [0, 45], got {args.gaze_degrees}")
    if any(not (np.isfinite(a) and a > 0) for a in args.kalman or ()):
        raise CommandError(f"--kalman accelerations must be finite and > 0, got {args.kalman}")
    if args.eyes_only and args.no_eyes:
        raise CommandError("--eyes-only and --no-eyes leave nothing to measure")
    if args.as_uploaded and args.generic_neutral != "shipped":
        raise CommandError("--as-uploaded pairs the character on the shipped generic set: "
                           "only with --generic-neutral shipped")  # fmt: skip
    if args.generic_neutral == "tracked" and args.exact_only:
        raise CommandError("--generic-neutral tracked renders and tracks ICT's generic face: "
                           "not with --exact-only")  # fmt: skip
    started = time.perf_counter()
    setup = _setup(args)
    if args.generic_neutral == "tracked":
        if args.videos:
            Path(args.videos).mkdir(parents=True, exist_ok=True)
            setup = _on_tracked_generic_neutral(setup, args, Path(args.videos))
        else:
            with tempfile.TemporaryDirectory(prefix="facecast-webcam-") as scratch:
                setup = _on_tracked_generic_neutral(setup, args, Path(scratch))
    experiment = setup.experiment
    truth_jitter = cloning_error(experiment.truth, experiment.truth)["jitter_percent"]
    contrast = args.blink_contrast
    print(
        f"webcam benchmark: take {setup.take_name} ({len(experiment.activations)} frames at "
        f"{experiment.fps:g} fps) performed by ICT {setup.performer_id}, cloned onto "
        f"{setup.target_id} ({setup.examples.num_vertices} vertices); "
        f"{len(setup.clips.names)} key clips ({len(setup.clips.activations)} frames at "
        f"{KEY_FPS:g} fps). eq. 4.1 % per axis; jitter % of the diagonal per frame^2 (truth "
        f"{truth_jitter:.4f}); worst weight RMS over the ARKit names",
        file=sys.stderr,
    )
    print(
        "the generic path's captured closed eyes read through "
        + _curve_text(contrast, setup.generic),
        file=sys.stderr,
    )
    performer = setup.performer
    report: dict[str, Any] = {
        "take": setup.take_name,
        "frames": len(experiment.activations),
        "fps": experiment.fps,
        "truth_jitter_percent": truth_jitter,
        "key_clip_frames": len(setup.clips.activations),
        "sway_degrees": args.sway,
        "gaze_degrees": args.gaze_degrees,
        "generic_neutral": args.generic_neutral,
        "blink_contrast": contrast,
        "as_uploaded": args.as_uploaded,
    }
    if not args.eyes_only:
        exact = _score_landmarks(
            setup,
            performer.landmark_points(experiment.activations),
            performer.landmark_points(setup.clips.activations),
            None,
            kalman=tuple(args.kalman or EYES_KALMAN),
            contrast=contrast,
        )
        report["exact"] = exact
        _print_table("exact landmarks (the ICT landmark vertices, head frame)", exact)
        if args.by_name and args.exact_only:
            _print_by_name("exact landmarks", exact)
    if not args.no_eyes:
        eyes = _score_eyes(
            setup,
            args,
            setup.eyes_performer.landmark_points(eyes_activations(setup)),
            None,
            contrast=contrast,
        )
        report["eyes_exact"] = eyes
        _print_eyes("exact landmarks", eyes)
    if not args.exact_only:
        if args.videos:
            folder = Path(args.videos)
            folder.mkdir(parents=True, exist_ok=True)
            tracked_raw = _tracked(args, setup, folder)
        else:
            with tempfile.TemporaryDirectory(prefix="facecast-webcam-") as scratch:
                tracked_raw = _tracked(args, setup, Path(scratch))
        if not args.no_eyes:
            eyes = _score_eyes(setup, args, *tracked_raw["eyes"], shipped=True, contrast=contrast)
            eyes["render_seconds"] = tracked_raw["render_seconds"].get("eyes")
            eyes["track_seconds"] = tracked_raw["track_seconds"].get("eyes")
            report["eyes_tracked"] = eyes
            _print_eyes("tracked landmarks (facecast track)", eyes)
    if not args.exact_only and not args.eyes_only:
        take_points, take_found = tracked_raw["take"]
        key_points, key_found = tracked_raw["keys"]
        if not take_found.any():
            raise CommandError("the tracker found no face in the take's video")
        tracked = _score_landmarks(
            setup,
            hold_last_found(take_points, take_found),
            key_points,
            key_found,
            shipped=True,
            kalman=tuple(args.kalman or EYES_KALMAN),
            contrast=contrast,
        )
        tracked["take_found"] = int(take_found.sum())
        tracked["key_found"] = int(key_found.sum())
        tracked["render_seconds"] = tracked_raw["render_seconds"]
        tracked["track_seconds"] = tracked_raw["track_seconds"]
        report["tracked"] = tracked
        _print_table(
            f"tracked landmarks (facecast track; face found in {tracked['take_found']} of "
            f"{len(take_found)} take frames, {tracked['key_found']} of {len(key_found)} key "
            "frames)",
            tracked,
        )
        personal, nnls = tracked["rows"][PERSONAL], tracked["rows"][NNLS]
        exact = report["exact"]
        share = 1.0 - _max_axis(exact["rows"][PERSONAL]) / max(_max_axis(personal), 1e-12)
        report["tracker_share_personal"] = share
        if args.by_name:
            _print_by_name("tracked landmarks", tracked)
        verdict = "PASS" if _max_axis(personal) < _max_axis(nnls) else "FAIL"
        report["goal_personal_below_nnls"] = verdict
        print(
            f"\ngoal: personal below NNLS on the same tracked points (max axis): "
            f"{_max_axis(personal):.3f} against {_max_axis(nnls):.3f}: {verdict}"
        )
        report["take_goals"] = _take_goals(tracked["rows"], tuple(args.kalman or EYES_KALMAN))
        for path, goal in report["take_goals"].items():
            print(
                f"goal: {path} at most {goal['goal']:g} % as viewers get it ({goal['row']}, max "
                f"axis): {goal['figure']:.3f}: {'PASS' if goal['pass'] else 'FAIL'}"
            )
        print(
            f"the tracker's share of the personal path's error (max axis): {100 * share:.0f} % "
            f"(exact landmarks {_max_axis(exact['rows'][PERSONAL]):.3f}, tracked "
            f"{_max_axis(personal):.3f})"
        )
    report["seconds"] = time.perf_counter() - started
    report["load_average"] = os.getloadavg()
    if args.json is not None:
        print(f"wrote {write_json(args.json, report)}", file=sys.stderr)
    return 0

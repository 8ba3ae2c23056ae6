"""``facecast bench``: the benchmarks (engine, transport, broadcast, transfer, webcam, live) as sub-commands.

Only parses arguments and hands over to ``facecast.cli.bench.<name>.run(args)``; it must
not measure anything itself.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from typing import TYPE_CHECKING

from facecast.cli.commands.expressions import add_solve_arguments
from facecast.cli.commands.perform import blink_contrast_arg
from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers


def _add_ict(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--ict", metavar="PATH",
        help="ICT-FaceKit folder or .npz (default: $FACECAST_ICT or ../shared/data/ict-facekit)",
    )  # fmt: skip


def _add_take(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--take", metavar="CSV", help="a Live Link Face CSV take (default: the bundled llv_dao)"
    )


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmarks of the engine, the transport and the broadcast path",
        description="Measure against a baseline from the same run and print PASS/FAIL per goal.",
    )
    sub = parser.add_subparsers(dest="bench", metavar="BENCH", required=True)

    engine = sub.add_parser(
        "engine",
        help="weights, blending and fit times on the ICT rig, against baselines",
        description=(
            "On the ICT-FaceKit target (its expressions as examples, K = 24 landmarks) time "
            "single-frame and batched weights, blending against a bare weights @ deltas "
            "product, the fit, and weights against scipy's RBFInterpolator; median of "
            "--repeat runs. Falls back to the procedural demo when ICT is absent."
        ),
    )
    _add_ict(engine)
    engine.add_argument("--json", metavar="FILE", help="write every figure as JSON")
    engine.add_argument(
        "--repeat", type=int, default=7, metavar="N", help="timed runs per figure (median)"
    )
    engine.add_argument("--demo", action="store_true", help="use the procedural demo rig")
    engine.set_defaults(func=_runner("engine"))

    transport = sub.add_parser(
        "transport", help="frame round trips through a real server (latency, throughput)"
    )
    transport.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    transport.add_argument("--duration", type=float, default=10.0, metavar="S", help="seconds")
    transport.add_argument(
        "--clients",
        type=int,
        default=20,
        metavar="N",
        help="concurrent vertices-mode connections at 60 fps (default 20)",
    )
    transport.add_argument(
        "--max-streams",
        type=int,
        default=200,
        metavar="N",
        help="most 60 fps moving-vertices streams the ramp tries (default 200)",
    )
    transport.set_defaults(func=_runner("transport"))

    transfer = sub.add_parser(
        "transfer",
        help="deformation transfer's cost (ICT -> ~10k, ~50k vertices) and accuracy",
        description=(
            "Cost of `facecast expressions` for ICT-FaceKit's 51 ARKit shapes onto remeshed "
            "ICT faces of about 10k and 50k vertices (correspondence, the one factorisation, "
            "each solve beside a floor: one product with the factors), and its accuracy on "
            "targets with a known truth (other ICT identities, ICT's face decimated or "
            "re-triangulated) beside the naive baseline, with a real take cloned through "
            "generated and true examples (eq. 4.1). Needs ICT-FaceKit; takes minutes."
        ),
    )
    _add_ict(transfer)
    _add_take(transfer)
    transfer.add_argument("--json", metavar="FILE", help="write every figure as JSON")
    transfer.add_argument(
        "--sheet", metavar="PNG", help="write a picture: transferred beside true expressions"
    )
    transfer.add_argument(
        "--repeat", type=int, default=5, metavar="N", help="timed runs per solve figure (median)"
    )
    held = transfer.add_mutually_exclusive_group()
    held.add_argument(
        "--marker-weight", type=float, default=0.01, metavar="M",
        help="pull the markers with M x w_C after the first step (default 0.01)",
    )  # fmt: skip
    held.add_argument(
        "--hold-markers", action="store_true", help="hold the markers, as the paper does"
    )
    add_solve_arguments(transfer)
    part = transfer.add_mutually_exclusive_group()
    part.add_argument("--cost-only", action="store_true", help="skip the accuracy runs")
    part.add_argument("--accuracy-only", action="store_true", help="skip the cost runs")
    transfer.set_defaults(func=_runner("transfer"))

    broadcast = sub.add_parser(
        "broadcast", help="fan-out of results to viewers (optionally through Redis)"
    )
    broadcast.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    # 5 s a step: 2 s windows gave per-step ratios to the floor from 0.84x to 1.27x in one
    # run on a shared 2-core machine, 5 s ones 0.93x to 1.13x.
    broadcast.add_argument(
        "--duration",
        type=float,
        default=35.0,
        metavar="S",
        help="each step measures max(2, S / 7) seconds (default 35: 5 s a step)",
    )
    broadcast.add_argument("--redis", metavar="URL", help="Redis URL (default: in-process)")
    broadcast.add_argument(
        "--steps",
        type=_viewer_counts,
        metavar="N,N,...",
        help="viewer counts of the ramp, in order (default 250,500,750,1000,1250,1500,2000)",
    )
    broadcast.add_argument(
        "--no-redis", action="store_true", help="skip the two-process run on Redis"
    )
    broadcast.set_defaults(func=_runner("broadcast"))

    webcam = sub.add_parser(
        "webcam",
        help="the webcam path against ground truth: a rendered ICT face, tracked and cloned",
        description=(
            "Render an ICT-FaceKit identity performing a real take's ARKit weights, and its "
            "key-expressions clip by clip, as 640 x 480 camera video; track both with "
            "facecast track; fit the performer's own rig from the tracked keys onto another "
            "identity, clone the tracked take and report eq. 4.1 per axis and jitter against "
            "the truth, beside NNLS on the same points, the generic rig re-based on the "
            "tracked neutral, and the same pipeline on the exact landmarks, with the take's "
            "real eye closures (each eye's peak as a share of the truth, and r). Then another "
            "identity performs its keys and an eyes clip (quick 5-frame blinks, a wink each "
            "side, gaze holds up, down, left and right, jaw open + smile), scored per event "
            "on the personal and generic paths: live unfiltered, through the live Kalman "
            "filter (as /perform and facecast perform publish: auto smoothing), and offline."
        ),
    )
    _add_ict(webcam)
    _add_take(webcam)
    webcam.add_argument("--performer", default=None, metavar="PERSON",
                        help="the ICT identity rendered (default person07)")  # fmt: skip
    webcam.add_argument("--target", default=None, metavar="PERSON",
                        help="the ICT identity cloned onto (default person01)")  # fmt: skip
    webcam.add_argument("--frames", type=int, metavar="N", help="use the take's first N frames")
    webcam.add_argument("--ramp", type=int, default=None, metavar="N",
                        help="frames a key clip rises to its expression (default 4)")  # fmt: skip
    webcam.add_argument("--hold", type=int, default=None, metavar="N",
                        help="frames each key-expression is held and captured (default 10)")  # fmt: skip
    webcam.add_argument("--keys", metavar="NAME,...", type=lambda text: text.split(","),
                        help="the key-expressions performed and captured (default: all 51); "
                        "the others are skipped, as in the page's walk-through")  # fmt: skip
    webcam.add_argument("--sway", type=float, default=1.5, metavar="DEG",
                        help="head sway amplitude in degrees (default 1.5; 0: a still head)")  # fmt: skip
    webcam.add_argument("--gaze-degrees", type=float, default=None, metavar="DEG",
                        help="turn the rendered eyeballs by DEG at an eye-look weight of 1 "
                        "(default 35, ARKit's scale on a real face: facevideo's "
                        "ARKIT_GAZE_DEGREES; 0: ICT's shapes alone, which move the lids and "
                        "leave the iris where it is)")  # fmt: skip
    webcam.add_argument("--generic-neutral", choices=("shipped", "ict", "tracked"),
                        default="shipped",
                        help="the generic rows' source: facecast's shipped generic set on "
                        "tracked landmarks (default: ICT's landmark vertices with the lids and "
                        "iris centres as the tracker sees ICT's generic face; exact rows use "
                        "ICT's), ICT's landmark vertices, or ICT's generic face rendered at "
                        "rest and tracked, each shape keeping ICT's own displacements")  # fmt: skip
    webcam.add_argument("--as-uploaded", action="store_true",
                        help="pair the tracked generic rows' character on the shipped set as "
                        "an uploaded file's is (gaze left out: its look-at turns its eyes); by "
                        "default every ARKit shape is paired, gaze too (the exact rows keep "
                        "ICT's landmarks and every shape)")  # fmt: skip
    webcam.add_argument("--exact-only", action="store_true",
                        help="skip rendering and tracking: the exact-landmark rows only")  # fmt: skip
    webcam.add_argument("--videos", metavar="DIR",
                        help="keep the rendered videos and tracked points in DIR (reused when "
                        "there and made with the same settings)")  # fmt: skip
    webcam.add_argument("--eyes-performer", default=None, metavar="PERSON",
                        help="the ICT identity performing its keys and then the eyes clip "
                        "(quick blinks, winks, gaze holds, jaw + smile; default person12)")  # fmt: skip
    webcam.add_argument("--eyes-only", action="store_true",
                        help="only the eyes clip: skip the take and its performer's keys")  # fmt: skip
    webcam.add_argument("--no-eyes", action="store_true", help="skip the eyes clip")
    webcam.add_argument("--eyes-short", action="store_true",
                        help="the eyes clip with one blink and every hold 3 frames (102 frames, "
                        "not 221): checks the path, its scores are not to compare")  # fmt: skip
    webcam.add_argument("--landmarks", metavar="N,...",
                        type=lambda text: [int(n) for n in text.split(",")],
                        help="with --exact-only: the feature points, as positions in ICT's "
                        "68 landmarks (Multi-PIE order; default the page's 20)")  # fmt: skip
    webcam.add_argument("--kalman", metavar="A,...",
                        type=lambda text: [float(a) for a in text.split(",")],
                        help="the live Kalman rows (the eyes clip's, the take's personal and "
                        "generic paths): accelerations in landmark-noise units per s^2 "
                        "(default 480, the live default)")  # fmt: skip
    webcam.add_argument("--backend", default="wasm",
                        help="the page's tracker's TensorFlow.js backend (wasm, webgl, cpu), or "
                        "mediapipe: `facecast perform`'s tracks kept in --videos by "
                        "scripts/perform_tracks.py")  # fmt: skip
    webcam.add_argument("--blink-contrast", type=blink_contrast_arg, metavar="LOW,HIGH",
                        help="read the generic path's captured closed eyes through this blink "
                        "curve, as a calibrate's blink_contrast asks (/perform's ?blink=, "
                        "facecast perform --blink-contrast; default the server's for each rig, "
                        "0.4,0.8 with eye-look shapes and 0.4,0.7 without, which both get "
                        "unless the performer sets one)")  # fmt: skip
    webcam.add_argument("--by-name", action="store_true",
                        help="also print each path's RMS weight error per ARKit name")  # fmt: skip
    webcam.add_argument("--json", metavar="FILE", help="write every figure as JSON")
    webcam.set_defaults(func=_runner("webcam"))

    live = sub.add_parser(
        "live",
        help="glass to glass: /perform on a fake camera, a real server, N viewer pages",
        description=(
            "Render an ICT-FaceKit face as Chromium's fake camera, run /perform on it, a real "
            "facecast serve and N viewer pages in another browser (the audience's machine); "
            "report each "
            "stage's p50/p95/p99 (captured, tracked, sent, server in, server out, received, "
            "drawn: PROTOCOL.md §5.4) and capture → drawn, frames lost per stage and the "
            "fps, beside a floor from the same run: the face model's time a frame + a bare "
            "WebSocket hop page to page + a viewer's render() call; and the delay the stamps "
            "cannot hold, the live filter the channel ran, run offline on the bench's motion "
            "at the rate the page tracked (filter_lag)."
        ),
    )
    _add_ict(live)
    live.add_argument("--viewers", type=int, default=10, metavar="N",
                      help="viewer pages (default 10)")  # fmt: skip
    live.add_argument("--page", choices=("viewer", "overlay"), default="viewer",
                      help="which page the viewers open (default viewer)")  # fmt: skip
    live.add_argument("--window", type=_window_size, default=(640, 480), metavar="WxH",
                      help="each viewer's window, CSS pixels (default 640x480; an OBS source "
                      "is often 1920x1080: without a GPU every pixel drawn is CPU)")  # fmt: skip
    live.add_argument("--duration", type=float, default=20.0, metavar="S",
                      help="seconds measured (default 20)")  # fmt: skip
    live.add_argument("--load", type=int, nargs="?", const=2, default=0, metavar="N",
                      help="run N busy loops (default with the flag: 2) while measuring")  # fmt: skip
    live.add_argument("--video", metavar="Y4M",
                      help="the camera video to play (rendered there first when missing)")  # fmt: skip
    live.add_argument("--gpu-compositing", action="store_true",
                      help="composite the pages in Chromium's GPU process (SwiftShader) "
                           "instead of in software, where each WebGL draw is read back on "
                           "its page's main thread (docs/latency.md)")  # fmt: skip
    live.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    live.set_defaults(func=_runner("live"))


def _viewer_counts(text: str) -> list[int]:
    """``--steps``: positive viewer counts, comma-separated."""
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N,N,... viewer counts, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"viewer counts must be positive, got {text!r}")
    return counts


def _window_size(text: str) -> tuple[int, int]:
    """``--window``: WxH in CSS pixels, each 16..4096."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 1920x1080, got {text!r}") from None
    if not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise argparse.ArgumentTypeError(f"width and height must be 16..4096, got {text!r}")
    return width, height


def _runner(name: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        module_name = f"facecast.cli.bench.{name}"
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            raise CommandError(
                f"bench {name} is not available in this installation ({module_name} is missing)"
            ) from None
        return int(module.run(args))

    return run

"""Benchmark of the performer page in headless Chromium: model time per backend, tracking
rate, and what facecast adds per frame, read from the page's own stats.

Not a test (nothing is asserted): ``python -m tests.perform.bench_perform [--backends
wasm,webgl,cpu] [--frames N]``. Uses the fake camera of the tests (the warped astronaut,
320 x 240 at 25 fps) and a local server with the 20-point cartoon rig; docs/perform.md
quotes its output.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from facecast.cli.snapshot import CHROMIUM_ARGS, chromium_path, serving, write_demo_rig
from facecast.server.pages.viewer import viewer_dir
from facecast.server.settings import Settings

from .conftest import CHARACTER, _write_character_rig
from .facevideo import FacePose, write_y4m

_KEYS = (
    "backend", "firstModelMs", "modelMs", "trackFps", "publishFps", "latencyMs",
    "latencyP95Ms", "latencyMaxMs", "overlayMs", "addedMs", "addedP95Ms", "renderMs", "waitMs", "drawCostMs", "drawn",
)  # fmt: skip


# The page's per-frame pipeline (normalise the mesh, head angles, eye openness, encode the
# frame message) on one real-sized mesh, many times: its CPU cost without the scheduling
# noise of a shared machine. Prints microseconds per frame: median and 99th percentile.
_PIPELINE = """
import { readFileSync } from "node:fs";
import { checkLayout, eyeOpenness, headAngles, imageToMesh, normaliseMesh } from "./src/perform/facemesh.js";
import { encodeFrame } from "./src/protocol.js";
const layout = checkLayout(JSON.parse(readFileSync("../../rig/sources/layouts/mediapipe_face_mesh.json")));
const landmarks = Array.from({ length: layout.tracker_points }, (_, i) => [200 + (i % 23) * 3, 150 + (i % 19) * 4, (i % 7) - 3]);
for (const [part, x, y] of [["right", 215, 160], ["left", 265, 160], ["top", 240, 110], ["bottom", 240, 200]]) {
  for (const i of layout.frame[part]) landmarks[i] = [x, y, 0];
}
const out = new Float32Array(layout.features.length * 3);
const times = [];
for (let n = 0; n < 20000; n++) {
  const t0 = performance.now();
  const mesh = imageToMesh(landmarks);
  const { frame } = normaliseMesh(mesh, layout, out);
  headAngles(frame);
  eyeOpenness(mesh, layout);
  encodeFrame(n, n / 30, out);
  times.push(performance.now() - t0);
}
times.sort((a, b) => a - b);
process.stdout.write(JSON.stringify({ median: times[10000] * 1000, p99: times[19800] * 1000 }));
"""


def pipeline_cost() -> dict | None:
    """The per-frame pipeline in node: {"median": µs, "p99": µs}, or None without node."""
    node = shutil.which("node")
    if node is None:
        return None
    run = subprocess.run(
        [node, "--input-type=module", "-e", _PIPELINE],
        cwd=viewer_dir(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(run.stdout)


#: The bench's camera rate by default: a webcam's 30 fps, so that a model faster than the
#: camera's frame interval is what bounds tracking only where it really is slower
#: (``--camera-fps 60`` makes the model the bound on a machine where it runs at 30-40 fps).
CAMERA_FPS = 30
#: Frames tracked before the rate is measured (model load, first-frame compilation).
WARM_UP = 10


def run(
    backends: list[str],
    frames: int,
    rig: str = f"{CHARACTER}@bench",
    runs: int = 1,
    camera_fps: int = CAMERA_FPS,
) -> list[dict]:
    from playwright.sync_api import sync_playwright

    work = Path(tempfile.mkdtemp(prefix="bench-perform-"))
    poses = [FacePose()] * camera_fps + [FacePose(mouth=14.0)] * camera_fps
    camera = write_y4m(work / "camera.y4m", poses, fps=camera_fps)
    rigs = work / "rigs"
    write_demo_rig(rigs)
    _write_character_rig(rigs)
    if rig != CHARACTER:  # a performer's own rig: published at once, results drawn
        shutil.copy(rigs / f"{CHARACTER}.rig", rigs / f"{rig}.rig")
    settings = Settings(rigs_dir=rigs, access_log=False, log_level="warning")
    args = [
        *CHROMIUM_ARGS,
        "--use-fake-device-for-media-stream",
        "--use-fake-ui-for-media-stream",
        f"--use-file-for-fake-video-capture={camera}",
    ]
    clock = "[window.facecastStats.tracked, performance.now()]"
    rows = []
    with serving(settings) as base, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_path(), headless=True, args=args)
        try:
            for backend in backends:
                for _ in range(runs):
                    load_before = os.getloadavg()[0]
                    page = browser.new_page(viewport={"width": 1280, "height": 720})
                    started = time.monotonic()
                    page.goto(f"{base}/perform?channel=bench&rig={rig}&backend={backend}")
                    warm = min(WARM_UP, frames - 1)
                    page.wait_for_function(
                        f"window.facecastStats && window.facecastStats.tracked >= {warm}",
                        timeout=600_000,
                    )
                    first, t_first = page.evaluate(clock)
                    page.wait_for_function(
                        f"window.facecastStats.tracked >= {first + frames}", timeout=600_000
                    )
                    last, t_last = page.evaluate(clock)
                    stats = page.evaluate("window.facecastStats")
                    row = {key: stats.get(key) for key in _KEYS}
                    row["frames"] = stats["tracked"]
                    row["withFace"] = stats["withFace"]
                    row["seconds"] = time.monotonic() - started
                    # The rate over the measured frames, not the page's last-second count.
                    row["fps"] = 1000.0 * (last - first) / (t_last - t_first)
                    row["modelFps"] = 1000.0 / row["modelMs"]
                    row["load"] = (load_before, os.getloadavg()[0])
                    rows.append(row)
                    page.close()
        finally:
            browser.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.perform.bench_perform")
    parser.add_argument("--backends", default="wasm,webgl,cpu")
    parser.add_argument("--frames", type=int, default=120, help="frames measured a run")
    parser.add_argument("--runs", type=int, default=1, help="page loads per backend")
    parser.add_argument(
        "--rig",
        default=f"{CHARACTER}@bench",
        help="the rig the page opens: a performer's own (default; frames published and the "
        f"character drawn) or {CHARACTER} (generic: nothing published before a neutral "
        "capture, the character never redrawn)",
    )
    parser.add_argument(
        "--camera-fps", type=int, default=CAMERA_FPS, help="the fake camera's frame rate"
    )
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)
    rows = run(args.backends.split(","), args.frames, args.rig, args.runs, args.camera_fps)
    print(f"{os.cpu_count()} CPUs; camera {args.camera_fps} fps; rig {args.rig}")
    for row in rows:
        bound = min(args.camera_fps, row["modelFps"])
        print(
            f"{row['backend']:>5}: tracking {row['fps']:.1f} fps beside 1000 / model ms = "
            f"{row['modelFps']:.1f} ({row['fps'] / row['modelFps']:.2f}x; "
            f"{row['fps'] / bound:.2f}x of min(camera, model)); load average "
            f"{row['load'][0]:.1f} -> {row['load'][1]:.1f}"
        )
        print(
            f"       model {row['modelMs']:.1f} ms a frame (first "
            f"{row['firstModelMs']:.0f} ms), face in {row['withFace']}/{row['frames']} "
            f"frames; waiting for a camera frame {row['waitMs'] or 0:.1f} ms; landmarks -> "
            f"publish {row['latencyMs']:.2f} ms (p95 {row['latencyP95Ms']:.2f}, max "
            f"{row['latencyMaxMs']:.2f}); facecast per frame {row['addedMs']:.2f} ms (p95 "
            f"{row['addedP95Ms']:.2f}; points overlay {row['overlayMs']:.2f}); character "
            f"drawn {row['drawn'] or 0} times, each blocking the page {row['drawCostMs'] or 0:.0f} "
            f"ms"
        )
    by_backend: dict[str, list[float]] = {}
    for row in rows:
        by_backend.setdefault(row["backend"], []).append(row["fps"] / row["modelFps"])
    for backend, ratios in by_backend.items():
        if len(ratios) > 1:
            print(
                f"{backend:>5}: tracking / (1000 / model ms) over {len(ratios)} runs: min "
                f"{min(ratios):.2f}, median {statistics.median(ratios):.2f}, max "
                f"{max(ratios):.2f}"
            )
    cost = pipeline_cost()
    if cost is not None:
        print(
            f"pipeline alone (node, 20000 frames): {cost['median']:.1f} µs a frame "
            f"(p99 {cost['p99']:.1f} µs)"
        )
    if args.json:
        args.json.write_text(json.dumps({"pages": rows, "pipeline_us": cost}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

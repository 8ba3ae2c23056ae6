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
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from facecast.cli.snapshot import CHROMIUM_ARGS, chromium_path, serving, write_demo_rig
from facecast.server.settings import Settings
from facecast.server.viewer import viewer_dir

from .conftest import CHARACTER, FPS, _write_character_rig
from .facevideo import FacePose, write_y4m

_KEYS = (
    "backend", "firstModelMs", "modelMs", "trackFps", "publishFps", "latencyMs",
    "latencyP95Ms", "latencyMaxMs", "overlayMs", "addedMs", "addedP95Ms", "renderMs",
)  # fmt: skip


# The page's per-frame pipeline (normalise the mesh, head angles, eye openness, encode the
# frame message) on one real-sized mesh, many times: its CPU cost without the scheduling
# noise of a shared machine. Prints microseconds per frame: median and 99th percentile.
_PIPELINE = """
import { readFileSync } from "node:fs";
import { checkLayout, eyeOpenness, headAngles, imageToMesh, normaliseMesh } from "./src/perform/facemesh.js";
import { encodeFrame } from "./src/protocol.js";
const layout = checkLayout(JSON.parse(readFileSync("../../rig/sources/layouts/mediapipe_face_mesh.json")));
const landmarks = Array.from({ length: 468 }, (_, i) => [200 + (i % 23) * 3, 150 + (i % 19) * 4, (i % 7) - 3]);
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


def run(backends: list[str], frames: int) -> list[dict]:
    from playwright.sync_api import sync_playwright

    work = Path(tempfile.mkdtemp(prefix="bench-perform-"))
    camera = write_y4m(
        work / "camera.y4m", [FacePose()] * FPS + [FacePose(mouth=14.0)] * FPS, fps=FPS
    )
    rigs = work / "rigs"
    write_demo_rig(rigs)
    _write_character_rig(rigs)
    settings = Settings(rigs_dir=rigs, access_log=False, log_level="warning")
    args = [
        *CHROMIUM_ARGS,
        "--use-fake-device-for-media-stream",
        "--use-fake-ui-for-media-stream",
        f"--use-file-for-fake-video-capture={camera}",
    ]
    rows = []
    with serving(settings) as base, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_path(), headless=True, args=args)
        try:
            for backend in backends:
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                started = time.monotonic()
                page.goto(f"{base}/perform?channel=bench&rig={CHARACTER}&backend={backend}")
                page.wait_for_function(
                    f"window.facecastStats && window.facecastStats.tracked >= {frames}",
                    timeout=600_000,
                )
                stats = page.evaluate("window.facecastStats")
                row = {key: stats[key] for key in _KEYS}
                row["frames"] = stats["tracked"]
                row["withFace"] = stats["withFace"]
                row["seconds"] = time.monotonic() - started
                rows.append(row)
                page.close()
        finally:
            browser.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.perform.bench_perform")
    parser.add_argument("--backends", default="wasm,webgl,cpu")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)
    rows = run(args.backends.split(","), args.frames)
    for row in rows:
        print(
            f"{row['backend']:>5}: model {row['modelMs']:.1f} ms a frame (first "
            f"{row['firstModelMs']:.0f} ms), tracking {row['trackFps']} fps, face in "
            f"{row['withFace']}/{row['frames']} frames; landmarks -> publish "
            f"{row['latencyMs']:.2f} ms (p95 {row['latencyP95Ms']:.2f}, max "
            f"{row['latencyMaxMs']:.2f}); facecast per frame {row['addedMs']:.2f} ms (p95 "
            f"{row['addedP95Ms']:.2f}; points overlay {row['overlayMs']:.2f}); character "
            f"render {row['renderMs']:.1f} ms"
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

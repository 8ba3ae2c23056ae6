"""The perform venv (.venv-perform, made by scripts/setup --test) and how tests drive it.

mediapipe 0.10.21 needs numpy < 2, so ``facecast perform`` and MediaPipe run only as
subprocesses of that venv's interpreter; the test process stays in .venv and never imports
mediapipe or OpenCV. Under CI=true a missing or broken perform venv fails the tests that
need it; elsewhere they skip, saying how to make it.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._requires import skip_or_fail

REPO = Path(__file__).resolve().parent.parent
PERFORM_PYTHON = REPO / ".venv-perform" / "bin" / "python"
WORKER = Path(__file__).resolve().parent / "_facetrack_worker.py"

#: Seconds for one worker or ``facecast perform`` run (mediapipe's import and model load
#: take seconds on a loaded machine; a hang must still end the test).
RUN_TIMEOUT = 240.0

#: Imports the perform venv must manage, and where its facecast lives (it must be this
#: checkout's, installed editable, or the tests would test other code).
_PROBE = (
    "import cv2, mediapipe.python.solutions.face_mesh, ai_edge_litert.interpreter, "
    "facecast.cli.facetrack as f; "
    "print(f.__file__)"
)


def perform_venv_problem(python: Path = PERFORM_PYTHON) -> str | None:
    """Why ``python`` cannot run the perform tests, or None when it can."""
    remedy = "run scripts/setup --test, which creates it"
    if not (os.access(python, os.X_OK) and os.access(python.parent / "facecast", os.X_OK)):
        return f"no perform venv with facecast at {python.parent.parent} ({remedy})"
    try:
        probe = subprocess.run(
            [str(python), "-c", _PROBE], capture_output=True, text=True, timeout=RUN_TIMEOUT
        )
    except subprocess.TimeoutExpired:
        return f"{python} took over {RUN_TIMEOUT:.0f} s to import mediapipe"
    if probe.returncode != 0:
        last = probe.stderr.strip().splitlines()[-1:] or ["no message"]
        return f"{python} cannot import mediapipe, OpenCV and facecast: {last[0]} ({remedy})"
    where = Path(probe.stdout.strip()).resolve()
    if not where.is_relative_to(REPO):
        return f"{python} runs the facecast at {where}, not this checkout's ({remedy})"
    return None


def require_perform_venv(
    python: Path = PERFORM_PYTHON, environ: Mapping[str, str] = os.environ
) -> Path:
    """``python`` if it can run the perform tests; else fail the test when ``environ`` is
    CI's (CI=true: scripts/test made the venv, so its absence is a bug), skip it elsewhere."""
    problem = perform_venv_problem(python)
    if problem is not None:
        skip_or_fail(f"the perform venv: {problem}", environ)
    return python


@dataclass(frozen=True)
class Finished:
    """A finished subprocess: its exit code and what it wrote on stderr."""

    code: int
    err: str


def run_worker(python: Path, command: str, *paths: Path) -> None:
    """Run ``_facetrack_worker.py COMMAND PATHS...`` in the perform venv; raise if it fails."""
    done = subprocess.run(
        [str(python), str(WORKER), command, *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT,
        cwd=REPO,
    )
    if done.returncode != 0:
        raise AssertionError(f"worker {command} failed ({done.returncode}):\n{done.stderr}")


def track_images(python: Path, images: list[np.ndarray], work: Path) -> dict[str, np.ndarray]:
    """Each (H, W, 3) uint8 RGB image through the real FaceTracker: ``points`` (N, K, 3),
    ``meshes`` (N, 478, 3), NaN where no face was found, and ``faces`` (N,)."""
    work.mkdir(parents=True, exist_ok=True)
    np.savez(work / "images.npz", **{str(i): image for i, image in enumerate(images)})
    run_worker(python, "track-images", work / "images.npz", work / "tracked.npz")
    with np.load(work / "tracked.npz") as tracked:
        return {name: tracked[name] for name in tracked.files}


async def run_facecast(python: Path, *argv: str) -> Finished:
    """The perform venv's installed ``facecast ARGV...`` (beside ``python``) as a
    subprocess, without blocking the loop (the test's server and watchers run on it);
    killed if it outlives RUN_TIMEOUT."""
    # The console script: the entry point the perform venv installed, as a user runs it.
    process = await asyncio.create_subprocess_exec(
        str(python.parent / "facecast"),
        *argv,
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
        cwd=REPO,
    )
    try:
        _, err = await asyncio.wait_for(process.communicate(), RUN_TIMEOUT)
    except TimeoutError:
        process.kill()
        await process.wait()
        raise
    assert process.returncode is not None
    return Finished(process.returncode, err.decode(errors="replace"))

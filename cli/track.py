"""A video file -> the /perform page's feature points and head pose for every frame, offline.

Runs the page's own tracking pipeline (client/viewer/src/perform/pipeline.js: the same
model files, TensorFlow.js backend and face-frame normalisation, bundled as dist/track.js)
in headless Chromium, and hands it the video's frames one at a time, so every frame is
tracked exactly once, in order. It serves the page and the frames to the browser itself,
over HTTP on 127.0.0.1 under a random path for as long as it tracks (nothing is fetched
from elsewhere); it never publishes and never fits anything. ``track_video`` tracks one
video; a ``Tracker`` tracks several in turn in one browser.
"""

from __future__ import annotations

import importlib.util
import secrets
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from facecast.cli.errors import CommandError
from facecast.cli.snapshot import CHROMIUM_ARGS, chromium_path
from facecast.cli.y4m import Y4MVideo, open_y4m
from facecast.server.pages.perform import PERFORM_ASSETS
from facecast.server.pages.viewer import viewer_dir

__all__ = ["BACKENDS", "TRACK_COLOR_SPACE", "TrackResult", "Tracker", "track_video"]

#: The TensorFlow.js backends the page can run (docs/perform.md).
BACKENDS = ("wasm", "webgl", "cpu")
#: The colour space the frames are tagged with for Chromium's YUV -> RGB conversion: the
#: one its fake camera gives the same file's frames (BT.601, limited range), so the
#: pixels tracked here are the live page's, bit for bit (tests/perform/test_track.py).
TRACK_COLOR_SPACE = {
    "primaries": "smpte170m",
    "transfer": "smpte170m",
    "matrix": "smpte170m",
    "fullRange": False,
}
_HTML = "text/html; charset=utf-8"


@dataclass(frozen=True, eq=False)
class TrackResult:
    """Every frame of a video, tracked.

    Attributes
    ----------
    points : (F, K, 3) float32
        The layout's K feature points in its face frame, as /perform publishes them
        (about cm); NaN in frames without a face.
    head : (F, 4) float32
        The head pose the page sends with each frame (its ``head.rotation``, PROTOCOL.md
        §5.3): the unit quaternion (x, y, z, w) in Unity's frame; NaN in frames without a
        face.
    found : (F,) bool
        Whether a face was found in each frame.
    fps : float
        The video's frame rate.
    faces : (F,) int
        Faces found in each frame (the largest is tracked).
    layout : str
        The layout the points follow (``mediapipe_face_mesh``).
    backend : str
        The TensorFlow.js backend that ran.
    seconds : float
        Time spent tracking the frames (the browser's start and the model's load not
        counted).
    model_ms : float
        The model's mean time a frame, within ``seconds``.
    """

    points: np.ndarray
    head: np.ndarray
    found: np.ndarray
    fps: float
    faces: np.ndarray
    layout: str
    backend: str
    seconds: float = 0.0
    model_ms: float = float("nan")

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    def save(self, path: str | Path) -> Path:
        """Write ``points``, ``head``, ``found``, ``fps`` and ``layout`` as an .npz (what
        ``facecast clone`` reads)."""
        path = Path(path)
        with path.open("wb") as handle:
            np.savez(
                handle, points=self.points, head=self.head, found=self.found,
                fps=np.float64(self.fps), faces=self.faces, layout=np.str_(self.layout),
            )  # fmt: skip
        return path


def _assets() -> dict[str, tuple[Path, str]]:
    """URL path -> (file, media type): the page, its script, the model and the .wasm files."""
    root = viewer_dir()
    dist = root / "dist"
    files = {"/track": (root / "track.html", _HTML)}
    for name, (path, media_type) in PERFORM_ASSETS.items():
        if not name.startswith("perform.js"):
            files[f"/perform/assets/{name}"] = (dist / path, media_type)
    files["/perform/assets/track.js"] = (dist / "track.js", "text/javascript; charset=utf-8")
    missing = [str(path) for path, _ in files.values() if not path.is_file()]
    if missing:
        raise CommandError(
            f"the offline tracker is not built ({missing[0]} is missing): run scripts/setup, "
            "or npm ci && npm run build in client/viewer"
        )
    return files


@contextmanager
def _serving(
    read_frame: Callable[[int], bytes], files: dict[str, tuple[Path, str]]
) -> Iterator[str]:
    """Serve the tracker's files and the frames ``read_frame(index)`` gives (``frames/<index>``:
    a video's ``Y4MVideo.read``) to the browser on 127.0.0.1 while tracking; yields the
    page's URL.

    A loopback socket, not Playwright's request interception: a route hands each frame to
    the browser base64-encoded through Playwright's driver and the DevTools protocol, which
    cost ~25 ms of CPU a 640 x 480 frame and ~6 s for one 4096 x 4096 frame (measured
    2026-12-05: 120 frames tracked in 13.5 s by route, 10.9 s here, the same points). The
    path starts with a random token, so another local user cannot read the frames by
    guessing it; the socket is closed on return.
    """
    prefix = f"/{secrets.token_urlsafe(16)}/"

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: object) -> None:
            """Quiet: the browser's requests are this module's own."""

        def do_GET(self) -> None:
            path = self.path.split("?")[0]
            name = "/" + path[len(prefix) :] if path.startswith(prefix) else ""
            body, media_type = b"", "application/octet-stream"
            if name.startswith("/frames/"):
                try:
                    body = read_frame(int(name[len("/frames/") :]))
                except (ValueError, IndexError):
                    name = ""
            elif name in files:
                file, media_type = files[name]
                body = file.read_bytes()
            else:
                name = ""
            self.send_response(200 if name else 404)
            self.send_header("Content-Type", media_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="facecast-track-files")
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}{prefix}track"
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def track_video(
    path: str | Path,
    *,
    backend: str = "wasm",
    max_frames: int | None = None,
    progress: bool = True,
    chromium: str | None = None,
) -> TrackResult:
    """Track every frame of the Y4M video at ``path`` with the /perform page's pipeline.

    Parameters
    ----------
    backend : str
        TensorFlow.js backend, one of ``BACKENDS`` (the page's default ``wasm``).
    max_frames : int, optional
        Track only the first ``max_frames`` frames.
    progress : bool
        Show a progress bar (tqdm, on stderr).
    chromium : str, optional
        The Chromium executable (default ``/usr/bin/chromium``, or FACECAST_CHROMIUM).

    Raises
    ------
    facecast.cli.y4m.Y4MError
        The file is not a Y4M video this reads (the message says what is).
    CommandError
        No Chromium or Playwright, the tracker is not built, or the model failed to load.
    """
    _check_backend(backend)
    video = _open(path, max_frames)  # a bad file is said before a browser starts
    with Tracker(backend=backend, chromium=chromium) as tracker:
        return tracker.track_opened(video, progress=progress)


def _check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise CommandError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")


def _open(path: str | Path, max_frames: int | None) -> Y4MVideo:
    if max_frames is not None and max_frames < 1:
        raise CommandError(f"max_frames must be at least 1, got {max_frames}")
    return open_y4m(path, max_frames=max_frames)  # only the frames it will track


class Tracker:
    """Videos tracked one after another in one headless Chromium (``track_video``'s, kept).

    Each video is tracked on a pipeline of its own (the page's model loaded anew for it:
    from the page's cache, ~0.05 s of CPU), so its points are the ones ``track_video``
    gives it alone, bit for bit (tests/perform/test_track.py); what is saved is the
    browser's start, the page's load and the model's first load, ~3 CPU-s a video
    (measured 2026-12-05). A context manager; ``close`` ends the browser.

    Parameters
    ----------
    backend, chromium
        As for ``track_video``.

    Raises
    ------
    CommandError
        No Chromium or Playwright, the tracker is not built, or the model failed to load.
    """

    def __init__(self, *, backend: str = "wasm", chromium: str | None = None) -> None:
        _check_backend(backend)
        files = _assets()
        executable = chromium or chromium_path()
        if executable is None:
            raise CommandError(
                "facecast track runs the face model in Chromium: no Chromium at "
                "/usr/bin/chromium (install Debian's chromium, or set FACECAST_CHROMIUM)"
            )
        if importlib.util.find_spec("playwright") is None:
            raise CommandError(
                "facecast track drives Chromium through Playwright: run ./scripts/setup "
                "--track (or pip install 'facecast[track]')"
            )
        self.backend = backend
        self._video: Y4MVideo | None = None
        self._videos = 0
        self._page: Any = None
        self._stack = ExitStack()
        # Playwright's sync API refuses a thread with a running event loop (Jupyter, an
        # async app, another sync Playwright session): the browser gets a thread of its
        # own, and every call to it is made there.
        self._pool: ThreadPoolExecutor | None = ThreadPoolExecutor(
            1, thread_name_prefix="facecast-track"
        )
        try:
            self._pool.submit(self._start, files, executable).result()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def track(
        self, path: str | Path, *, max_frames: int | None = None, progress: bool = True
    ) -> TrackResult:
        """Track every frame (or the first ``max_frames``) of the Y4M video at ``path``, as
        ``track_video`` does.

        Raises
        ------
        facecast.cli.y4m.Y4MError
            The file is not a Y4M video this reads.
        CommandError
            The model failed to load, or the page failed on a frame.
        """
        return self.track_opened(_open(path, max_frames), progress=progress)

    def track_opened(self, video: Y4MVideo, *, progress: bool = True) -> TrackResult:
        """``track`` on a video already opened (``open_y4m``)."""
        if self._pool is None:
            raise CommandError("this Tracker is closed")
        return self._pool.submit(self._track, video, progress).result()

    def close(self) -> None:
        """End the browser and the frames' server (on the thread that started them)."""
        if self._pool is not None:
            pool, self._pool = self._pool, None
            try:
                pool.submit(self._stack.close).result()
            finally:
                pool.shutdown()

    def _read_frame(self, index: int) -> bytes:
        if self._video is None:
            raise IndexError(index)
        return self._video.read(index)

    def _start(self, files: dict[str, tuple[Path, str]], executable: str) -> None:
        from playwright.sync_api import sync_playwright

        url = self._stack.enter_context(_serving(self._read_frame, files))
        pw = self._stack.enter_context(sync_playwright())
        browser = pw.chromium.launch(
            executable_path=executable, headless=True, args=[*CHROMIUM_ARGS]
        )
        self._stack.callback(browser.close)
        page = browser.new_page()
        page.goto(url)
        page.wait_for_function("window.facecastTrack !== undefined", timeout=60_000)
        self._page = page

    def _track(self, video: Y4MVideo, progress: bool) -> TrackResult:
        from playwright.sync_api import Error as PlaywrightError

        page = self._page
        self._video = video
        self._videos += 1
        # Each video's frames under a URL of its own: nothing the browser kept of the last
        # video's is taken for this one's (the server reads the path before the "?").
        query = f"?video={self._videos}"
        frames = video.num_frames
        faces = np.zeros(frames, dtype=np.int64)
        model_ms = np.zeros(frames)
        shape = {
            "format": video.format, "width": video.width, "height": video.height,
            "colorSpace": TRACK_COLOR_SPACE,
        }  # fmt: skip
        try:
            # A new pipeline: none of the last video's state (the eyelids' history) is kept.
            loaded = page.evaluate("(b) => window.facecastTrack.load(b)", self.backend)
        except PlaywrightError as exc:
            raise CommandError(f"the face model did not load: {exc}") from None
        k = int(page.evaluate("window.facecastTrack.k"))
        layout = str(page.evaluate("window.facecastTrack.layout"))
        points = np.full((frames, k, 3), np.nan, dtype=np.float32)
        head = np.full((frames, 4), np.nan, dtype=np.float32)
        bar = tqdm(total=frames, unit="frame", desc="tracking", disable=not progress, leave=False)
        started = time.perf_counter()
        with bar:
            for index in range(frames):
                following = f"frames/{index + 1}{query}" if index + 1 < frames else None
                try:
                    tracked = page.evaluate(
                        "([url, shape, next]) => window.facecastTrack.track(url, shape, next)",
                        [f"frames/{index}{query}", shape, following],
                    )
                except PlaywrightError as exc:
                    # The page's process died (out of memory, a crash): said, not a
                    # traceback (before: a TargetClosedError after minutes at 8192^2).
                    raise CommandError(
                        f"Chromium's page failed on frame {index} ({video.width} x "
                        f"{video.height}): {str(exc).splitlines()[0][:200]}"
                    ) from None
                faces[index] = tracked["faces"]
                model_ms[index] = tracked["modelMs"]
                if tracked["points"] is not None:
                    points[index] = np.asarray(tracked["points"], dtype=np.float32).reshape(k, 3)
                    head[index] = tracked["head"]
                bar.update(1)
        seconds = time.perf_counter() - started
        found = np.asarray(np.isfinite(points).all(axis=(1, 2)))
        return TrackResult(
            points, head, found, video.fps, faces, layout, loaded["backend"], seconds,
            float(model_ms.mean()),
        )  # fmt: skip

"""Fixtures of the performer-studio tests: a real Chromium with a fake camera, a real server.

One browser for the whole package (the fake camera is a browser flag), with one profile:
each test writes the video it needs to the camera file, and a page opened afterwards plays
it from the start (Chromium opens the file anew for each getUserMedia). The pages share
the profile's HTTP cache, as a performer's own browser does from the second visit on: the
studio's scripts and WebAssembly come with their compiled code, which saves a /perform
page ~1.1 of its ~3 CPU-s to its first tracked frame (each test still gets fresh pages;
the pages keep nothing else: no storage, no cookies). Skips, with the reason, when
Chromium, the studio's build or scikit-image is missing (fails under CI=true:
tests/_requires.py).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from facecast.cli.snapshot import CHROMIUM_ARGS, chromium_path, serving, write_demo_rig
from facecast.cli.track import Tracker
from facecast.protocol import SUBPROTOCOL, decode_server
from facecast.rig import fit
from facecast.rig.characters.generic import generic_sources
from facecast.rig.demo import demo_example_set
from facecast.rig.examples import ExampleSet
from facecast.rig.sources.ict import locate_ict
from facecast.rig.sources.layouts import load_layout
from facecast.server.pages.perform import PERFORM_ASSETS
from facecast.server.pages.viewer import viewer_dir
from facecast.server.settings import Settings

playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
pytest.importorskip("skimage", reason="scikit-image (the test extras) is not installed")

from .facevideo import FacePose, write_y4m  # noqa: E402

FPS = 25
#: ICT-FaceKit's archive, or None; the marks of a test module that renders its head and
#: tracks it with ``facecast track`` (skipped, with the reason, when something is missing).
ICT_ARCHIVE = locate_ict()
ICT_TRACKING = [
    pytest.mark.ict,
    pytest.mark.skipif(
        ICT_ARCHIVE is None, reason="ICT-FaceKit not found (../shared/data/ict-facekit)"
    ),
    pytest.mark.skipif(chromium_path() is None, reason="no Chromium at /usr/bin/chromium"),
    pytest.mark.skipif(
        not (viewer_dir() / "dist" / "track.js").is_file(),
        reason="the offline tracker is not built (npm run build in client/viewer)",
    ),
]


def _missing() -> str | None:
    if chromium_path() is None:
        return "no Chromium at /usr/bin/chromium (scripts/setup --test installs it)"
    if not all((viewer_dir() / "dist" / path).is_file() for path, _ in PERFORM_ASSETS.values()):
        return "the performer studio is not built (npm ci && npm run build in client/viewer)"
    return None


@pytest.fixture(scope="package")
def camera_file(tmp_path_factory) -> Path:
    """The y4m file the browser's fake camera plays; tests rewrite it (``Camera.show``)."""
    path = tmp_path_factory.mktemp("camera") / "camera.y4m"
    write_y4m(path, [FacePose()] * 2, fps=FPS)
    return path


@dataclass
class Camera:
    path: Path

    def show(self, poses: list[FacePose], second_face: float | None = None) -> None:
        """What the next page to open the camera sees, looped; ``second_face``: also a
        second person, that much smaller, beside the first."""
        write_y4m(self.path, poses, fps=FPS, second_face=second_face)


@pytest.fixture
def camera(camera_file) -> Camera:
    return Camera(camera_file)


@pytest.fixture(scope="package")
def browser(camera_file, tmp_path_factory):
    """The package's Chromium as one persistent context (its profile in a temporary
    folder): ``open_page`` opens each page in it."""
    reason = _missing()
    if reason is not None:
        pytest.skip(reason)
    args = [
        *CHROMIUM_ARGS,
        "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-video-capture={camera_file}",
    ]
    with playwright_api.sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            tmp_path_factory.mktemp("profile"),
            executable_path=chromium_path(),
            headless=True,
            args=args,
            permissions=["camera"],
        )
        try:
            yield context
        finally:
            context.close()


@pytest.fixture(scope="package")
def tracker() -> Iterator[Tracker]:
    """``facecast track``'s browser, kept for every module that tracks a rendered video:
    each video gets the points ``track_video`` gives it alone (a pipeline of its own,
    tests/perform/test_track.py), without a browser started and a model loaded for each
    (~3 CPU-s a module). The modules that ask for it carry ``ICT_TRACKING``'s skips."""
    with Tracker() as kept:
        yield kept


#: The demo character in a rig that takes the layout's first 20 points (the demo rig takes
#: 21, the layout gives 26): a character the page can publish for and calibrate on without
#: ICT-FaceKit's data, fitted as a rig of the layout's earlier 20-point version was, so the
#: page tests drive that path (the page sends such a rig the first 20 of its points).
CHARACTER = "cartoon"


def _write_character_rig(rigs: Path) -> None:
    demo = demo_example_set()
    k = load_layout().earlier_counts[0]
    examples = ExampleSet(
        demo.names, demo.source_points[:, :k], demo.target_vertices, demo.target_faces
    )
    fit(examples).save(rigs / f"{CHARACTER}.rig")


#: A rig on the layout's full 26 points, for tests of what the page publishes (a points
#: watcher reads the frames as sent): the generic ARKit set's 26 points (ICT's landmarks,
#: its lids and irises as the tracker sees them), its target the same points as a mesh (no
#: ICT-FaceKit data needed).
LAYOUT_RIG = "points26"


def _write_layout_rig(rigs: Path) -> None:
    generic = generic_sources()
    layout = load_layout()
    points = generic.points
    k = points.shape[1]
    assert k == layout.num_features and layout.feature_names[-2:] == ("right_iris", "left_iris")
    faces = [[i, i + 1, i + 2] for i in range(k - 2)]
    examples = ExampleSet(generic.names, points, points, faces)
    fit(examples, noise=0.035, clamp="unit").save(rigs / f"{LAYOUT_RIG}.rig")


@pytest.fixture(scope="package")
def rigs_dir(tmp_path_factory) -> Path:
    """The demo rig (``demo``, K = 21), the demo character for this layout's earlier 20
    points (``cartoon``) and a rig on its 26 (``points26``)."""
    rigs = tmp_path_factory.mktemp("perform-rigs")
    write_demo_rig(rigs)
    _write_character_rig(rigs)
    _write_layout_rig(rigs)
    return rigs


@pytest.fixture(scope="package")
def server(rigs_dir) -> Iterator[str]:
    """A real uvicorn with the demo rig, no auth (rigs fitted by a test stay for the next)."""
    settings = Settings(rigs_dir=rigs_dir, access_log=False, log_level="warning")
    with serving(settings) as base_url:
        yield base_url


def open_page(
    browser,
    url: str,
    *,
    camera: bool = True,
    size: tuple[int, int] = (960, 540),
    sent: list | None = None,
):
    """A new page of the package's browser recording its errors in ``errors``; ``camera``
    False: the camera denied (the profile's permission withdrawn until the next page that
    allows it: no other page may be capturing then); ``size``, its window's CSS pixels
    (what a page draws costs SwiftShader by the pixel); ``sent``, a list the page's
    WebSocket messages are appended to as it sends them (bytes, the wire's)."""
    if camera:
        browser.grant_permissions(["camera"])
    else:
        browser.clear_permissions()
    page = browser.new_page()
    page.set_viewport_size({"width": size[0], "height": size[1]})
    page.errors = []
    page.on("pageerror", lambda exc: page.errors.append(f"pageerror: {exc}"))
    page.set_default_timeout(30_000)
    if sent is not None:
        page.on("websocket", lambda ws: ws.on("framesent", lambda payload: sent.append(payload)))
    page.goto(url)
    return page


def done(page) -> None:
    """Close a page a test has read all it needs from, before it opens the next: an open
    /perform page goes on tracking, a core's worth of the machine (``pages`` closes every
    page at the end of the test anyway; closing twice is harmless)."""
    page.close()


@pytest.fixture
def pages(browser) -> Iterator[list]:
    """Pages a test opens through ``open_page``; they close after the test."""
    opened: list = []
    yield opened
    for page in opened:
        page.close()


@dataclass
class ChannelRecorder:
    """A real channel watcher in a thread: every result and event it receives, timed."""

    url: str
    results: list = field(default_factory=list)  # (monotonic time, Result)
    events: list = field(default_factory=list)  # (monotonic time, message type)
    ready: threading.Event = field(default_factory=threading.Event)
    stop: threading.Event = field(default_factory=threading.Event)
    arrived: threading.Condition = field(default_factory=threading.Condition)

    def wait_for(self, kind: str, timeout: float) -> bool:
        """Wait until an event of ``kind`` (``face_lost``...) has arrived; False on timeout."""
        with self.arrived:
            return self.arrived.wait_for(
                lambda: kind in [k for _, k in self.events], timeout=timeout
            )

    def run(self) -> None:
        from websockets.sync.client import connect

        with connect(self.url, subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:
            while not self.stop.is_set():
                try:
                    message = decode_server(ws.recv(timeout=0.2))
                except TimeoutError:
                    continue
                now = time.monotonic()
                kind = getattr(message, "TYPE", type(message).__name__)
                if kind == "ready":
                    self.ready.set()
                with self.arrived:
                    if kind == "result":
                        self.results.append((now, message))
                    else:
                        self.events.append((now, kind))
                    self.arrived.notify_all()


def watching(base_url: str, channel: str, rig: str, output: str = "weights"):
    """Start a ChannelRecorder on ``channel`` (cloned on ``rig``); returns (recorder, thread)."""
    ws_base = base_url.replace("http", "ws")
    recorder = ChannelRecorder(f"{ws_base}/v1/channels/{channel}/watch?rig={rig}&output={output}")
    thread = threading.Thread(target=recorder.run, daemon=True)
    thread.start()
    assert recorder.ready.wait(10), "the watcher got no ready"
    return recorder, thread

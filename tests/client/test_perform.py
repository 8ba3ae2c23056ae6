"""``facecast perform`` on a real video (scikit-image's astronaut photo, moved and warped),
tracked by the real MediaPipe FaceMesh, published to a real server's channel.

MediaPipe and OpenCV run only in the perform venv (``tests._perform_venv``): the video is
made, tracked and performed by its interpreter as subprocesses; this process holds the
server, the watchers and the assertions.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib.util
import json
import re
import warnings

import numpy as np
import pytest
from skimage import data as skimage_data
from skimage.transform import rescale

from facecast.cli.main import main
from facecast.client.channel import channel_url, watch_channel
from facecast.protocol import FaceLost, Ready, Result
from facecast.rig import ExampleSet, fit
from facecast.rig.sources.ict import locate_ict
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from .._perform_venv import run_facecast, run_worker, track_images

pytestmark = pytest.mark.slow


#: Head motions (degrees, scale, dx, dy in pixels) with a neutral face.
MOTIONS = [(0, 1.0, 0, 0), (4, 1.03, 6, -4), (-5, 0.94, -6, 3), (6, 1.06, 4, 5),
           (-3, 0.97, -3, -5), (2, 1.0, 8, 0), (0, 1.0, 0, 0), (-6, 1.04, 0, 6)]  # fmt: skip
#: The jaw drops over a few frames, as a face does, and holds.
JAW_PIXELS = (5, 10, 15, 20, 20, 20, 20, 20)
JAW_FRAMES = len(JAW_PIXELS)
BLANK_FRAMES = 3
CHIN = 19  # feature "chin" in the mediapipe_face_mesh layout


@pytest.fixture(scope="module")
def face_video(tmp_path_factory, perform_python):
    """An MJPG video: the astronaut's head moving, then her jaw dropping, then no face."""
    work = tmp_path_factory.mktemp("video")
    spec = {"motions": MOTIONS, "jaw_pixels": JAW_PIXELS, "blank_frames": BLANK_FRAMES}
    (work / "spec.json").write_text(json.dumps({**spec, "fps": 15.0}))
    np.save(work / "astronaut.npy", skimage_data.astronaut())
    path = work / "astronaut.avi"
    run_worker(perform_python, "video", work / "spec.json", work / "astronaut.npy", path)
    return path


@pytest.fixture(scope="module")
def tracked(face_video, perform_python, tmp_path_factory):
    """Every frame of the video through the real FaceTracker (in the perform venv)."""
    out = tmp_path_factory.mktemp("tracked") / "tracked.npz"
    run_worker(perform_python, "track-video", face_video, out)
    with np.load(out) as data:
        return {name: data[name] for name in data.files}


def _found(points: np.ndarray) -> np.ndarray:
    """The frames (of (N, K, 3) points, NaN where no face) in which a face was found."""
    return points[np.isfinite(points).all(axis=(1, 2))]


def test_the_face_is_found_in_the_face_frames_and_not_in_the_blank_ones(tracked):
    faces = len(MOTIONS) + JAW_FRAMES
    points = tracked["points"]
    assert len(points) == len(MOTIONS) + JAW_FRAMES + BLANK_FRAMES
    assert len(_found(points[:faces])) >= 0.9 * faces
    assert np.isnan(points[faces:]).all() and (tracked["faces"][faces:] == 0).all()


def test_points_stay_put_when_the_head_moves_and_the_chin_drops_with_the_jaw(tracked):
    still = _found(tracked["points"][: len(MOTIONS)])
    jaw = _found(tracked["points"][len(MOTIONS) : -BLANK_FRAMES])
    neutral = np.median(still, axis=0)
    head_motion = np.linalg.norm(still - neutral, axis=2).max()
    chin_drop = neutral[CHIN, 1] - np.median(jaw[:, CHIN, 1])
    assert head_motion < 0.35  # cm: rotations, zoom and shifts are removed
    assert chin_drop > 2 * head_motion


def _character() -> ExampleSet:
    rng = np.random.default_rng(0)
    names = ("neutral", "smile", "jawOpen")
    source = np.repeat(rng.normal(scale=3.0, size=(1, 20, 3)), 3, axis=0)
    source[1:] += rng.normal(scale=0.5, size=(2, 20, 3))
    target = np.repeat(rng.normal(size=(1, 10, 3)), 3, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(2, 10, 3))
    return ExampleSet(names, source, target, np.array([[i, i + 1, i + 2] for i in range(8)]))


class _Recorder:
    """A channel watcher that keeps every message, in order, until cancelled."""

    def __init__(self) -> None:
        self.messages: list = []
        self.ready = asyncio.Event()
        self._arrived = asyncio.Event()

    async def watch(self, url: str) -> None:
        async for message in watch_channel(url):
            self.messages.append(message)
            self._arrived.set()
            if isinstance(message, Ready):
                self.ready.set()

    async def result_of(self, seq: int, timeout: float) -> None:
        """Wait for the result of frame ``seq`` (the channel's last results may follow
        its ``channel_idle``: the performer need not wait for them before it leaves)."""
        async with asyncio.timeout(timeout):
            while not any(isinstance(m, Result) and m.seq >= seq for m in self.messages):
                self._arrived.clear()
                await self._arrived.wait()


def _perform_stats(err: str) -> dict[str, int]:
    match = re.search(r"(\d+) frames read, face found in (\d+), (\d+) published", err)
    assert match, err
    return dict(zip(("read", "found", "published"), map(int, match.groups()), strict=True))


#: The channel's ``face_lost_after`` for these performances. On a loaded machine the
#: tracker can stall past the default 0.5 s between two face frames (CI: a gap after the
#: 4th published frame, the channel eased to neutral before the jaw dropped); these tests
#: are about what is performed, so only the blank frames at the end may be a lost face.
FACE_LOST_AFTER = 30.0


def _performed(messages: list) -> list[Result]:
    """The results a watcher got of published frames: those before any ``face_lost``
    (results after one are the channel easing to the neutral pose)."""
    lost = next((i for i, m in enumerate(messages) if isinstance(m, FaceLost)), len(messages))
    return [m for m in messages[:lost] if isinstance(m, Result)]


async def _perform_to_channel(python, settings, rig, argv_extra, video):
    """Run ``facecast perform`` (perform venv) on ``video`` to channel "stage" of a real
    server while a watcher of the channel on rig "hero" records what it is sent, up to
    the result of the last frame published."""
    async with run_server(dataclasses.replace(settings, face_lost_after=FACE_LOST_AFTER)) as server:
        server.app.state.store.put_rig("hero", rig)
        url = channel_url(server.base_url, "stage", "watch", {"rig": "hero"})
        recorder = _Recorder()
        watcher = asyncio.create_task(recorder.watch(url))
        try:
            await asyncio.wait_for(recorder.ready.wait(), 20)
            finished = await run_facecast(
                python, "perform", server.base_url, "--channel", "stage", "--rig", "hero",
                "--video", str(video), *argv_extra,
            )  # fmt: skip
            assert finished.code == 0, finished.err
            # seq counts the frames published from 0; the burst (19 frames) is far
            # within the server's rate_burst, so the last one has a result.
            await recorder.result_of(_perform_stats(finished.err)["published"] - 1, 30)
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
        messages = recorder.messages
    return finished, messages


@pytest.mark.anyio
async def test_perform_publishes_the_tracked_points_and_viewers_see_them(
    tmp_path, perform_python, face_video
):
    rig = fit(_character())
    finished, messages = await _perform_to_channel(
        perform_python, Settings(rigs_dir=tmp_path / "rigs"), rig, ["--no-calibrate"], face_video
    )
    stats = _perform_stats(finished.err)
    results = [m for m in messages if isinstance(m, Result)]
    assert stats["read"] == len(MOTIONS) + JAW_FRAMES + BLANK_FRAMES
    assert stats["found"] >= 0.9 * (len(MOTIONS) + JAW_FRAMES)
    assert stats["published"] == stats["found"]
    assert 1 <= len(results) <= stats["published"]
    assert all(np.isfinite(r.weights).all() for r in results)
    # Its hello asks for the server's auto filter: on a rig fitted exactly and no
    # calibrate, no noise is known, so the one-euro filter (PROTOCOL.md §5.1.1).
    assert "viewers got the points one-euro-filtered" in finished.err


@pytest.mark.ict
@pytest.mark.anyio
@pytest.mark.skipif(locate_ict() is None, reason="needs ../shared/data/ict-facekit")
async def test_generic_ict_rig_calibrated_on_the_neutral_opens_the_jaw(
    tmp_path, perform_python, face_video
):
    from facecast.cli.commands.import_ import arkit_example_set
    from facecast.rig.sources.ict import DEFAULT_LANDMARKS

    example_set, _ = arkit_example_set(locate_ict(), DEFAULT_LANDMARKS, "face")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # it amplifies noise: the re-base must not pass it on
        rig = fit(example_set)  # exact, as 'facecast import ict-facekit' and 'rigs put' give
    finished, messages = await _perform_to_channel(
        perform_python,
        Settings(rigs_dir=tmp_path / "rigs"),
        rig,
        ["--neutral-frames", "4"],
        face_video,
    )
    stats = _perform_stats(finished.err)
    weights = np.stack([m.weights for m in _performed(messages)])
    jaw = weights[:, rig.names.index("jawOpen")]
    assert stats["published"] == stats["found"] - 3  # 4 neutral frames, 1 frame
    # The calibrate's noise turned the auto filter into the Kalman (PROTOCOL.md §5.2.5).
    assert "viewers got the points kalman-filtered" in finished.err
    # Re-based noise-aware and bounded on the neutral (its calibrate carries the noise):
    # every weight a viewer gets is plausible.
    assert weights[:, 1:].min() >= -0.25 and weights[:, 1:].max() <= 1.25
    # Watchers may skip frames; the published sequence is head motion, then the jaw drop.
    assert jaw[-1] > jaw[0] + 0.1
    assert rig.names[1 + int(np.argmax(weights[-1, 1:]))] == "jawOpen"  # the mouth open


@pytest.mark.anyio
async def test_an_absent_camera_is_a_clear_error(perform_python):
    finished = await run_facecast(
        perform_python, "perform", "http://127.0.0.1:9", "--channel", "x", "--rig", "hero",
        "--camera", "9", "-q",
    )  # fmt: skip
    assert finished.code == 2 and "cannot open camera 9" in finished.err


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (["--wink-frames", "2"], "--wink-frames must be at least 3"),
        (["--winks", "--no-calibrate"], "--winks are captured after the neutral"),
        (["--winks", "--rig", "hero@ann"], "--winks are captured after the neutral"),
        (["--blink-contrast", "0.5,0.9"], "--blink-contrast shapes the winks' closed eyes"),
    ],
)
def test_winks_without_a_neutral_or_frames_enough_are_refused(extra, said, capsys):
    code = main(["perform", "http://127.0.0.1:9", "--channel", "x", "--rig", "hero", *extra])
    assert code == 2 and said in capsys.readouterr().err


@pytest.mark.parametrize(
    ("value", "said"),
    [("0.9,0.5", "expected 0 <= LOW < HIGH <= 1"), ("0.5", "expected LOW,HIGH"),
     ("nan,0.9", "expected 0 <= LOW < HIGH <= 1"), ("0.5,1.2", "expected 0 <= LOW < HIGH <= 1")],
)  # fmt: skip
def test_an_unusable_blink_contrast_stops_before_the_camera(value, said, capsys):
    argv = ["perform", "http://127.0.0.1:9", "--channel", "x", "--rig", "hero", "--winks",
            "--blink-contrast", value]  # fmt: skip
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2 and said in capsys.readouterr().err


@pytest.mark.skipif(
    importlib.util.find_spec("mediapipe") is not None,
    reason="this .venv has the perform extra (scripts/setup --perform)",
)
def test_without_the_extra_perform_says_what_to_install(capsys):
    code = main(["perform", "http://127.0.0.1:9", "--channel", "x", "--rig", "hero", "-q"])
    assert code == 2 and "pip install 'facecast[perform]'" in capsys.readouterr().err


@pytest.mark.anyio
async def test_a_rig_with_another_point_count_is_refused_by_name(
    tmp_path, perform_python, face_video
):
    rng = np.random.default_rng(1)
    source = rng.normal(size=(2, 5, 3))
    target = rng.normal(size=(2, 4, 3))
    small = fit(ExampleSet(("neutral", "smile"), source, target, np.array([[0, 1, 2]])))
    async with run_server(Settings(rigs_dir=tmp_path / "rigs")) as server:
        server.app.state.store.put_rig("small", small)
        finished = await run_facecast(
            perform_python, "perform", server.base_url, "--channel", "stage", "--rig", "small",
            "--video", str(face_video), "-q",
        )  # fmt: skip

    assert finished.code == 2 and "has 5 feature points" in finished.err


def test_with_two_faces_in_view_the_largest_is_tracked(tmp_path, perform_python):
    photo = skimage_data.astronaut()
    head = photo[30:260, 110:330]
    small = rescale(head, 0.85, channel_axis=-1, preserve_range=True).round().astype(np.uint8)
    canvas = np.full((300, 500, 3), 90, np.uint8)
    canvas[40:270, 10:230] = head
    canvas[40 : 40 + small.shape[0], 260 : 260 + small.shape[1]] = small
    tracked = track_images(perform_python, [canvas, canvas[:, :250].copy()], tmp_path)

    both, alone = tracked["meshes"]
    assert tracked["faces"].tolist() == [2, 1]
    # The left, larger face: the same mesh as when it is alone in view (to a pixel or two).
    assert np.abs(both[:, :2] - alone[:, :2]).mean() < 1.0

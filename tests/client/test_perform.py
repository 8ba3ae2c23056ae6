"""``facecast perform`` on a real video (scikit-image's astronaut photo, moved and warped),
tracked by the real MediaPipe FaceMesh, published to a real server's channel."""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("mediapipe")
skimage_data = pytest.importorskip("skimage.data")

from facecast.client.bridges.channel import channel_url, watch_channel  # noqa: E402
from facecast.client.cli import main  # noqa: E402
from facecast.client.facetrack import FaceTracker, VideoSource  # noqa: E402
from facecast.protocol import ChannelIdle, Ready, Result  # noqa: E402
from facecast.rig import ExampleSet, fit  # noqa: E402
from facecast.rig.ict import locate_ict  # noqa: E402
from facecast.server.settings import Settings  # noqa: E402
from facecast.server.testing import run_server  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


#: Head motions (degrees, scale, dx, dy in pixels) with a neutral face.
MOTIONS = [(0, 1.0, 0, 0), (4, 1.03, 6, -4), (-5, 0.94, -6, 3), (6, 1.06, 4, 5),
           (-3, 0.97, -3, -5), (2, 1.0, 8, 0), (0, 1.0, 0, 0), (-6, 1.04, 0, 6)]  # fmt: skip
#: The jaw drops over a few frames, as a face does, and holds.
JAW_PIXELS = (5, 10, 15, 20, 20, 20, 20, 20)
JAW_FRAMES = len(JAW_PIXELS)
BLANK_FRAMES = 3
CHIN = 19  # feature "chin" in the mediapipe_face_mesh layout


def _similarity(image, angle, scale, dx, dy):
    h, w = image.shape[:2]
    matrix = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    matrix[:, 2] += (dx, dy)
    return cv2.warpAffine(image, matrix, (w, h), borderMode=cv2.BORDER_REFLECT)


def _jaw_open(image, mesh_pixels, amount):
    """Pull the lower face down below the lips, most at the chin: the jaw drops."""
    h, w = image.shape[:2]
    lip, chin = mesh_pixels[14, 1], mesh_pixels[152, 1]
    centre = mesh_pixels[[61, 291], 0].mean()
    half = abs(mesh_pixels[291, 0] - mesh_pixels[61, 0])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = np.clip((yy - lip) / (chin - lip), 0, 1)
    ramp = ramp * ramp * (3 - 2 * ramp)
    dy = amount * ramp * np.exp(-(((xx - centre) / (1.6 * half)) ** 2))
    return cv2.remap(image, xx, (yy - dy).astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)  # fmt: skip


@pytest.fixture(scope="module")
def face_video(tmp_path_factory):
    """An MJPG video: the astronaut's head moving, then her jaw dropping, then no face."""
    photo = skimage_data.astronaut()
    with FaceTracker(static=True) as tracker:
        mesh = tracker.track(photo).mesh
    pixels = mesh * [1.0, -1.0, -1.0]  # back to image x right, y down
    frames = [_similarity(photo, *motion) for motion in MOTIONS]
    frames += [_jaw_open(photo, pixels, amount) for amount in JAW_PIXELS]
    frames += [np.full_like(photo, 128)] * BLANK_FRAMES
    path = tmp_path_factory.mktemp("video") / "astronaut.avi"
    h, w = photo.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (w, h))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


@pytest.fixture(scope="module")
def tracked(face_video):
    with VideoSource(face_video) as video, FaceTracker() as tracker:
        return [tracker.track(rgb) for rgb in video.frames()]


def test_the_face_is_found_in_the_face_frames_and_not_in_the_blank_ones(tracked):
    faces = tracked[: len(MOTIONS) + JAW_FRAMES]
    assert len(tracked) == len(MOTIONS) + JAW_FRAMES + BLANK_FRAMES
    assert sum(t.points is not None for t in faces) >= 0.9 * len(faces)
    assert all(t.points is None and t.faces == 0 for t in tracked[len(faces) :])


def test_points_stay_put_when_the_head_moves_and_the_chin_drops_with_the_jaw(tracked):
    still = np.stack([t.points for t in tracked[: len(MOTIONS)] if t.points is not None])
    jaw = np.stack(
        [t.points for t in tracked[len(MOTIONS) : -BLANK_FRAMES] if t.points is not None]
    )
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


async def _watch(url: str, into: list) -> None:
    async for message in watch_channel(url):
        into.append(message)
        if isinstance(message, ChannelIdle) and any(isinstance(m, Result) for m in into):
            return


def _perform_stats(err: str) -> dict[str, int]:
    match = re.search(r"(\d+) frames read, face found in (\d+), (\d+) published", err)
    assert match, err
    return dict(zip(("read", "found", "published"), map(int, match.groups()), strict=True))


async def _perform_to_channel(settings, rig, argv_extra, video):
    async with run_server(settings) as server:
        server.app.state.store.put_rig("hero", rig)
        url = channel_url(server.base_url, "stage", "watch", {"rig": "hero"})
        messages: list = []
        watcher = asyncio.create_task(_watch(url, messages))
        await asyncio.wait_for(_first_ready(messages), 20)
        argv = ["perform", server.base_url, "--channel", "stage", "--rig", "hero",
                "--video", str(video), *argv_extra]  # fmt: skip
        code = await asyncio.to_thread(main, argv)
        await asyncio.wait_for(watcher, 30)
    return code, messages


async def _first_ready(messages: list) -> None:
    while not any(isinstance(m, Ready) for m in messages):
        await asyncio.sleep(0.01)


@pytest.mark.anyio
async def test_perform_publishes_the_tracked_points_and_viewers_see_them(
    tmp_path, face_video, capsys
):
    rig = fit(_character())
    code, messages = await _perform_to_channel(
        Settings(rigs_dir=tmp_path / "rigs"), rig, ["--no-calibrate"], face_video
    )
    stats = _perform_stats(capsys.readouterr().err)
    results = [m for m in messages if isinstance(m, Result)]
    assert code == 0
    assert stats["read"] == len(MOTIONS) + JAW_FRAMES + BLANK_FRAMES
    assert stats["found"] >= 0.9 * (len(MOTIONS) + JAW_FRAMES)
    assert stats["published"] == stats["found"]
    assert 1 <= len(results) <= stats["published"]
    assert all(np.isfinite(r.weights).all() for r in results)


@pytest.mark.ict
@pytest.mark.anyio
@pytest.mark.skipif(locate_ict() is None, reason="needs ../shared/data/ict-facekit")
async def test_generic_ict_rig_calibrated_on_the_neutral_opens_the_jaw(
    tmp_path, face_video, capsys
):
    from facecast.client.commands.import_ import arkit_example_set
    from facecast.rig.ict import DEFAULT_LANDMARKS

    example_set, _ = arkit_example_set(locate_ict(), DEFAULT_LANDMARKS, "face")
    rig = fit(example_set, noise=0.05, clamp="unit")
    code, messages = await _perform_to_channel(
        Settings(rigs_dir=tmp_path / "rigs"), rig, ["--neutral-frames", "4"], face_video
    )
    stats = _perform_stats(capsys.readouterr().err)
    weights = np.stack([m.weights for m in messages if isinstance(m, Result)])
    jaw = weights[:, rig.names.index("jawOpen")]
    assert code == 0 and stats["published"] == stats["found"] - 3  # 4 neutral frames, 1 frame
    # Watchers may skip frames; the published sequence is head motion, then the jaw drop.
    assert jaw[-1] > jaw[0] + 0.1


def test_an_absent_camera_is_a_clear_error(capsys):
    code = main(["perform", "http://127.0.0.1:9", "--channel", "x", "--rig", "hero",
                 "--camera", "9", "-q"])  # fmt: skip
    assert code == 2 and "cannot open camera 9" in capsys.readouterr().err


@pytest.mark.anyio
async def test_a_rig_with_another_point_count_is_refused_by_name(tmp_path, face_video, capsys):
    rng = np.random.default_rng(1)
    source = rng.normal(size=(2, 5, 3))
    target = rng.normal(size=(2, 4, 3))
    small = fit(ExampleSet(("neutral", "smile"), source, target, np.array([[0, 1, 2]])))
    async with run_server(Settings(rigs_dir=tmp_path / "rigs")) as server:
        server.app.state.store.put_rig("small", small)
        argv = ["perform", server.base_url, "--channel", "stage", "--rig", "small",
                "--video", str(face_video), "-q"]  # fmt: skip
        code = await asyncio.to_thread(main, argv)

    assert code == 2 and "has 5 feature points" in capsys.readouterr().err


def test_with_two_faces_in_view_the_largest_is_tracked():
    photo = skimage_data.astronaut()
    head = photo[30:260, 110:330]
    small = cv2.resize(head, None, fx=0.85, fy=0.85)
    canvas = np.full((300, 500, 3), 90, np.uint8)
    canvas[40:270, 10:230] = head
    canvas[40 : 40 + small.shape[0], 260 : 260 + small.shape[1]] = small
    with FaceTracker() as tracker:
        both = tracker.track(canvas)
        alone = tracker.track(canvas[:, :250].copy())

    assert both.faces == 2 and alone.faces == 1
    # The left, larger face: the same mesh as when it is alone in view (to a pixel or two).
    assert np.abs(both.mesh[:, :2] - alone.mesh[:, :2]).mean() < 1.0

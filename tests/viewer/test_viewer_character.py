"""Characters shown as authored: the viewer, overlay and perform page render the rig's
uploaded glTF / VRM 1.0 / VRM 0.x file in a real Chromium, posed through its bindings.

One server for the module (rigs stored with their character files), the package's one
browser; a publisher thread streams the poses a test asks for into a channel the page
watches. Checked by pixel: the texture's colours, the teeth when the jaw opens, the
silhouette when the head turns; and through the page's ``window.characterState()``: what
three-vrm made of a VRM (humanoid, look-at at the camera, expressions, spring bones), the
morphs the weights drive, the head bone's turn.
"""

from __future__ import annotations

import base64
import math
import os
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from websockets.sync.client import connect

from facecast.cli.snapshot import serving
from facecast.protocol import PUBLISH_PATH, SUBPROTOCOL, Frame, Hello, Ready, decode_server, encode
from facecast.protocol.head import Head
from facecast.rig import fit
from facecast.server.settings import Settings
from facecast.server.storage.characters import pack_character
from facecast.server.storage.rig_store import RigStore

from ..rig import _avatars as ict_avatars
from ._character import NAMES, build_character
from .test_viewer_pages import pixels

#: Screenshots written for people to look at (not read by the tests).
SHOTS = Path(os.environ.get("FACECAST_SHOTS", tempfile.gettempdir())) / "facecast-character-shots"
VARIANTS = {"face": ("gltf", True), "face-vrm1": ("vrm1", True), "face-vrm0": ("vrm0", True)}
LOCKED = "face-locked"


@pytest.fixture(scope="module")
def examples():
    return build_character().examples


@pytest.fixture(scope="module")
def character_server(tmp_path_factory, examples) -> Iterator[str]:
    rigs = tmp_path_factory.mktemp("character-rigs")
    store = RigStore(rigs)
    store.open()
    rig = fit(examples)
    for rig_id, (variant, redistribution) in {**VARIANTS, LOCKED: ("vrm1", False)}.items():
        made = build_character(variant, redistribution=redistribution)
        store.put_rig(rig_id, rig, character=pack_character(made.glb, made.record))
    store.close()
    settings = Settings(rigs_dir=rigs, access_log=False, log_level="warning")
    with serving(settings) as base_url:
        yield base_url


class Publisher:
    """Streams one pose (example ``index``'s points, a head turned ``yaw`` degrees) into a
    channel, lockstep at ~30 fps, from a thread; ``pose`` changes it, ``seq`` says from
    which frame on the new pose is sent."""

    def __init__(self, base_url: str, channel: str, rig: str, points: np.ndarray) -> None:
        self.url = base_url.replace("http", "ws") + PUBLISH_PATH.format(name=channel)
        self.rig = rig
        self.points = points.astype(np.float32)
        self.lock = threading.Lock()
        self.index, self.yaw = 0, 0.0
        self.jaw_open = NAMES.index("jawOpen")  # which of ``points`` opens the jaw
        self.seq = 0
        self.changed_at = 0
        self.stop = threading.Event()
        self.ready = threading.Event()

    def pose(self, index: int, yaw: float = 0.0) -> int:
        with self.lock:
            self.index, self.yaw = index, yaw
            self.changed_at = self.seq + 1
            return self.changed_at

    def run(self) -> None:
        with connect(self.url, subprotocols=[SUBPROTOCOL]) as ws:
            ws.send(encode(Hello(rig=self.rig)))
            assert isinstance(decode_server(ws.recv(timeout=10)), Ready)
            self.ready.set()
            while not self.stop.wait(1 / 30):
                with self.lock:
                    self.seq += 1
                    seq, index, yaw = self.seq, self.index, self.yaw
                half = math.radians(yaw) / 2
                head = Head(rotation=np.array([0, math.sin(half), 0, math.cos(half)], np.float32))
                ws.send(encode(Frame(seq=seq, ts=seq / 30, points=self.points[index], head=head)))
                ws.recv(timeout=10)


@contextmanager
def publishing(base_url: str, channel: str, rig: str, points: np.ndarray) -> Iterator[Publisher]:
    publisher = Publisher(base_url, channel, rig, points)
    thread = threading.Thread(target=publisher.run, daemon=True)
    thread.start()
    assert publisher.ready.wait(10), "the publisher got no ready"
    try:
        yield publisher
    finally:
        publisher.stop.set()
        thread.join(10)


def shown(page, seq: int) -> None:
    """Wait until the page shows a result of frame ``seq`` or later: the animation frame
    that applies a result draws it, or finds its pose on screen already."""
    page.wait_for_function("s => window.facecastStats.appliedSeq >= s", arg=seq)


def canvas_png(page) -> bytes:
    """The character's canvas as last drawn (a PNG; the page keeps its drawing buffer): what
    a screenshot of it shows, without the page's compositing a new frame for it, which
    takes seconds a shot with a large character on a machine without a GPU."""
    url = page.evaluate("document.querySelector('#stage canvas').toDataURL('image/png')")
    return base64.b64decode(url.split(",", 1)[1])


def lips(image: np.ndarray) -> int:
    """Pixels of the texture's painted lips (saturated red), however lit."""
    r, g, b = (image[..., c].astype(int) for c in range(3))
    return int(((r > 70) & (r > 2.2 * g) & (r > 1.8 * b) & (image[..., 3] > 0)).sum())


def iris(image: np.ndarray) -> int:
    """Pixels of the eyes' blue iris material."""
    r, g, b = (image[..., c].astype(int) for c in range(3))
    return int(((b > 90) & (b > 1.6 * r) & (b > 1.2 * g)).sum())


def skin(image: np.ndarray) -> int:
    r, g, b = (image[..., c].astype(int) for c in range(3))
    return int(((r > 90) & (r > 1.15 * g) & (g > 1.05 * b) & (r < 2.2 * g)).sum())


def teeth(image: np.ndarray) -> np.ndarray:
    """Mask of bright, pale pixels (teeth; the eyes' whites too, in every pose), not skin."""
    r, g, b = (image[..., c].astype(int) for c in range(3))
    return (r > 150) & (g > 150) & (b > 0.75 * r) & (image[..., 3] > 0)


def silhouette(image: np.ndarray, background: tuple[int, int, int] | None) -> np.ndarray:
    if background is None:
        return image[..., 3] > 0
    return np.abs(image[..., :3].astype(int) - background).max(axis=-1) > 12


YAW = 35.0  # degrees: the head turn check_character_page sends


def check_character_page(page, publisher: Publisher, name: str, background) -> dict:
    """Neutral, jaw open, head turned: screenshots saved and checked; returns the counts
    and the page's ``characterState()`` in each pose (``states``)."""
    states = {}

    def shot(tag: str) -> np.ndarray:
        png = canvas_png(page)
        SHOTS.mkdir(exist_ok=True)
        (SHOTS / f"{name}-{tag}.png").write_bytes(png)
        states[tag] = page.evaluate("window.characterState()")
        return pixels(png)

    shown(page, publisher.pose(0))
    neutral = shot("neutral")
    shown(page, publisher.pose(publisher.jaw_open))
    jaw = shot("jaw")
    shown(page, publisher.pose(0, yaw=YAW))
    page.wait_for_function("() => Math.abs(window.facecastStats.head[1]) > 0.2")
    turned = shot("turned")

    counts: dict = {"lips": lips(neutral), "iris": iris(neutral), "skin": skin(neutral)}
    assert counts["lips"] > 150, counts
    assert counts["iris"] > 20, counts
    assert counts["skin"] > 2000, counts
    # The teeth sit behind the face until the jaw opens: then they are in front of it.
    closed, opened = teeth(neutral), teeth(jaw)
    assert opened.sum() > closed.sum() + 300, (closed.sum(), opened.sum())
    ys = np.nonzero(opened & ~closed)[0]
    assert ys.mean() > neutral.shape[0] * 0.45  # in the lower half: the mouth, not a highlight
    # The head turns the whole character (face, teeth, eyes skinned to the head bone).
    before, after = silhouette(neutral, background), silhouette(turned, background)
    # Same expression (neutral) both times: without the head pose nothing would change.
    moved = float((before ^ after).sum() / before.sum())
    assert moved > 0.01, moved
    counts["states"] = states
    return counts


@pytest.mark.parametrize("rig_id", list(VARIANTS))
def test_viewer_renders_the_character_file_posed_by_weights_and_head(
    character_server, examples, page, rig_id
):
    channel = f"ch-{rig_id}"
    with publishing(character_server, channel, rig_id, examples.source_points) as publisher:
        # Wide: the HUD is a sidebar beside the character, not over it.
        page.set_viewport_size({"width": 800, "height": 420})
        page.goto(f"{character_server}/viewer?rig={rig_id}&channel={channel}")
        page.wait_for_function("window.facecastStats.state === 'live'")
        stats = page.evaluate("window.facecastStats.character")
        check_character_page(page, publisher, f"viewer-{rig_id}", background=(0x14, 0x16, 0x1C))

    variant = VARIANTS[rig_id][0]
    assert stats["format"] == variant
    assert stats["meshes"] == 3
    assert stats["vrm"] is (variant != "gltf")
    assert stats["head"] is not None
    assert stats["bound"] == 5  # four face morphs and the teeth's jawOpen
    if variant == "vrm1":
        assert "MToonMaterial" in stats["materials"]  # three-vrm's MToon for the skin
    info = page.locator("#character").inner_text()
    if variant != "gltf":
        assert "Facecast Tests" in info and "VRM" in info
    assert page.errors == []


@pytest.mark.parametrize("output", ["weights", "vertices"])
def test_a_pose_equal_to_the_one_on_screen_is_not_drawn_again(
    character_server, examples, page, output
):
    # A performer holding still sends the same pose frame after frame: the page applies
    # each (appliedSeq) and draws none of them after the first; a change is drawn at once.
    # Weights pose the character file, vertices the rig's own mesh ("moving" is the demo's).
    channel = f"ch-still-{output}"
    with publishing(character_server, channel, "face", examples.source_points) as publisher:
        page.goto(f"{character_server}/overlay?rig=face&channel={channel}&output={output}")
        page.wait_for_function("window.facecastStats.state === 'live'")
        shown(page, publisher.pose(0))
        before = page.evaluate("window.facecastStats")
        page.wait_for_function(
            "n => window.facecastStats.appliedSeq >= n", arg=before["appliedSeq"] + 10
        )
        still = page.evaluate("window.facecastStats")
        shown(page, publisher.pose(NAMES.index("jawOpen")))
        moved = page.evaluate("window.facecastStats")

    assert still["rendered"] == before["rendered"], (before, still)
    assert moved["rendered"] > still["rendered"]
    assert page.errors == []


def test_overlay_renders_the_vrm_on_transparency(character_server, examples, page):
    page.set_viewport_size({"width": 400, "height": 400})
    with publishing(character_server, "ch-overlay", "face-vrm1", examples.source_points) as pub:
        page.goto(f"{character_server}/overlay?rig=face-vrm1&channel=ch-overlay")
        page.wait_for_function("window.facecastStats.state === 'live'")
        check_character_page(page, pub, "overlay-face-vrm1", background=None)
    assert page.errors == []


def test_vertex_output_of_a_character_rig_shows_its_face_mesh(character_server, examples, page):
    # PROTOCOL.md §5.2: the vertex outputs carry the face mesh alone, so the page shows the
    # rig's model.glb (that mesh), not the character file.
    with publishing(character_server, "ch-vertices", "face", examples.source_points) as pub:
        page.goto(f"{character_server}/overlay?rig=face&channel=ch-vertices&output=vertices")
        page.wait_for_function("window.facecastStats.state === 'live'")
        shown(page, pub.pose(NAMES.index("jawOpen")))
        image = pixels(page.screenshot(omit_background=True))
        stats = page.evaluate("window.facecastStats")
        state = page.evaluate("window.characterState()")

    assert stats["character"] is None and stats["error"] is None
    assert state["status"] == "model" and state["meshes"] == []
    assert (image[..., 3] > 0).mean() > 0.05  # the face mesh is drawn
    assert lips(image) == 0  # ... untextured: the character file is not used
    assert page.errors == []


def test_a_vrm_that_forbids_redistribution_is_not_fetched_anonymously(character_server, page):
    page.goto(f"{character_server}/viewer?rig={LOCKED}")
    status = loaded_character(page)
    stats = page.evaluate("window.facecastStats.character")

    assert status == "model"  # the rig's own mesh instead
    assert "redistribution" in stats["withheld"]
    assert "forbids redistribution" in page.locator("#character").inner_text()


# -- the ICT-FaceKit test avatars, uploaded through PUT /v1/characters --------------------

ICT_VARIANTS = ("arkit", "vrm0", "vrm1")  # uploaded; the overlay shows vrm0, the viewer the rest


@pytest.fixture(scope="module")
def ict_poses(character_server) -> np.ndarray:
    """Uploads each ICT avatar as ``ict-<variant>``; the generic set's neutral and jawOpen."""
    import httpx

    from facecast.rig.characters.generic import generic_sources

    ict_avatars.require_ict()
    for variant in ICT_VARIANTS:
        response = httpx.put(
            f"{character_server}/v1/characters/ict-{variant}",
            content=ict_avatars.avatar(variant),
            params={"noise": 0.05, "clamp": "unit"},
            timeout=120,
        )
        assert response.status_code == 201, response.text
    generic = generic_sources()
    return np.stack([generic.points[0], generic.source_points("jawOpen")]).astype(np.float32)


def loaded_character(page) -> str:
    """Wait until the canvas shows a character file (or failed to): its data-character."""
    page.wait_for_function(
        "() => ['vrm', 'gltf', 'model', 'error'].includes("
        "document.querySelector('#stage canvas').dataset.character)",
        timeout=60_000,
    )
    return page.locator("#stage canvas").get_attribute("data-character")


def check_ict_states(states: dict, variant: str) -> None:
    """What three-vrm made of the avatar and how the page posed it, from characterState()."""
    neutral, jaw, turned = states["neutral"], states["jaw"], states["turned"]
    assert neutral["status"] == ("gltf" if variant == "arkit" else "vrm")
    assert [m["name"] for m in neutral["meshes"]] == ["face", "teeth", "eyes"]
    assert all(m["skinned"] for m in neutral["meshes"])
    # ICT's 51 ARKit shapes on the face, its jaw shapes on the teeth.
    assert neutral["morphs"] == 51 + len(ict_avatars.TEETH_SHAPES)
    # The rig's weights reach the morphs of both meshes bound to jawOpen.
    assert jaw["influences"]["face"]["jawOpen"] > 0.5, jaw["influences"]
    assert jaw["influences"]["teeth"]["jawOpen"] > 0.5, jaw["influences"]
    assert neutral["influences"].get("teeth", {}).get("jawOpen", 0.0) < 0.1
    # The head bone holds the sent turn (a VMC yaw: mirrored, PROTOCOL.md §5.3).
    assert neutral["head"]["rotation"][1] == pytest.approx(0.0, abs=0.01)
    expected_y = -math.sin(math.radians(YAW) / 2)
    assert turned["head"]["rotation"][1] == pytest.approx(expected_y, abs=0.02)
    if variant == "arkit":
        assert neutral["vrm"] is None
        return
    vrm = neutral["vrm"]
    assert neutral["vrmError"] is None
    assert vrm["metaVersion"] == variant[-1]
    assert vrm["humanoid"] and vrm["lookAt"] and vrm["expressionManager"], vrm
    assert vrm["springBoneManager"] and vrm["springJoints"] >= 2, vrm
    assert {"chest", "neck", "leftEye", "rightEye"} <= set(vrm["humanBones"])
    assert {"aa", "blink", "happy", "surprised", "neutral"} <= set(vrm["expressions"])
    # The eyes look at the viewer: the camera is a little to the character's left (+x of
    # a character facing +z) and above, for VRM 0.x (turned by rotateVRM0) as for 1.0.
    look = neutral["lookAt"]
    assert look["target"] == "camera"
    assert look["yaw"] > 3 and look["pitch"] != 0, look


@pytest.mark.parametrize("variant", ["arkit", "vrm1"])
def test_viewer_renders_an_uploaded_ict_avatar_as_authored(
    character_server, ict_poses, page, variant
):
    rig_id = f"ict-{variant}"
    with publishing(character_server, f"ch-{rig_id}", rig_id, ict_poses) as publisher:
        page.set_viewport_size({"width": 800, "height": 420})
        page.goto(f"{character_server}/viewer?rig={rig_id}&channel=ch-{rig_id}")
        status = loaded_character(page)
        page.wait_for_function("window.facecastStats.state === 'live'", timeout=60_000)
        publisher.jaw_open = 1
        checked = check_character_page(
            page, publisher, f"viewer-{rig_id}", background=(0x14, 0x16, 0x1C)
        )

    assert status == ("gltf" if variant == "arkit" else "vrm")
    check_ict_states(checked["states"], variant)
    assert page.errors == []


def test_overlay_renders_an_uploaded_ict_vrm0_on_transparency(character_server, ict_poses, page):
    page.set_viewport_size({"width": 400, "height": 400})
    with publishing(character_server, "ch-ict-overlay", "ict-vrm0", ict_poses) as publisher:
        page.goto(f"{character_server}/overlay?rig=ict-vrm0&channel=ch-ict-overlay")
        assert loaded_character(page) == "vrm"
        page.wait_for_function("window.facecastStats.state === 'live'", timeout=60_000)
        publisher.jaw_open = 1
        checked = check_character_page(page, publisher, "overlay-ict-vrm0", background=None)
    # The publisher gone, the overlay draws until the spring bones settle, then no more.
    page.wait_for_function("() => window.characterState().vrm.springsSettled")
    drawn = page.evaluate(
        """async () => {
            const before = window.facecastStats.rendered;
            for (let i = 0; i < 5; i++) await new Promise(requestAnimationFrame);
            return window.facecastStats.rendered - before;
        }"""
    )

    check_ict_states(checked["states"], "vrm0")
    assert drawn == 0
    assert page.errors == []


def test_viewer_renders_a_neutral_only_avatar_moved_by_its_transferred_shapes(
    character_server, ict_poses, page
):
    import time

    import httpx

    rig_id = "ict-transferred"
    put = httpx.put(
        f"{character_server}/v1/characters/{rig_id}",
        content=ict_avatars.avatar("neutral_only"),
        params={"expressions": "transfer", "names": "jawOpen", "noise": 0.05, "clamp": "unit"},
        timeout=120,
    )
    assert put.status_code == 202, put.text
    deadline = time.monotonic() + 120
    while (job := httpx.get(f"{character_server}/v1/characters/{rig_id}/job").json())[
        "state"
    ] not in ("done", "failed"):  # a job resource: polled
        assert time.monotonic() < deadline, job
        time.sleep(0.1)
    assert job["state"] == "done", job
    with publishing(character_server, f"ch-{rig_id}", rig_id, ict_poses) as publisher:
        page.set_viewport_size({"width": 800, "height": 420})
        page.goto(f"{character_server}/viewer?rig={rig_id}&channel=ch-{rig_id}")
        page.wait_for_function("window.facecastStats.state === 'live'", timeout=60_000)
        publisher.jaw_open = 1
        check_character_page(page, publisher, f"viewer-{rig_id}", background=(0x14, 0x16, 0x1C))

    assert page.errors == []

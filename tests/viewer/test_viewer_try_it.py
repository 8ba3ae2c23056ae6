"""Your own character in the first minutes: the demo on it without a camera, its licence
settled by its owner. A real server (characters uploaded through ``PUT /v1/characters``),
the CLI's ``publish``/``watch``/``rigs put``, and the pages in a real Chromium.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest

from facecast.cli.main import main
from facecast.cli.snapshot import serving, write_demo_rig
from facecast.rig import fit, load_rig
from facecast.rig.characters.expression_names import ARKIT_NAMES
from facecast.rig.characters.generic import generic_sources
from facecast.rig.demo import arkit_demo_animation, arkit_demo_weights
from facecast.rig.examples import ExampleSet
from facecast.server.settings import Settings
from facecast.server.storage.rig_store import RigStore

from ._character import build_character
from .test_viewer_character import loaded_character
from .test_viewer_pages import FRAMES

#: Screenshots written for people to look at (not read by the tests).
SHOTS = Path(os.environ.get("FACECAST_SHOTS", tempfile.gettempdir())) / "facecast-try-it-shots"
TAKE = Path(__file__).parents[1] / "data" / "livelink" / "llv_dao.csv"
BOUND = ("jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp")
TOKENS = {"admin-token": frozenset({"admin"}), "viewer-token": frozenset({"viewer"})}


def _names_on_primitives(glb: bytes) -> bytes:
    """The GLB with each mesh's ``extras.targetNames`` moved onto its primitives."""
    length = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20 : 20 + length])
    rest = glb[20 + length :]
    for mesh in gltf["meshes"]:
        names = mesh.pop("extras", {}).get("targetNames")
        if names is not None:
            for primitive in mesh["primitives"]:
                primitive["extras"] = {"targetNames": names}
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _arkit_rig_set() -> ExampleSet:
    """A plain mesh with one morph per ARKit shape of the generic set (52 weights): the
    HUD's longest list."""
    generic = generic_sources()
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 8), np.linspace(-1, 1, 8)), -1).reshape(-1, 2)
    neutral = np.column_stack([grid, np.zeros(len(grid))])
    rng = np.random.default_rng(3)
    targets = neutral + np.concatenate([[0], rng.uniform(0.02, 0.2, len(generic.names) - 1)])[
        :, None, None
    ] * rng.normal(size=(len(generic.names), len(grid), 3))
    i = np.arange(7)
    a = (i[:, None] * 8 + i[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + 9], 1), np.stack([a, a + 9, a + 8], 1)])
    return ExampleSet(generic.names, generic.points, targets, faces)


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[str]:
    rigs = tmp_path_factory.mktemp("try-it-rigs")
    write_demo_rig(rigs)
    store = RigStore(rigs)
    store.open()
    # A rig on points of its own (the test character's own source set): no demo for it.
    store.put_rig("own-points", fit(build_character().examples))
    store.put_rig("arkit52", fit(_arkit_rig_set(), noise=0.05, clamp="unit"))
    # A character fitted before the layout grew 20 -> 24 points (the generic set's first 20).
    old = _arkit_rig_set()
    store.put_rig(
        "arkit20",
        fit(ExampleSet(old.names, old.source_points[:, :20], old.target_vertices,
                       old.target_faces), noise=0.05, clamp="unit"),
    )  # fmt: skip
    store.close()
    settings = Settings(rigs_dir=rigs, access_log=False, log_level="warning")
    with serving(settings) as base_url:
        for rig_id, glb, query in (
            ("face", build_character("gltf").glb, {}),
            ("prims", _names_on_primitives(build_character("gltf").glb), {}),
            ("mine", build_character("vrm1", redistribution=False).glb, {"rights_holder": "true"}),
            ("locked", build_character("vrm1", redistribution=False).glb, {}),
        ):
            response = httpx.put(
                f"{base_url}/v1/characters/{rig_id}", content=glb, params=query, timeout=120
            )
            assert response.status_code == 201, response.text
        yield base_url


def _animation(base_url: str, **params: str) -> dict:
    # A performance is built on its first request (~0.5 s quiet; many times that on a
    # loaded 2-core runner, past httpx's 5 s default): not what is tested here.
    response = httpx.get(f"{base_url}/v1/demo/animation", params=params, timeout=60)
    assert response.status_code == 200, response.text
    value = msgpack.unpackb(response.content)
    wire = value["points"]
    assert wire["dtype"] == "f32"
    value["points"] = np.frombuffer(wire["data"], "<f4").reshape(wire["shape"])
    return value


# -- 1. the demo performance on any character ---------------------------------------------


def test_demo_animation_comes_on_the_points_of_the_rig_asked_for(server):
    plain = _animation(server)
    demo = _animation(server, rig="demo")
    character = _animation(server, rig="face")
    earlier = _animation(server, rig="arkit20")
    generic = generic_sources()

    assert (plain["performance"], plain["points"].shape[1]) == ("demo", 21)
    assert (demo["performance"], demo["points"].shape[1]) == ("demo", 21)
    assert (character["performance"], character["points"].shape[1]) == ("generic", 26)
    # A character of the layout's earlier version gets the same performance's first 20.
    assert (earlier["performance"], earlier["points"].shape[1]) == ("generic", 20)
    np.testing.assert_array_equal(earlier["points"], character["points"][:, :20])
    # The generic performance's rest frames are the generic set's neutral.
    rest = np.abs(character["points"] - generic.points[0]).max(axis=(1, 2)).min()
    assert rest < 1e-4


def test_demo_animation_for_a_rig_on_its_own_points_or_no_rig_is_a_clear_error(server):
    own = httpx.get(f"{server}/v1/demo/animation", params={"rig": "own-points"})
    missing = httpx.get(f"{server}/v1/demo/animation", params={"rig": "nobody"})
    bad = httpx.get(f"{server}/v1/demo/animation", params={"rig": "../x"})

    assert (own.status_code, own.json()["code"]) == (409, "no_demo_performance")
    assert "watch a channel" in own.json()["detail"]
    assert (missing.status_code, missing.json()["code"]) == (404, "rig_not_found")
    assert (bad.status_code, bad.json()["code"]) == (400, "invalid_rig_id")


def _sample(page) -> dict:
    return page.evaluate(
        """() => {
          const influences = window.characterState().influences || {};
          const merged = {};
          for (const morphs of Object.values(influences))
            for (const [name, value] of Object.entries(morphs))
              merged[name] = Math.max(merged[name] || 0, value);
          return { demoTime: window.facecastStats.demoTime, weights: merged };
        }"""
    )


def test_viewer_without_a_channel_plays_the_demo_on_an_uploaded_character(server, page):
    rig = load_rig_from(server, "face")
    points = _animation(server, rig="face")["points"]
    fps = 60.0
    truth = arkit_demo_weights()
    page.goto(f"{server}/viewer?rig=face")
    assert loaded_character(page) == "gltf"
    page.wait_for_function(FRAMES, arg=3)
    samples = []
    for _ in range(40):
        page.wait_for_function(FRAMES, arg=page.evaluate("window.facecastStats.frames") + 6)
        samples.append(_sample(page))
    page.screenshot(path=str(_shot("viewer-demo-on-character.png")))

    shown = np.array([[s["weights"].get(n, 0.0) for n in BOUND] for s in samples])
    frames = np.array([int(s["demoTime"] * fps) % len(points) for s in samples])
    # What the page shows is the rig's weights for a frame just sent (the newest result,
    # at most a few frames behind the one the stats name).
    expected = rig.weights(points.astype(np.float32))
    columns = [rig.names.index(n) for n in BOUND]
    errors = np.array(
        [
            min(np.abs(expected[(f - lag) % len(points)][columns] - row).max() for lag in range(4))
            for f, row in zip(frames, shown, strict=True)
        ]
    )
    assert (errors < 2e-3).mean() >= 0.8, errors
    # ... and they move with the performance: the jaw opens and closes, and the page's
    # weights follow the performance's own ARKit weights for these shapes.
    jaw = shown[:, BOUND.index("jawOpen")]
    assert jaw.max() - jaw.min() > 0.4
    want = truth[frames][:, [ARKIT_NAMES.index(n) for n in BOUND]]
    assert np.corrcoef(shown.ravel(), want.ravel())[0, 1] > 0.7
    assert page.errors == []


def load_rig_from(base_url: str, rig_id: str):
    response = httpx.get(f"{base_url}/v1/rigs/{rig_id}/rig")
    assert response.status_code == 200
    path = Path(tempfile.mkdtemp()) / f"{rig_id}.rig"
    path.write_bytes(response.content)
    return load_rig(path)


def _shot(name: str) -> Path:
    SHOTS.mkdir(parents=True, exist_ok=True)
    return SHOTS / name


def test_overlay_without_a_channel_plays_the_demo_on_a_vrm(server, page):
    page.goto(f"{server}/overlay?rig=mine&width=360&height=360")
    assert loaded_character(page) == "vrm"
    page.wait_for_function(FRAMES, arg=10)
    page.screenshot(path=str(_shot("overlay-demo-on-vrm.png")))

    assert page.evaluate("window.facecastStats.state") == "live"
    assert page.errors == []


def test_viewer_names_morphs_that_only_a_primitive_names(server, page):
    page.goto(f"{server}/viewer?rig=prims")
    assert loaded_character(page) == "gltf"
    # One read: the influences are those of the frame drawn, which the demo moves on.
    names = page.wait_for_function(
        "() => { const names = [...new Set(Object.values("
        "window.characterState().influences || {}).flatMap(m => Object.keys(m)))];"
        " return names.includes('jawOpen') && names; }"
    ).json_value()

    assert set(names) <= set(BOUND) and "jawOpen" in names


def test_viewer_hud_fits_52_weights_in_a_540_px_window(server, page):
    for width in (960, 540):
        page.set_viewport_size({"width": width, "height": 540})
        page.goto(f"{server}/viewer?rig=arkit52")
        page.wait_for_function(FRAMES, arg=3)
        page.screenshot(path=str(_shot(f"viewer-hud-52-{width}x540.png")))
        rows = page.locator("#weights .weight")
        last = rows.nth(rows.count() - 1).bounding_box()
        hud = page.locator("#hud").bounding_box()

        assert rows.count() == 52
        assert last["y"] + last["height"] <= 540, width
        assert hud["y"] + hud["height"] <= 540, width
    assert page.errors == []


def test_publish_demo_on_a_character_rig_drives_a_watcher(server, tmp_path):
    out = tmp_path / "seen.npz"
    watched: list[int] = []
    watcher = threading.Thread(
        target=lambda: watched.append(
            main(["watch", server, "try", "--rig", "face", "-o", str(out),
                  "--frames", "300", "--timeout", "60"])
        ),
    )  # fmt: skip
    watcher.start()
    _wait_viewers(server, "try", 1)
    published = _cli(["publish", server, "try", "demo", "--rig", "face", "--seconds", "6", "-q"])
    watcher.join(90)

    assert (published, watched) == (0, [0])
    seen = np.load(out)
    rig = load_rig_from(server, "face")
    sent = arkit_demo_animation(6.0).points.astype(np.float32)[seen["seq"]]
    # The watcher saw the rig's weights for the generic performance's frames ...
    np.testing.assert_allclose(seen["weights"], rig.weights(sent), atol=1e-6)
    # ... and the mouth opens and closes.
    jaw = seen["weights"][:, list(seen["names"]).index("jawOpen")]
    assert jaw.max() > 0.6 and jaw.min() < 0.05


def test_publish_the_bundled_livelink_take_on_the_generic_source(server, tmp_path):
    published = _cli(
        ["publish", server, "take", str(TAKE), "--source-rig", "generic", "--rig", "face", "-q"]
    )
    shipped = Path(__file__).parents[2] / "rig" / "characters" / "generic_arkit" / "points.npz"
    by_path = _cli(
        ["publish", server, "take", str(TAKE), "--source-rig", str(shipped), "--rig", "face", "-q"]
    )

    assert (published, by_path) == (0, 0)


def _cli(argv: list[str]) -> int:
    """``facecast ARGV`` in a thread of its own (this thread runs Playwright's event loop,
    and the commands run their own), its exit status."""
    codes: list[int] = []
    thread = threading.Thread(target=lambda: codes.append(main(argv)))
    thread.start()
    thread.join(120)
    assert codes, f"facecast {argv[0]} did not finish"
    return codes[0]


def _wait_viewers(base_url: str, channel: str, count: int) -> None:
    with httpx.Client(base_url=base_url) as http:
        for _ in range(600):
            response = http.get(f"/v1/channels/{channel}")
            if response.status_code == 200 and response.json()["viewers"] >= count:
                return
            threading.Event().wait(0.05)
    raise AssertionError(f"no viewer joined {channel!r}")


# -- 2. the licence, settled by the character's owner -------------------------------------


def test_upload_answer_says_who_is_shown_a_licence_restricted_vrm(server):
    glb = build_character("vrm1", redistribution=False).glb
    held = httpx.put(f"{server}/v1/characters/answer", content=glb, timeout=120)
    owned = httpx.put(
        f"{server}/v1/characters/answer", content=glb, params={"rights_holder": "true"}, timeout=120
    )
    plain = httpx.put(
        f"{server}/v1/characters/answer-gltf", content=build_character("gltf").glb, timeout=120
    )

    held_view, owned_view = held.json()["character"], owned.json()["character"]
    assert (held_view["shown_to"], held_view["rights_holder"]) == ("token_holders", False)
    assert "--rights-holder" in held_view["licence_note"]
    assert (owned_view["shown_to"], owned_view["rights_holder"]) == ("everyone", True)
    assert (
        "holds the rights" in owned_view["licence_note"]
        or "hold the rights" in (owned_view["licence_note"])
    )
    assert plain.json()["character"]["shown_to"] == "everyone"


def test_the_rights_holder_declaration_is_kept_and_listed(server):
    described = httpx.get(f"{server}/v1/rigs/mine").json()["character"]
    listed = {r["id"]: r["character"] for r in httpx.get(f"{server}/v1/rigs").json()["rigs"]}
    served = httpx.get(f"{server}/v1/rigs/mine/character.glb")
    withheld = httpx.get(f"{server}/v1/rigs/locked/character.glb")

    assert (described["rights_holder"], described["shown_to"]) == (True, "everyone")
    assert listed["mine"]["shown_to"] == "everyone" and listed["mine"]["rights_holder"]
    assert listed["locked"]["shown_to"] == "token_holders"
    assert listed["demo"] is None
    assert served.status_code == 200 and served.content[:4] == b"glTF"
    assert (withheld.status_code, withheld.json()["code"]) == (
        403,
        "character_not_redistributable",
    )


@pytest.mark.parametrize(("rig_id", "status"), [("mine", "vrm"), ("locked", "model")])
def test_viewer_shows_a_licence_restricted_vrm_only_when_its_owner_said_so(
    server, page, rig_id, status
):
    page.goto(f"{server}/viewer?rig={rig_id}")
    shown = loaded_character(page)
    page.wait_for_function(FRAMES, arg=3)
    page.screenshot(path=str(_shot(f"viewer-licence-{rig_id}.png")))
    text = page.locator("#character").inner_text()

    assert shown == status
    assert ("forbids redistribution" in text) == (rig_id == "locked")
    assert ("its uploader holds the rights" in text) == (rig_id == "mine")
    # The withheld file's 403 is the one thing the browser logs.
    assert [e for e in page.errors if "403" not in e] == []


def test_landing_page_shows_who_is_shown_each_character(server, page):
    page.set_viewport_size({"width": 1000, "height": 640})
    page.goto(f"{server}/")
    page.wait_for_function("() => window.facecastLanding && window.facecastLanding.loaded")
    page.screenshot(path=str(_shot("landing-licence.png")))

    def cell(rig_id: str) -> str:
        row = page.locator("#rigs tbody tr", has=page.locator("td.id", has_text=rig_id))
        return row.first.locator("td.character").inner_text()

    assert "shown to everyone (rights holder)" in cell("mine")
    assert "token holders only" in cell("locked")
    assert cell("demo") == "—"


def test_rigs_put_rights_holder_and_demo_from_the_command_line(server, tmp_path, capsys):
    avatar = tmp_path / "avatar.vrm"
    avatar.write_bytes(build_character("vrm1", redistribution=False).glb)

    owned = _cli(["rigs", "put", server, "cli-mine", str(avatar), "--rights-holder"])
    held = _cli(["rigs", "put", server, "cli-held", str(avatar)])
    demo = _cli(["rigs", "put", server, "cli-demo", "demo"])
    out = capsys.readouterr().out

    assert (owned, held, demo) == (0, 0, 0)
    assert "licence: shown to everyone: its VRM licence forbids redistribution, and" in out
    assert "licence: shown only to viewers with a token" in out
    assert "created cli-demo: the demo set fitted here, M=13 K=21" in out
    assert httpx.get(f"{server}/v1/rigs/cli-demo").json()["num_points"] == 21


def test_rights_holder_without_the_admin_role_is_refused_and_stores_nothing(tmp_path):
    settings = Settings(
        rigs_dir=tmp_path / "rigs", auth=True, tokens=TOKENS, access_log=False, log_level="warning"
    )
    glb = build_character("vrm1", redistribution=False).glb
    with serving(settings) as base_url, httpx.Client(base_url=base_url, timeout=120) as http:
        refused = http.put(
            "/v1/characters/mine",
            content=glb,
            params={"rights_holder": "true"},
            headers={"Authorization": "Bearer viewer-token"},
        )
        after = http.get("/v1/rigs/mine", headers={"Authorization": "Bearer admin-token"})
        accepted = http.put(
            "/v1/characters/mine",
            content=glb,
            params={"rights_holder": "true"},
            headers={"Authorization": "Bearer admin-token"},
        )

    assert (refused.status_code, refused.json()["code"]) == (403, "forbidden")
    assert (after.status_code, after.json()["code"]) == (404, "rig_not_found")
    assert accepted.status_code == 201
    assert accepted.json()["character"]["rights_holder"] is True


def _without_morphs(glb: bytes) -> bytes:
    """The GLB with every morph target (and VRM expression) taken out: a neutral-only file."""
    length = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20 : 20 + length])
    for mesh in gltf["meshes"]:
        mesh.pop("extras", None)
        for primitive in mesh["primitives"]:
            primitive.pop("targets", None)
        mesh.pop("weights", None)
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + glb[20 + length :]
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def test_a_neutral_only_upload_is_offered_a_transfer_only_by_a_server_that_has_one(tmp_path):
    settings = Settings(
        rigs_dir=tmp_path / "rigs", transfer_source="off", access_log=False, log_level="warning"
    )
    with serving(settings) as base_url:
        answer = httpx.put(
            f"{base_url}/v1/characters/head",
            content=_without_morphs(build_character("gltf").glb),
            timeout=120,
        )

    assert (answer.status_code, answer.json()["code"]) == (422, "no_expressions")
    assert "?expressions=transfer" not in answer.json()["detail"]
    assert "facecast expressions FILE -o FOLDER" in answer.json()["detail"]


def test_watch_on_a_rig_of_another_point_count_says_the_cause(server, tmp_path, capsys):
    watched: list[int] = []
    watcher = threading.Thread(
        target=lambda: watched.append(
            main(["watch", server, "mismatch", "--rig", "face", "-o", str(tmp_path / "w.npz"),
                  "--timeout", "60"])
        ),
    )  # fmt: skip
    watcher.start()
    _wait_viewers(server, "mismatch", 1)
    published = _cli(
        ["publish", server, "mismatch", "demo", "--rig", "demo", "--seconds", "1", "-q"]
    )
    watcher.join(90)
    err = capsys.readouterr().err

    assert published == 0 and watched and watched[0] != 0
    assert "no result received from channel 'mismatch': the server said wrong_point_count" in err
    assert "rig_mismatch" in err

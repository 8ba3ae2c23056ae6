"""Performer calibration against a real uvicorn: capture -> {id}@{performer} rig, profile, refit."""

from __future__ import annotations

import json

import httpx
import msgpack
import numpy as np
import pytest
import websockets
from _server_helpers import open_session, tiny_rig

from facecast.protocol import Frame, Result, decode_server, encode
from facecast.rig import ExampleSet, fit
from facecast.rig.sources.capture import robust_example
from facecast.server.settings import Settings
from facecast.server.storage.profiles import HELD_NOISE_FLOOR, MAX_HELD_FRAMES
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

K = 20  # the mediapipe_face_mesh layout's first version's feature points (26 now)
NAMES = ("neutral", "smile", "frown", "jawOpen", "browUp")


def character(names=NAMES, seed: int = 0, num_vertices: int = 30, k: int = K) -> ExampleSet:
    """A character whose source face has ``k`` feature points (the layout's 20 or 24)."""
    rng = np.random.default_rng(seed)
    m = len(names)
    source = np.repeat(rng.normal(scale=3.0, size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.5, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, num_vertices, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, num_vertices, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(num_vertices - 2)])
    return ExampleSet(names, source, target, faces)


def performer_points(names=NAMES, seed: int = 11, k: int = K) -> dict[str, np.ndarray]:
    """Another face making the expressions: its own neutral and its own displacements."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(scale=3.0, size=(k, 3))
    points = {"neutral": neutral}
    for name in names[1:]:
        points[name] = neutral + rng.normal(scale=0.6, size=(k, 3))
    return points


def capture_body(points, **extra) -> dict:
    return {
        "layout": "mediapipe_face_mesh",
        "points": {n: np.asarray(p).tolist() for n, p in points.items()},
        **extra,
    }


@pytest.fixture
async def server(settings):
    async with run_server(settings) as running:
        store = running.app.state.store
        store.put_rig("hero", fit(character()))
        store.put_rig("other", fit(character(("neutral", "jawOpen", "smile", "pout"), seed=5)))
        store.put_rig("tiny", tiny_rig())
        store.put_rig("hero24", fit(character(k=24)))
        yield running


def http(server, **kwargs) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=60, **kwargs)


async def test_capture_fits_a_rig_whose_weights_are_cardinal_on_the_captured_points(server):
    points = performer_points()
    async with http(server) as client:
        response = await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))
        rig_file = await client.get("/v1/rigs/hero@alice/rig")

    assert response.status_code == 201, response.text
    body = response.json()
    assert body["id"] == "hero@alice" and body["names"] == list(NAMES)
    assert body["performer"] == "alice" and body["skipped"] == [] and body["warnings"] == []
    from facecast.rig import rig_from_bytes

    rig = rig_from_bytes(rig_file.content)
    weights = rig.weights(np.stack([points[n] for n in NAMES]))
    np.testing.assert_allclose(weights, np.eye(len(NAMES)), atol=1e-8)
    # The targets are the character's own: the expression's captured points give its mesh.
    hero = server.app.state.store.get("hero")
    np.testing.assert_allclose(
        rig.clone(points["smile"]), hero.blend(np.eye(len(NAMES))[1]), atol=1e-5
    )


async def test_a_capture_of_a_later_layout_fits_a_rig_of_its_earlier_count_on_every_point(
    server,
):
    """The layout grew 20 -> 24 -> 26 points by appending (lid points, then the iris
    centres): a capture of today's points fits a rig of an earlier count (a character
    uploaded before, or made from ICT's 68 landmarks, which have no iris) on all of them,
    the performer's rig taking the capture's count; here the iris is all that tells two
    expressions apart. A capture of fewer points than the rig, or of a count no version of
    the layout had, is refused."""
    base = performer_points(k=24)
    shift = np.array([0.0, -0.1, 0.0])
    full = {n: np.concatenate([p, p[6:10:2] + shift]) for n, p in base.items()}
    full["smile"] = full["neutral"].copy()
    full["smile"][24:] += [0.4, 0.0, 0.0]  # only the irises move (the eyes turn)
    async with http(server) as client:
        response = await client.put("/v1/rigs/hero24/performer/carol", json=capture_body(full))
        rig_file = await client.get("/v1/rigs/hero24@carol/rig")
        lids = await client.put(
            "/v1/rigs/hero/performer/erin",
            json=capture_body({n: p[:24] for n, p in full.items() if n != "smile"}),
        )
        short = await client.put(
            "/v1/rigs/hero24/performer/carol", json=capture_body(performer_points())
        )
        odd = await client.put(
            "/v1/rigs/hero/performer/dave",
            json=capture_body({n: p[:22] for n, p in full.items()}),
        )

    assert response.status_code == 201, response.text
    from facecast.rig import rig_from_bytes

    rig = rig_from_bytes(rig_file.content)
    assert rig.num_points == 26 and response.json()["num_points"] == 26
    weights = rig.weights(np.stack([full[n] for n in NAMES]))
    np.testing.assert_allclose(weights, np.eye(len(NAMES)), atol=1e-8)
    assert lids.status_code == 201 and lids.json()["num_points"] == 24, lids.text
    # 20 points for a 24-point rig, 22 (no version of the layout) for a 20-point one.
    for answer in (short, odd):
        assert (answer.status_code, answer.json()["code"]) == (422, "wrong_point_count")


async def test_msgpack_capture_gives_the_same_rig_and_a_second_put_answers_200(server):
    points = performer_points()
    packed = msgpack.packb(capture_body(points))
    async with http(server) as client:
        first = await client.put("/v1/rigs/hero/performer/bob", json=capture_body(points))
        second = await client.put(
            "/v1/rigs/hero/performer/bob",
            content=packed,
            headers={"Content-Type": "application/msgpack"},
        )

    assert (first.status_code, second.status_code) == (201, 200)
    same = ("names", "condition_number", "components", "noise")
    assert [first.json()[k] for k in same] == [second.json()[k] for k in same]


async def test_skipped_expressions_are_left_out_of_the_fit_and_named(server):
    points = performer_points()
    del points["frown"], points["browUp"]
    async with http(server) as client:
        response = await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))

    body = response.json()
    assert response.status_code == 201
    assert body["names"] == ["neutral", "smile", "jawOpen"]
    assert body["skipped"] == ["frown", "browUp"]


async def test_the_capture_spread_becomes_the_fit_noise_with_bounded_weights(server):
    rng = np.random.default_rng(2)
    sigma = 0.05
    points = performer_points()
    captured, spreads = {}, []
    for name, held in points.items():
        frames = held + rng.normal(scale=sigma, size=(30, K, 3))
        captured[name], spread, _ = robust_example(frames)
        spreads.append(spread)
    noise = float(np.sqrt(np.mean(np.square(spreads))))
    async with http(server) as client:
        response = await client.put(
            "/v1/rigs/hero/performer/carol", json=capture_body(captured, noise=noise)
        )

    body = response.json()
    assert response.status_code == 201, body
    assert abs(noise - sigma) < 0.3 * sigma  # the robust spread measures the tracker noise
    assert body["noise"] == noise and body["clamp"] == "unit"


def _held(points, sigma: float, frames: int = 30, seed: int = 4) -> dict[str, np.ndarray]:
    """Frames of each expression held still under tracker noise of std ``sigma``."""
    rng = np.random.default_rng(seed)
    return {n: p + rng.normal(scale=sigma, size=(frames, K, 3)) for n, p in points.items()}


async def test_noise_is_measured_from_the_held_frames_and_the_rig_fitted_with_it(server):
    sigma = 0.05
    points = performer_points()
    held = _held(points, sigma)
    body = capture_body(points, held={n: f.tolist() for n, f in held.items()})
    async with http(server) as client:
        response = await client.put("/v1/rigs/hero/performer/carol", json=body)
        profile = await client.get("/v1/performers/carol")

    answer = response.json()
    assert response.status_code == 201, answer
    steps = np.concatenate([np.diff(f, axis=0).ravel() for f in held.values()])
    expected = float(np.sqrt(np.mean(steps * steps) / 2.0))  # pooled over every step
    assert answer["noise"] == pytest.approx(expected, rel=1e-12)
    assert abs(answer["noise"] - sigma) < 0.05 * sigma
    assert (answer["noise_source"], answer["held_frames"]) == ("held_frames", 30 * len(points))
    fitted = server.app.state.store.get("hero@carol").fit_report
    assert fitted["noise"] == answer["noise"] and fitted["clamp"] == "unit"
    assert profile.json()["noise"] == answer["noise"]
    assert profile.json()["noise_source"] == "held_frames"


async def test_held_frames_of_a_still_image_measure_the_noise_floor(server):
    points = performer_points()
    held = {n: [p.tolist()] * 10 for n, p in points.items()}  # identical frames
    async with http(server) as client:
        response = await client.put(
            "/v1/rigs/hero/performer/carol", json=capture_body(points, held=held)
        )

    answer = response.json()
    assert response.status_code == 201, answer
    assert (answer["noise"], answer["noise_source"]) == (HELD_NOISE_FLOOR, "held_frames")


async def test_a_noise_given_with_held_frames_wins(server):
    points = performer_points()
    held = {n: f.tolist() for n, f in _held(points, 0.05).items()}
    async with http(server) as client:
        response = await client.put(
            "/v1/rigs/hero/performer/carol", json=capture_body(points, noise=0.02, held=held)
        )

    answer = response.json()
    assert response.status_code == 201, answer
    assert (answer["noise"], answer["noise_source"], answer["held_frames"]) == (0.02, "capture", 0)


@pytest.mark.parametrize("frames,status", [(MAX_HELD_FRAMES, 201), (MAX_HELD_FRAMES + 1, 422)])
async def test_held_frames_at_the_limit_are_taken_and_past_it_refused(server, frames, status):
    points = performer_points()
    held = {"neutral": _held({"neutral": points["neutral"]}, 0.05, frames)["neutral"].tolist()}
    async with http(server) as client:
        response = await client.put(
            "/v1/rigs/hero/performer/carol", json=capture_body(points, held=held)
        )

    assert response.status_code == status, response.text
    if status == 422:
        assert response.json()["code"] == "bad_held_frames"


def _nan_json(points) -> bytes:
    text = json.dumps(capture_body(points))
    return text.replace(str(points["smile"][0][0].tolist()), "NaN", 1).encode()


def _bad_cases():
    points = performer_points()
    no_neutral = {k: v for k, v in points.items() if k != "neutral"}
    coincide = dict(points, frown=points["smile"])
    short = dict(points, smile=points["smile"][:19])
    only_neutral = {"neutral": points["neutral"]}
    # All 20 neutral points equal: was stored (201), a rig refusing every other frame.
    flat_neutral = dict(points, neutral=np.full((K, 3), 2.5))
    held = {n: f.tolist() for n, f in _held(points, 0.05, frames=3).items()}
    return {
        "no-neutral": (capture_body(no_neutral), None, 422, "no_neutral"),
        "unknown-expression": (capture_body(dict(points, wink=points["smile"])), None, 422,
                               "unknown_expression"),
        "wrong-k": (capture_body({n: p[:19] for n, p in points.items()}), None, 422,
                    "wrong_point_count"),
        "k-differs": (capture_body(short), None, 422, "wrong_point_count"),
        "not-triples": (dict(capture_body(points), points={"neutral": [[1, 2]] * K}), None, 422,
                        "wrong_point_count"),
        "only-neutral": (capture_body(only_neutral), None, 422, "too_few_examples"),
        "flat-neutral": (capture_body(flat_neutral), None, 422, "degenerate_neutral"),
        "negative-noise": (capture_body(points, noise=-1.0), None, 422, "bad_noise"),
        "string-noise": (capture_body(points, noise="high"), None, 422, "bad_noise"),
        "unknown-layout": (dict(capture_body(points), layout="dlib_68"), None, 422,
                           "unknown_layout"),
        "unknown-field": (dict(capture_body(points), extra=1), None, 422, "bad_capture"),
        "coinciding": (capture_body(coincide), None, 422, "examples_coincide"),
        "held-unknown": (capture_body(points, held={"wink": held["smile"]}), None, 422,
                         "bad_held_frames"),
        "held-one-frame": (capture_body(points, held={"smile": held["smile"][:1]}), None, 422,
                           "bad_held_frames"),
        "held-wrong-k": (capture_body(points, held={"smile": [f[:19] for f in held["smile"]]}),
                         None, 422, "bad_held_frames"),
        "held-not-a-map": (capture_body(points, held=[1, 2]), None, 422, "bad_held_frames"),
        "nan-literal": (_nan_json(points), "application/json", 422, "non_finite"),
        "not-json": (b"{not json", "application/json", 400, "bad_capture"),
        "not-msgpack": (b"\xc1\xc1", "application/msgpack", 400, "bad_capture"),
        "text-plain": (b"hello", "text/plain", 415, "unsupported_media_type"),
        "empty": (b"", "application/json", 400, "empty_body"),
    }  # fmt: skip


@pytest.mark.parametrize("case", list(_bad_cases()))
async def test_each_bad_capture_gets_its_status_and_code(server, case):
    body, content_type, status, code = _bad_cases()[case]
    async with http(server) as client:
        if content_type is None:
            response = await client.put("/v1/rigs/hero/performer/alice", json=body)
        else:
            response = await client.put(
                "/v1/rigs/hero/performer/alice",
                content=body,
                headers={"Content-Type": content_type},
            )
        stored = await client.get("/v1/rigs/hero@alice")

    assert (response.status_code, response.json()["code"]) == (status, code), response.text
    assert stored.status_code == 404  # nothing is stored from a refused capture


async def test_coinciding_expressions_are_named_in_the_refusal(server):
    points = performer_points()
    points["frown"] = points["smile"]
    async with http(server) as client:
        response = await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))

    detail = response.json()["detail"]
    assert "'smile'" in detail and "'frown'" in detail


async def test_a_huge_number_is_refused_as_non_finite(server):
    text = json.dumps(capture_body(performer_points()))
    first = text.index("[[") + 2
    end = text.index(",", first)
    body = (text[:first] + "1e400" + text[end:]).encode()
    async with http(server) as client:
        response = await client.put(
            "/v1/rigs/hero/performer/alice",
            content=body,
            headers={"Content-Type": "application/json"},
        )

    assert (response.status_code, response.json()["code"]) == (422, "non_finite")


@pytest.mark.parametrize(
    ("path", "status", "code"),
    [
        ("/v1/rigs/nobody/performer/alice", 404, "rig_not_found"),
        ("/v1/rigs/hero/performer/bad name", 400, "invalid_performer"),
        ("/v1/rigs/hero@bob/performer/alice", 400, "invalid_rig_id"),
        ("/v1/rigs/tiny/performer/alice", 422, "layout_mismatch"),
    ],
)
async def test_bad_rig_or_performer_in_the_path_is_refused(server, path, status, code):
    async with http(server) as client:
        response = await client.put(path, json=capture_body(performer_points()))

    assert (response.status_code, response.json()["code"]) == (status, code)


async def test_capture_over_the_size_limit_is_413(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_capture_bytes=1000)
    body = json.dumps(capture_body(performer_points())).encode()
    async with run_server(settings) as running, http(running) as client:
        running.app.state.store.put_rig("hero", fit(character()))
        response = await client.put(
            "/v1/rigs/hero/performer/alice",
            content=body,
            headers={"Content-Type": "application/json"},
        )

    assert len(body) > 1000
    assert (response.status_code, response.json()["code"]) == (413, "payload_too_large")


async def test_profile_is_refitted_onto_another_character_sharing_expression_names(server):
    points = performer_points()
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))
        profile = await client.get("/v1/performers/alice")
        refit = await client.post("/v1/performers/alice/refit", params={"rig": "other"})
        again = await client.post("/v1/performers/alice/refit", params={"rig": "other"})
        rig_file = await client.get("/v1/rigs/other@alice/rig")

    assert profile.json()["expressions"] == list(NAMES) and profile.json()["rig"] == "hero"
    assert (refit.status_code, again.status_code) == (201, 200)
    body = refit.json()
    assert body["id"] == "other@alice" and body["names"] == ["neutral", "jawOpen", "smile"]
    assert body["skipped"] == ["pout"]
    from facecast.rig import rig_from_bytes

    rig = rig_from_bytes(rig_file.content)
    weights = rig.weights(np.stack([points[n] for n in ("neutral", "jawOpen", "smile")]))
    np.testing.assert_allclose(weights, np.eye(3), atol=1e-8)


@pytest.mark.parametrize(
    ("request_args", "status", "code"),
    [
        (("POST", "/v1/performers/nobody/refit", {"rig": "other"}), 404, "performer_not_found"),
        (("GET", "/v1/performers/nobody", None), 404, "performer_not_found"),
        (("DELETE", "/v1/performers/nobody", None), 404, "performer_not_found"),
        (("POST", "/v1/performers/alice/refit", {"rig": "nobody"}), 404, "rig_not_found"),
        (("POST", "/v1/performers/alice/refit", {"rig": "tiny"}), 422, "layout_mismatch"),
        (("POST", "/v1/performers/alice/refit", {"rig": "x@y"}), 400, "invalid_rig_id"),
        (("GET", "/v1/performers/bad%20name", None), 400, "invalid_performer"),
    ],
)
async def test_bad_profile_requests_get_their_codes(server, request_args, status, code):
    method, path, params = request_args
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(performer_points()))
        response = await client.request(method, path, params=params)

    assert (response.status_code, response.json()["code"]) == (status, code)


async def test_refit_without_shared_expressions_is_refused(server):
    async with http(server) as client:
        points = performer_points()
        await client.put(
            "/v1/rigs/hero/performer/dan",
            json=capture_body({n: points[n] for n in ("neutral", "frown", "browUp")}),
        )
        response = await client.post("/v1/performers/dan/refit", params={"rig": "other"})

    assert (response.status_code, response.json()["code"]) == (422, "too_few_examples")


async def test_a_tampered_profile_is_refused_on_load(server, settings):
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(performer_points()))
        path = settings.rigs_dir / "performers" / "alice.json"
        doc = json.loads(path.read_text())
        doc["points"]["smile"] = doc["points"]["smile"][:3]
        path.write_text(json.dumps(doc))
        response = await client.post("/v1/performers/alice/refit", params={"rig": "other"})

    assert (response.status_code, response.json()["code"]) == (500, "bad_profile")


async def test_deleting_a_profile_keeps_its_rigs(server):
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(performer_points()))
        deleted = await client.delete("/v1/performers/alice")
        profile = await client.get("/v1/performers/alice")
        rig = await client.get("/v1/rigs/hero@alice")

    assert deleted.status_code == 204 and profile.status_code == 404
    assert rig.status_code == 200


async def test_performer_rig_id_is_streamable_and_listed(server):
    points = performer_points()
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))
        listed = await client.get("/v1/rigs")
    async with websockets.connect(f"{server.ws_url}/v1/stream", subprotocols=["facecast.v1"]) as ws:
        ready = await open_session(ws, "hero@alice")
        await ws.send(encode(Frame(seq=1, ts=0.0, points=points["jawOpen"].astype(np.float32))))
        result = decode_server(await ws.recv())

    assert "hero@alice" in [r["id"] for r in listed.json()["rigs"]]
    assert ready.rig == "hero@alice" and ready.names == NAMES
    assert isinstance(result, Result)
    assert int(np.argmax(result.weights)) == NAMES.index("jawOpen")


TOKENS = {
    "admin-token": frozenset({"admin"}),
    "performer-token": frozenset({"performer"}),
    "viewer-token": frozenset({"viewer"}),
    "publisher-token": frozenset({"publisher"}),
    "stream-token": frozenset({"stream"}),
}


@pytest.mark.parametrize(
    ("token", "status"),
    [
        (None, 401),
        ("viewer-token", 403),
        ("publisher-token", 403),
        ("stream-token", 403),
        ("performer-token", 201),
        ("admin-token", 201),
    ],
)
async def test_capture_needs_the_performer_or_admin_role(tmp_path, token, status):
    settings = Settings(rigs_dir=tmp_path / "rigs", auth=True, tokens=TOKENS)
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    async with run_server(settings) as running, http(running, headers=headers) as client:
        running.app.state.store.put_rig("hero", fit(character()))
        put = await client.put(
            "/v1/rigs/hero/performer/alice", json=capture_body(performer_points())
        )
        get = await client.get("/v1/performers/alice")
        refit = await client.post("/v1/performers/alice/refit", params={"rig": "hero"})

    assert put.status_code == status
    expected_get = 200 if status == 201 else status
    assert get.status_code == expected_get and refit.status_code in (
        (200,) if status == 201 else (status,)
    )


def _rigs_cli(*argv: str) -> int:
    import argparse

    from facecast.cli.commands import rigs

    parser = argparse.ArgumentParser(prog="facecast")
    rigs.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["rigs", *argv])
    return args.func(args)


async def test_rigs_capture_and_refit_commands_drive_the_endpoints(server, tmp_path, capsys):
    capture = tmp_path / "alice.json"
    capture.write_text(json.dumps(capture_body(performer_points())))
    _rigs_cli("capture", server.base_url, "hero", "alice", str(capture), "--noise", "0.02")
    captured = capsys.readouterr().out
    _rigs_cli("refit", server.base_url, "--performer", "alice", "--rig", "other")
    refitted = capsys.readouterr().out

    assert captured.startswith("fitted hero@alice: M=5 K=20 (skipped: none)")
    assert refitted.startswith("fitted other@alice: M=3 K=20 (skipped: pout)")
    assert server.app.state.store.get("hero@alice").fit_report["noise"] == 0.02


async def test_rigs_refit_shows_the_servers_code(server, capsys):
    from facecast.cli.errors import CommandError

    with pytest.raises(CommandError, match="performer_not_found"):
        _rigs_cli("refit", server.base_url, "--performer", "nobody", "--rig", "other")


async def test_a_performer_rig_publishes_to_a_channel_watched_on_another_character(server):
    import asyncio

    from facecast.client.channel import FramePublisher, channel_url, watch_channel
    from facecast.protocol import Hello, Ready

    points = performer_points()
    async with http(server) as client:
        await client.put("/v1/rigs/hero/performer/alice", json=capture_body(points))
    watch = channel_url(server.base_url, "stage", "watch", {"rig": "other"})
    publish = channel_url(server.base_url, "stage", "publish")
    seen: list = []
    ready = asyncio.Event()

    async def watcher():
        async for message in watch_channel(watch):
            seen.append(message)
            if isinstance(message, Ready):
                ready.set()
            if isinstance(message, Result):
                return

    task = asyncio.create_task(watcher())
    async with asyncio.timeout(20):
        await ready.wait()
        async with FramePublisher(publish, Hello(rig="hero@alice")) as publisher:
            assert publisher.ready.rig == "hero@alice"
            while not task.done():
                await publisher.send(points["jawOpen"].astype(np.float32), 0.0)
                await asyncio.sleep(0.05)
    result = next(m for m in seen if isinstance(m, Result))
    assert seen[0].rig == "other" and np.isfinite(result.weights).all()

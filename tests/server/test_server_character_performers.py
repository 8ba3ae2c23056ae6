"""A performer's calibration on an uploaded character, against a real uvicorn: the capture
makes ``{id}@{performer}``, whose weights on the performer's own expressions are theirs and
whose description carries the base character (issue #22: generic first, then personal)."""

from __future__ import annotations

import warnings

import httpx
import numpy as np
import pytest
import websockets
from _server_helpers import open_session

from facecast.protocol import Frame, Result, decode_server, encode
from facecast.rig import ExampleSet, fit, rig_from_bytes
from facecast.rig.characters.generic import (
    CHARACTER_FIT_DEFAULTS,
    VRM_COMPOSITIONS,
    generic_sources,
)
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

#: What the performer captures, by the character's names: ARKit shapes (the VRM 1.0
#: character's presets bind its ARKit morphs, so they are not its rig's) and, for the
#: VRoid-style ``fcl`` character, presets only (their sources are composed).
CAPTURED = {
    "vrm1": ("jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp"),
    "fcl": ("aa", "ou", "blinkLeft", "happy", "surprised"),
}


def performer_points(names, seed: int = 3) -> dict[str, np.ndarray]:
    """Another face than the generic set's making the expressions its own way: the generic
    neutral turned, scaled, moved and reshaped, each expression's displacement its own."""
    generic = generic_sources()
    rng = np.random.default_rng(seed)
    angle = np.radians(12.0)
    turn = np.array(
        [[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]
    )
    neutral_src = generic.points[0]
    neutral = 1.15 * (neutral_src + rng.normal(scale=0.15, size=neutral_src.shape)) @ turn.T
    neutral += np.array([2.0, -1.0, 30.0])
    points = {"neutral": neutral}
    for name in names:
        source = generic.source_points(name)
        assert source is not None, name
        delta = (source - neutral_src) * rng.uniform(0.8, 1.4)
        delta += rng.normal(scale=0.05, size=delta.shape)
        points[name] = neutral + 1.15 * delta @ turn.T
    return points


@pytest.mark.parametrize("variant", ["vrm1", "fcl"])
async def test_a_performer_calibrates_an_uploaded_character_into_their_own_rig(settings, variant):
    from tests.rig._avatars import avatar

    data = avatar(variant)
    names = CAPTURED[variant]
    points = performer_points(names)
    capture = {
        "layout": "mediapipe_face_mesh",
        "points": {n: p.tolist() for n, p in points.items()},
    }
    async with run_server(settings) as server:
        async with httpx.AsyncClient(base_url=server.base_url, timeout=120) as http:
            uploaded = await http.put("/v1/characters/ava", content=data)
            assert uploaded.status_code == 201, uploaded.text
            fitted = await http.put("/v1/rigs/ava/performer/ann", json=capture)
            assert fitted.status_code == 201, fitted.text
            described = (await http.get("/v1/rigs/ava@ann")).json()
            rig_file = await http.get("/v1/rigs/ava@ann/rig")
            served = await http.get("/v1/rigs/ava@ann/character.glb")
            base = rig_from_bytes((await http.get("/v1/rigs/ava/rig")).content)
        url = f"{server.ws_url}/v1/stream"
        async with websockets.connect(url, subprotocols=["facecast.v1"]) as ws:
            ready = await open_session(ws, "ava@ann")
            streamed = {}
            for seq, name in enumerate(names, start=1):
                frame = Frame(seq=seq, ts=seq / 30, points=points[name].astype(np.float32))
                await ws.send(encode(frame))
                result = decode_server(await ws.recv())
                assert isinstance(result, Result), result
                streamed[name] = np.asarray(result.weights)

    body = fitted.json()
    assert body["id"] == "ava@ann" and body["character"] == "ava"
    assert body["names"] == ["neutral", *[n for n in base.names if n in names]]
    assert set(body["skipped"]) == set(base.names[1:]) - set(names)
    rig = rig_from_bytes(rig_file.content)
    order = rig.names
    # The performer's own expressions give their own names' weights, one-hot, exactly.
    weights = rig.weights(np.stack([points[n] for n in order]))
    np.testing.assert_allclose(weights, np.eye(len(order)), atol=1e-6)
    # ... and the character's own shapes: the blend of that expression on the character.
    for name in names:
        one_hot = np.eye(len(base.names))[base.names.index(name)]
        np.testing.assert_allclose(rig.clone(points[name]), base.blend(one_hot), atol=1e-4)
    # Live through the stream: each frame of an expression gives that expression's weight.
    assert ready.names == tuple(order)
    for name, w in streamed.items():
        assert int(np.argmax(w)) == order.index(name), (name, w)
        assert w[order.index(name)] == pytest.approx(1.0, abs=0.02), (name, w)
    # The performer's rig carries the base character: its file and its bindings per weight.
    character = described["character"]
    assert character["format"] == {"fcl": "vrm0"}.get(variant, variant)
    assert character["url"] == "/v1/rigs/ava@ann/character.glb"
    assert len(character["bindings"]) == len(order)
    by_name = dict(zip(described["names"], character["bindings"], strict=True))
    assert by_name["neutral"] == [] and all(by_name[n] for n in names)
    assert served.status_code == 200 and served.content == data


async def test_a_character_uploaded_without_a_noise_is_fitted_for_a_live_tracker(settings):
    from tests.rig._avatars import avatar

    async with (
        run_server(settings) as server,
        httpx.AsyncClient(base_url=server.base_url, timeout=120) as http,
    ):
        uploaded = await http.put("/v1/characters/ava", content=avatar("arkit"))

    body = uploaded.json()
    assert uploaded.status_code == 201, body
    assert (body["noise"], body["clamp"]) == (
        CHARACTER_FIT_DEFAULTS["noise"],
        CHARACTER_FIT_DEFAULTS["clamp"],
    )


def generic_rig():
    """A rig with the generic set's ARKit names and points (its target: the points)."""
    generic = generic_sources()
    examples = ExampleSet(
        generic.names, generic.points, generic.points.copy(), np.array([[0, 1, 2]])
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # exact on 20 landmarks: the noise-gain advice
        return fit(examples)


async def test_a_calibration_on_an_arkit_rig_refits_onto_a_vroid_character_by_composing(
    settings,
):
    from tests.rig._avatars import avatar

    presets = ("happy", "aa", "blinkLeft")
    shapes = sorted({shape for p in presets for shape in VRM_COMPOSITIONS[p]})
    points = performer_points(shapes)
    capture = {
        "layout": "mediapipe_face_mesh",
        "points": {n: p.tolist() for n, p in points.items()},
    }
    async with run_server(settings) as server:
        server.app.state.store.put_rig("arkit", generic_rig())
        async with httpx.AsyncClient(base_url=server.base_url, timeout=120) as http:
            uploaded = await http.put("/v1/characters/vroid", content=avatar("fcl"))
            assert uploaded.status_code == 201, uploaded.text
            captured = await http.put("/v1/rigs/arkit/performer/ann", json=capture)
            assert captured.status_code == 201, captured.text
            refit = await http.post("/v1/performers/ann/refit", params={"rig": "vroid"})
            rig_file = await http.get("/v1/rigs/vroid@ann/rig")

    # The VRoid character has presets only: none was captured, three are composed from the
    # performer's own ARKit shapes by the generic set's rule (docs/characters.md).
    assert refit.status_code == 201, refit.text
    body = refit.json()
    base_names = uploaded.json()["names"]
    in_order = [n for n in base_names if n in presets]
    assert body["composed"] == in_order and body["names"] == ["neutral", *in_order]
    rig = rig_from_bytes(rig_file.content)
    neutral = points["neutral"]
    made = {
        p: neutral + sum(w * (points[s] - neutral) for s, w in VRM_COMPOSITIONS[p].items())
        for p in presets
    }
    weights = rig.weights(np.stack([neutral, *(made[n] for n in in_order)]))
    np.testing.assert_allclose(weights, np.eye(len(rig.names)), atol=1e-6)

"""Compressed characters through a real server: the ICT test avatar uploaded as meshopt,
quantised and Draco files (made at test time, tests/rig/_compressed.py) is accepted, paired
and fitted as its uncompressed twin and served as uploaded, still compressed; one that does
not decode is a named 422 and nothing is stored."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from facecast.rig.characters.generic import generic_sources
from facecast.rig.io.gltf import pack_glb
from facecast.rig.rigfile import rig_from_bytes
from facecast.server.testing import run_server
from tests.rig import _avatars
from tests.rig._compressed import GLTFPACK_MISSING, KINDS, compressed, gltfpack, split_glb

pytestmark = pytest.mark.anyio

FIT = {"noise": 0.05, "clamp": "unit"}


def client(server) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=120)


def generic_poses() -> np.ndarray:
    """The generic ARKit source's neutral and every expression's points."""
    generic = generic_sources()
    names = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "browInnerUp")
    return np.stack([generic.points[0], *(generic.source_points(n) for n in names)])


async def test_each_compressed_kind_is_paired_and_fitted_like_its_twin_and_served_compressed(
    settings,
):
    _avatars.require_ict()
    twin = _avatars.avatar("arkit")
    files = {"twin": twin, **{kind: compressed(twin, kind) for kind in KINDS}}
    async with run_server(settings) as server, client(server) as http:
        puts = {k: await http.put(f"/v1/characters/{k}", content=v, params=FIT) for k, v in files.items()}  # fmt: skip
        served = {k: (await http.get(f"/v1/rigs/{k}/character.glb")).content for k in files}
        rigs = {k: rig_from_bytes((await http.get(f"/v1/rigs/{k}/rig")).content) for k in files}
        models = {k: (await http.get(f"/v1/rigs/{k}/model.glb")).status_code for k in files}

    for kind, put in puts.items():
        assert put.status_code == 201, (kind, put.text)
    twin_pairing = puts["twin"].json()["pairing"]
    points = generic_poses()
    twin_weights = rigs["twin"].weights(points)
    assert twin_weights[1, rigs["twin"].names.index("jawOpen")] > 0.9  # the poses do drive it
    for kind in KINDS:
        body = puts[kind].json()
        assert body["pairing"]["paired"] == twin_pairing["paired"], kind
        assert body["names"] == puts["twin"].json()["names"]
        # Stored and served as uploaded: viewers get the compressed file.
        assert served[kind] == files[kind]
        assert kind.replace("quantized", "mesh_quantization") in json_of(served[kind]), kind
        np.testing.assert_allclose(rigs[kind].weights(points), twin_weights, atol=1e-6)
        assert rigs[kind].num_vertices == rigs["twin"].num_vertices
        assert models[kind] == 200


def json_of(glb: bytes) -> str:
    return str(split_glb(glb)[0].get("extensionsRequired"))


async def test_a_compressed_file_that_does_not_decode_is_a_named_422_and_nothing_is_stored(
    settings,
):
    _avatars.require_ict()
    doc, blob = split_glb(compressed(_avatars.avatar("arkit"), "draco"))
    view = doc["bufferViews"][
        doc["meshes"][0]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]["bufferView"]
    ]
    broken = bytearray(blob)
    at = view["byteOffset"] + 16
    broken[at : at + 64] = bytes(range(64))

    async with run_server(settings) as server, client(server) as http:
        put = await http.put("/v1/characters/broken", content=pack_glb(doc, bytes(broken)))
        listed = (await http.get("/v1/rigs")).json()
        described = await http.get("/v1/rigs/broken")

    assert put.status_code == 422 and put.json()["code"] == "bad_compression", put.text
    assert "Draco" in put.json()["detail"] and str(settings.rigs_dir) not in put.text
    assert listed["rigs"] == [] and described.status_code == 404
    assert not list(settings.rigs_dir.glob("broken*"))


@pytest.mark.skipif(GLTFPACK_MISSING is not None, reason=str(GLTFPACK_MISSING))
async def test_a_file_packed_by_gltfpack_is_paired_and_fitted_like_its_twin(settings):
    _avatars.require_ict()
    twin = _avatars.avatar("arkit")
    packed = gltfpack(twin)
    async with run_server(settings) as server, client(server) as http:
        puts = {k: await http.put(f"/v1/characters/{k}", content=v, params=FIT) for k, v in (("twin", twin), ("packed", packed))}  # fmt: skip
        served = (await http.get("/v1/rigs/packed/character.glb")).content
        rigs = {k: rig_from_bytes((await http.get(f"/v1/rigs/{k}/rig")).content) for k in puts}

    assert puts["packed"].status_code == 201, puts["packed"].text
    assert puts["packed"].json()["pairing"]["paired"] == puts["twin"].json()["pairing"]["paired"]
    assert served == packed
    points = generic_poses()
    np.testing.assert_allclose(
        rigs["packed"].weights(points), rigs["twin"].weights(points), atol=1e-6
    )

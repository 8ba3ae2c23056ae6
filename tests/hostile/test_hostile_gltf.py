"""Hostile glTF/GLB uploads (issue #31 part A): sizes declared in a few bytes, node graphs
that are not trees, URIs leaving the file, wrongly typed fields.

Each body is a tiny GLB written with struct and json (``_glb``), sent to a real server on both
upload paths (a character with expressions, and a transfer job's): every one is refused
with a named 4xx before anything is allocated for it, nothing is stored, and the server's
peak memory (VmHWM, reset before each upload) hardly moves.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from facecast.rig.io.gltf_check import max_decoded_bytes
from facecast.rig.sources.ict import locate_ict
from facecast.server.http.character_upload import gltf_limits
from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.hostile._glb import aliased, glb, meshopt_zeros, triangle, zeros
from tests.viewer._character import build_character

pytestmark = pytest.mark.anyio

MiB = 1 << 20


def zeros_position(count: int) -> bytes:
    """The issue's 396-byte body: POSITION (and its morph) without a bufferView, ``count``
    vertices of zeros."""
    doc, _ = triangle()
    doc.pop("buffers"), doc.pop("bufferViews")
    for accessor in doc["accessors"]:
        accessor.pop("bufferView")
        accessor["count"] = count
    return glb(doc)


def edited(edit) -> bytes:
    doc, blob = triangle()
    edit(doc)
    return glb(doc, blob)


def zero_indices(count: int) -> Any:
    def edit(doc: dict[str, Any]) -> None:
        doc["accessors"].append({"componentType": 5125, "count": count, "type": "SCALAR"})
        doc["meshes"][0]["primitives"][0]["indices"] = 2

    return edit


def many_targets(doc: dict[str, Any]) -> None:
    # 5,000 targets of 3 vertices, each an accessor of zeros declaring 2,000 vertices.
    doc["accessors"][0]["count"] = 3
    doc["accessors"].append({"componentType": 5126, "count": 3, "type": "VEC3"})
    doc["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": 2}] * 5000


def nodes(count: int) -> Any:
    return lambda doc: doc.update(nodes=[{"mesh": 0}] + [{} for _ in range(count - 1)])


def chain(depth: int) -> Any:
    def edit(doc: dict[str, Any]) -> None:
        doc["nodes"] = [{"children": [i + 1]} for i in range(depth - 1)] + [{"mesh": 0}]

    return edit


#: Bodies declaring more than a default ``max_gltf_*`` allows: (body, the setting named).
OVER_LIMITS = {
    "33M zero vertices": (zeros_position(33_300_000), "max_gltf_accessor_values"),
    "2M zero vertices": (zeros_position(2_000_000), "max_gltf_vertices"),
    "99,999,999 indices": (edited(zero_indices(99_999_999)), "max_gltf_accessor_values"),
    "2M + 1 triangles": (edited(zero_indices(6_000_003)), "max_gltf_faces"),
    "5000 morph targets": (edited(many_targets), "max_gltf_morph_targets"),
    "200,000 nodes": (edited(nodes(200_000)), "max_gltf_nodes"),
    "a 20,000-deep chain": (edited(chain(20_000)), "max_gltf_depth"),
    "[{},{},...] JSON": (
        glb({"asset": {"version": "2.0"}, "extras": [{}] * 2_000_000}),
        "max_gltf_json_values",
    ),
}


def _second_mesh_on(uri: str) -> Any:
    """A second mesh whose POSITION lies in buffer 1 (or 0) named by ``uri``."""

    def edit(doc: dict[str, Any]) -> None:
        doc["buffers"].append({"byteLength": 36, "uri": uri})
        doc["bufferViews"].append({"buffer": 1, "byteLength": 36})
        doc["accessors"].append(
            {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC3"}
        )
        doc["meshes"].append({"primitives": [{"attributes": {"POSITION": 2}}]})
        doc["nodes"].append({"mesh": 1})
        doc["scenes"][0]["nodes"].append(1)

    return edit


def _buffer_zero_uri(doc: dict[str, Any]) -> None:
    # The body: a BIN chunk, yet buffers[0] also names a URL a second mesh uses.
    doc["buffers"][0]["uri"] = "http://127.0.0.1:9/steal.bin"
    doc["buffers"][0]["byteLength"] = 108
    doc["bufferViews"].append({"buffer": 0, "byteOffset": 72, "byteLength": 36})
    doc["accessors"].append({"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC3"})
    doc["meshes"].append({"primitives": [{"attributes": {"POSITION": 2}}]})
    doc["nodes"].append({"mesh": 1})


#: Malformed bodies: (edit of the triangle, the code, a phrase of the detail).
MALFORMED = {
    "buffer 0 with a BIN chunk and a URL": (_buffer_zero_uri, "external_uri", "127.0.0.1:9"),
    "buffer 1 a URL": (_second_mesh_on("https://example.com/b.bin"), "external_uri", "example"),
    "an image URL": (
        lambda doc: doc.update(images=[{"uri": "http://example.com/skin.png"}]),
        "external_uri",
        "skin.png",
    ),
    "a URI in an extension": (
        lambda doc: doc.update(extensions={"KHR_audio": {"audio": [{"uri": "//x.example/a"}]}}),
        "external_uri",
        "x.example",
    ),
    "buffer 0 with a BIN chunk and a data URI": (
        lambda doc: doc["buffers"][0].update(uri="data:application/octet-stream;base64,AAAA"),
        "bad_gltf",
        "BIN chunk",
    ),
    "bufferView byteLength 2^40": (
        lambda doc: doc["bufferViews"][0].update(byteLength=2**40),
        "bad_gltf",
        "bufferView 0",
    ),
    "count as a string": (
        lambda doc: doc["accessors"][0].update(count="3"),
        "bad_gltf",
        "not an integer",
    ),
    "accessor past its view": (
        lambda doc: doc["accessors"][1].update(byteOffset=4),
        "bad_gltf",
        "runs past its bufferView",
    ),
    "nodes 0 <-> 1": (
        lambda doc: doc.update(nodes=[{"mesh": 0, "children": [1]}, {"children": [0]}]),
        "bad_gltf",
        "tree",
    ),
    "a self-loop": (
        lambda doc: doc.update(nodes=[{"mesh": 0}, {"children": [1]}]),
        "bad_gltf",
        "tree",
    ),
    "a node with two parents": (
        lambda doc: doc.update(nodes=[{"mesh": 0}, {"children": [0]}, {"children": [0]}]),
        "bad_gltf",
        "two parents",
    ),
    "weights not a list": (
        lambda doc: doc["nodes"][0].update(weights=5),
        "bad_gltf",
        "weights",
    ),
}


def client(server) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=60)


def reset_peak() -> int:
    """Reset this process's peak RSS (the server runs in it) and return the current RSS."""
    Path("/proc/self/clear_refs").write_text("5")
    return _status("VmRSS")


def _status(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no {field} in /proc/self/status")


async def test_declared_sizes_over_the_limits_are_refused_before_anything_is_allocated(
    tmp_path,
):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    async with run_server(settings) as server, client(server) as http:
        answers = {}
        for name, (body, _) in OVER_LIMITS.items():
            before = reset_peak()
            started = time.perf_counter()
            response = await http.put("/v1/characters/hostile", content=body)
            seconds = time.perf_counter() - started
            answers[name] = (response, seconds, _status("VmHWM") - before, len(body))
        listed = (await http.get("/v1/rigs")).json()

    for name, (response, seconds, grown, size) in answers.items():
        problem = response.json()
        assert (response.status_code, problem["code"]) == (422, "gltf_exceeds_limits"), (
            name,
            problem,
        )
        assert OVER_LIMITS[name][1] in problem["detail"], (name, problem)
        # Refused from what the file declares: time and memory of the order of its bytes
        # (the 33 M vertices took 4.7 GB and 15 s; 200,000 nodes took minutes).
        assert seconds < 5, (name, seconds)
        assert grown < 64 * MiB + 20 * size, (name, grown / MiB)
    assert listed["rigs"] == []
    assert not list(settings.rigs_dir.glob("*.character"))


async def test_a_file_at_the_node_limit_is_read_in_linear_time(tmp_path):
    # pygltflib's objects cost ~0.33 ms a node, twice per upload: 20,000 took 14 s.
    body = edited(nodes(20_000))
    settings = Settings(rigs_dir=tmp_path / "rigs")
    async with run_server(settings) as server, client(server) as http:
        started = time.perf_counter()
        response = await http.put("/v1/characters/many", content=body)
        seconds = time.perf_counter() - started

    assert response.status_code == 201, response.json()
    assert seconds < 5, seconds


async def test_malformed_declarations_are_refused_with_a_code_and_nothing_stored(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    async with run_server(settings) as server, client(server) as http:
        answers = {
            name: await http.put("/v1/characters/hostile", content=edited(edit))
            for name, (edit, _, _) in MALFORMED.items()
        }
        listed = (await http.get("/v1/rigs")).json()

    for name, (_, code, phrase) in MALFORMED.items():
        problem = answers[name].json()
        assert (answers[name].status_code, problem["code"]) == (422, code), (name, problem)
        assert phrase in problem["detail"], (name, problem)
    assert listed["rigs"] == []


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
async def test_the_transfer_path_refuses_the_same_before_any_job(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    transfer = {"expressions": "transfer"}
    async with run_server(settings) as server, client(server) as http:
        before = reset_peak()
        started = time.perf_counter()
        zeros = await http.put(
            "/v1/characters/hostile", params=transfer, content=zeros_position(33_300_000)
        )
        seconds = time.perf_counter() - started
        grown = _status("VmHWM") - before
        faces = await http.put(
            "/v1/characters/hostile", params=transfer, content=edited(zero_indices(6_000_003))
        )
        cycle = await http.put(
            "/v1/characters/hostile", params=transfer, content=edited(MALFORMED["nodes 0 <-> 1"][0])
        )
        job = await http.get("/v1/characters/hostile/job")

    assert (zeros.status_code, zeros.json()["code"]) == (422, "gltf_exceeds_limits")
    assert (faces.status_code, faces.json()["code"]) == (422, "gltf_exceeds_limits")
    assert "max_gltf_faces" in faces.json()["detail"]
    assert (cycle.status_code, cycle.json()["code"]) == (422, "bad_gltf")
    assert (job.status_code, job.json()["code"]) == (404, "no_job")  # no job ever existed
    assert seconds < 5 and grown < 64 * MiB, (seconds, grown / MiB)


def declared(doc: dict[str, Any], text: bytes) -> dict[str, int]:
    """What a document declares, counted as ``GltfLimits`` documents each limit."""
    sizes = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
    accessors = doc["accessors"]
    children = {c for node in doc["nodes"] for c in node.get("children", [])}
    level = [i for i in range(len(doc["nodes"])) if i not in children]
    depth = 0
    while level:
        depth += 1
        level = [c for i in level for c in doc["nodes"][i].get("children", [])]
    prims = [p for mesh in doc["meshes"] for p in mesh["primitives"]]
    per_mesh = [{p["attributes"]["POSITION"] for p in mesh["primitives"]} for mesh in doc["meshes"]]
    targets = [max(len(p.get("targets", [])) for p in m["primitives"]) for m in doc["meshes"]]
    quantised = [
        any(accessors[t["POSITION"]]["componentType"] != 5126 for p in m["primitives"]
            for t in p.get("targets", []))
        for m in doc["meshes"]
    ]  # fmt: skip
    return {
        "json_values": sum(text.count(c) for c in (b"[", b",", b":", b"{")) + 1,
        "nodes": len(doc["nodes"]),
        "depth": depth,
        "meshes": len(doc["meshes"]),
        "primitives": len(prims),
        "vertices": sum(accessors[i]["count"] for i in set().union(*per_mesh)),
        "faces": sum(
            (accessors[p["indices"]]["count"] if "indices" in p else 0) // 3 for p in prims
        ),
        "morph_targets": max(targets),
        "morph_values": sum(
            t * sum(accessors[i]["count"] for i in used) * (2 if quantised else 1)
            for t, used, quantised in zip(targets, per_mesh, quantised, strict=True)
        ),
        "accessor_values": sum(a["count"] * sizes[a["type"]] for a in accessors),
    }


async def test_each_limit_is_its_setting_at_the_limit_and_one_past(tmp_path):
    body = build_character("gltf").glb
    (length,) = struct.unpack_from("<I", body, 12)
    text = body[20 : 20 + length]
    exact = {f"max_gltf_{k}": v for k, v in declared(json.loads(text), text).items()}
    at_limit = Settings(rigs_dir=tmp_path / "rigs", **exact)
    async with run_server(at_limit) as server, client(server) as http:
        stored = await http.put("/v1/characters/ok", content=body)
    past = {}
    for name, value in exact.items():
        one_past = Settings(rigs_dir=tmp_path / name, **{**exact, name: value - 1})
        async with run_server(one_past) as server, client(server) as http:
            past[name] = await http.put("/v1/characters/ok", content=body)

    assert stored.status_code == 201, stored.json()
    for name, response in past.items():
        problem = response.json()
        assert (response.status_code, problem["code"]) == (422, "gltf_exceeds_limits"), name
        assert name in problem["detail"], (name, problem)


def mixing_expressions(count: int) -> bytes:
    """A VRM 1.0 triangle with ``count`` expressions each binding its morph at 0.5: every
    one needs a face-sized array of its own."""

    def edit(doc: dict[str, Any]) -> None:
        binds = [{"node": 0, "index": 0, "weight": 0.5}]
        custom = {f"half{i}": {"morphTargetBinds": binds} for i in range(count)}
        doc["extensions"] = {"VRMC_vrm": {"specVersion": "1.0", "expressions": {"custom": custom}}}

    return edited(edit)


async def test_expressions_mixing_morphs_are_bounded_as_morph_values(tmp_path):
    # The triangle's 3 vertices: its morph is 3 values, and each mixing expression a float64
    # copy of the face that counts twice, 6: with 10 of them 63 values, with 11, 69.
    settings = Settings(rigs_dir=tmp_path / "rigs", max_gltf_morph_values=63)
    async with run_server(settings) as server, client(server) as http:
        at_limit = await http.put("/v1/characters/mix", content=mixing_expressions(10))
        past = await http.put("/v1/characters/mix", content=mixing_expressions(11))

    assert at_limit.status_code == 201, at_limit.json()  # its jawOpen morph is fitted
    assert (past.status_code, past.json()["code"]) == (422, "gltf_exceeds_limits")
    assert "max_gltf_morph_values" in past.json()["detail"]


async def test_quantised_morph_targets_count_twice_as_morph_values(tmp_path):
    # Read as float64 (so that the rig is what the file says), a quantised morph value
    # costs what two float32 ones do: 4 int16 targets on 999 vertices are 7,992 values.
    body = zeros(999, 4, quantized=True)
    at = Settings(rigs_dir=tmp_path / "at", max_gltf_morph_values=7_992)
    past = Settings(rigs_dir=tmp_path / "past", max_gltf_morph_values=7_991)
    async with run_server(at) as server, client(server) as http:
        stored = await http.put("/v1/characters/q", content=body)
    async with run_server(past) as server, client(server) as http:
        refused = await http.put("/v1/characters/q", content=body)

    assert stored.status_code == 201, stored.json()
    assert (refused.status_code, refused.json()["code"]) == (422, "gltf_exceeds_limits")
    assert "max_gltf_morph_values" in refused.json()["detail"]


async def test_expressions_aliasing_one_morph_are_bounded_as_morph_values(tmp_path):
    # Each ARKit-named VRM expression binds the one morph at weight 1: no array of its own
    # when read, but a copy of the face in the fit (a 1 M-vertex face: 1.6 GB for 46 MB).
    # 2,500 vertices: 10 paired expressions are 25,000 values, 11 are 27,500.
    settings = Settings(rigs_dir=tmp_path / "rigs", max_gltf_morph_values=25_000)
    async with run_server(settings) as server, client(server) as http:
        at_limit = await http.put("/v1/characters/alias", content=aliased(2_500, 10))
        past = await http.put("/v1/characters/alias", content=aliased(2_500, 11))

    assert at_limit.status_code == 201, at_limit.json()
    assert len(at_limit.json()["names"]) == 11  # the neutral and the 10 expressions
    assert (past.status_code, past.json()["code"]) == (422, "gltf_exceeds_limits"), past.json()
    assert "11 expressions paired" in past.json()["detail"]
    assert "max_gltf_morph_values" in past.json()["detail"]


async def test_a_meshopt_view_at_the_decode_limit_is_held_once(tmp_path):
    # 1 MB of meshopt stream decode to max_gltf_accessor_values x 4 bytes of zeros (64 MB
    # here, 128 MB at the defaults), all read by an accessor no mesh uses: the reader
    # checks that view and lets it go, and never copies the decoder's array. Copied and kept, the
    # default's took +493 MB.
    settings = Settings(rigs_dir=tmp_path / "rigs", max_gltf_accessor_values=16_000_000)
    decoded = max_decoded_bytes(gltf_limits(settings)) // 16 * 16
    body = meshopt_zeros(decoded)
    size = len(body)
    async with run_server(settings) as server, client(server) as http:
        before = reset_peak()
        response = await http.put("/v1/characters/zeros", content=body)
        grown = _status("VmHWM") - before

    assert response.status_code == 201, response.json()
    assert size < decoded / 50
    # The view once, the body, and less than half the view besides (a triangle's fit).
    assert grown < decoded + size + 32 * MiB, grown / MiB


async def test_a_meshopt_view_decoding_more_than_its_accessors_read_is_refused_undecoded(tmp_path):
    # Within the document's decode budget, 1 MB of meshopt stream declare 64 MB of zeros
    # that one accessor of 3 values reads 33 bytes of: before issue 31's per-view bound
    # it was stored (201), the view decoded (+64 MB) for nothing.
    settings = Settings(rigs_dir=tmp_path / "rigs")
    decoded = 64 * MiB
    assert decoded < max_decoded_bytes(gltf_limits(settings))
    body = meshopt_zeros(decoded, read_rows=3)
    async with run_server(settings) as server, client(server) as http:
        before = reset_peak()
        response = await http.put("/v1/characters/zeros", content=body)
        grown = _status("VmHWM") - before

    assert (response.status_code, response.json()["code"]) == (422, "bad_compression")
    assert "decodes to 67108864 bytes" in response.json()["detail"]
    assert "its accessors read 33 of them" in response.json()["detail"]
    assert grown < decoded / 4, grown / MiB  # refused before the decoder ran

"""The /v1 rig API against a real uvicorn: CRUD, fitting uploads and every bad upload."""

from __future__ import annotations

import asyncio
import dataclasses
import io
import shutil
import time
import zipfile

import httpx
import numpy as np
import pytest
from _server_helpers import (
    errors_logged,
    folder_members,
    server_logs,
    tar_bytes,
    tiny_example_set,
    wait_until,
    write_example_folder,
    zip_bytes,
)

from facecast.rig import fit, rig_from_bytes
from facecast.server.app import create_app
from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio


def client(server) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=server.base_url, timeout=30)


async def wait_for_record(records, event: str, timeout: float = 10.0) -> None:
    """Wait until the server (in its own thread) has logged ``event``."""
    deadline = time.monotonic() + timeout
    while not any(getattr(r, "event", None) == event for r in records):
        assert time.monotonic() < deadline, f"no {event} logged"
        await asyncio.sleep(0.01)


async def test_put_then_get_list_download_delete_round_trip(settings, rig):
    async with run_server(settings) as server, client(server) as http:
        put = await http.put("/v1/rigs/face-1", content=rig.to_bytes())
        listed = await http.get("/v1/rigs")
        meta = await http.get("/v1/rigs/face-1")
        downloaded = await http.get("/v1/rigs/face-1/rig")
        deleted = await http.delete("/v1/rigs/face-1")
        after = await http.get("/v1/rigs/face-1")

    assert put.status_code == 201 and put.json()["checksum"] == rig.checksum
    assert [r["id"] for r in listed.json()["rigs"]] == ["face-1"]
    assert meta.json() == {"id": "face-1", **rig.summary()}
    assert rig_from_bytes(downloaded.content).checksum == rig.checksum
    assert deleted.status_code == 204
    assert after.status_code == 404 and after.json()["code"] == "rig_not_found"


async def test_replacing_a_rig_answers_200_and_serves_the_new_one(settings, rig):
    other = fit(tiny_example_set(seed=7))
    async with run_server(settings) as server, client(server) as http:
        first = await http.put("/v1/rigs/face", content=rig.to_bytes())
        await http.get("/v1/rigs/face")  # load it into the cache
        second = await http.put("/v1/rigs/face", content=other.to_bytes())
        meta = await http.get("/v1/rigs/face")

    assert (first.status_code, second.status_code) == (201, 200)
    assert meta.json()["checksum"] == other.checksum


async def test_model_glb_has_a_morph_target_per_example_but_the_neutral(settings, rig):
    import pygltflib

    async with run_server(settings) as server, client(server) as http:
        await http.put("/v1/rigs/face", content=rig.to_bytes())
        response = await http.get("/v1/rigs/face/model.glb")

    assert response.headers["content-type"] == "model/gltf-binary"
    gltf = pygltflib.GLTF2.load_from_bytes(response.content)
    # The neutral's target would move nothing; every other carries normals too.
    targets = gltf.meshes[0].primitives[0].targets
    assert gltf.meshes[0].extras["targetNames"] == list(rig.names[1:])
    assert len(targets) == rig.num_examples - 1
    assert all(set(target) == {"POSITION", "NORMAL"} for target in targets)


@pytest.mark.parametrize("kind", ["zip", "tar", "tar.gz", "zip-with-top-folder"])
async def test_examples_archive_is_fitted_server_side_like_fit(settings, tmp_path, kind):
    example_set = write_example_folder(tmp_path / "set")
    members = folder_members(tmp_path / "set", "face/" if kind.endswith("folder") else "")
    body = zip_bytes(members) if kind.startswith("zip") else tar_bytes(members, gz=kind == "tar.gz")
    expected = fit(example_set, noise=0.01)
    points = expected.source_neutral + 0.05

    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/fitted/examples", params={"noise": 0.01}, content=body)
        stored = server.app.state.store.get("fitted")

    assert response.status_code == 201, response.text
    assert response.json()["names"] == list(example_set.names)
    np.testing.assert_allclose(stored.weights(points), expected.weights(points), atol=1e-5)


async def test_fit_error_in_examples_is_422_with_the_engine_code(settings, tmp_path):
    es = tiny_example_set()
    # Two identical key-expressions cannot be told apart.
    source = es.source_points.copy()
    source[2] = source[1]
    write_example_folder(
        tmp_path / "set",
        type(es)(es.names, source, es.target_vertices, es.target_faces),
    )
    body = zip_bytes(folder_members(tmp_path / "set"))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/bad/examples", content=body)

    assert response.status_code == 422
    assert response.json()["code"] == "examples_coincide"


async def test_unknown_kernel_is_422(settings, tmp_path):
    write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/k/examples", params={"kernel": "nope"}, content=body)

    assert response.status_code == 422 and response.json()["code"]


async def test_examples_fitted_with_clamp_nonneg_keep_the_bound_and_nonnegative_weights(
    settings, tmp_path
):
    example_set = write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))
    expected = fit(example_set, noise=0.05, clamp="nonneg")
    points = expected.source_neutral + np.random.default_rng(4).normal(
        scale=0.3, size=(64, *expected.source_neutral.shape)
    )

    async with run_server(settings) as server, client(server) as http:
        response = await http.put(
            "/v1/rigs/bounded/examples",
            params={"noise": 0.05, "clamp": "nonneg"},
            content=body,
        )
        meta = await http.get("/v1/rigs/bounded")
        stored = server.app.state.store.get("bounded")

    assert response.status_code == 201, response.text
    assert response.json()["clamp"] == meta.json()["clamp"] == "nonneg"
    assert stored.fit_report["clamp"] == "nonneg" and stored.fit_report["sparsity"] == 0.0
    weights = stored.weights(points)
    assert weights[:, 1:].min() >= 0.0
    np.testing.assert_allclose(weights, expected.weights(points), atol=1e-6)


async def test_examples_fitted_with_a_sparsity_setting_store_its_penalty(settings, tmp_path):
    example_set = write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))
    expected = fit(example_set, noise=0.05, clamp="unit", sparsity=0.5)

    async with run_server(settings) as server, client(server) as http:
        response = await http.put(
            "/v1/rigs/sparse/examples",
            params={"noise": 0.05, "clamp": "unit", "sparsity": 0.5},
            content=body,
        )
        stored = server.app.state.store.get("sparse")

    assert response.status_code == 201, response.text
    assert stored.fit_report["sparsity"] == 0.5
    assert stored.model.sparsity_penalty == expected.model.sparsity_penalty > 0


@pytest.mark.parametrize(
    "params,code,match",
    [
        ({"clamp": "yes"}, "invalid_request", "clamp"),
        ({"clamp": "nonneg", "sparsity": -1}, "invalid_request", "sparsity"),
        ({"clamp": "nonneg", "sparsity": "inf"}, "invalid_request", "sparsity"),
        ({"sparsity": 1}, "sparsity_without_clamp", "clamp"),
    ],
)
async def test_bad_clamp_or_sparsity_is_422_naming_it_and_stores_nothing(
    settings, tmp_path, params, code, match
):
    write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/bad/examples", params=params, content=body)
        listed = await http.get("/v1/rigs")

    assert (response.status_code, response.json()["code"]) == (422, code)
    assert match in response.json()["detail"]
    assert listed.json()["rigs"] == []


@pytest.mark.filterwarnings("ignore::facecast.rig.IdentifiabilityWarning")
async def test_fit_warnings_are_returned_to_the_uploader(settings, tmp_path):
    es = tiny_example_set()
    source = es.source_points.copy()
    source[3] = source[2] + 1e-3  # 'jaw' nearly collapses onto 'frown'
    write_example_folder(
        tmp_path / "set", type(es)(es.names, source, es.target_vertices, es.target_faces)
    )
    body = zip_bytes(folder_members(tmp_path / "set"))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/near/examples", content=body)

    assert response.status_code == 201, response.text
    assert any("collapse" in message for message in response.json()["warnings"])


@pytest.mark.parametrize("kind", ["examples", "rig"])
async def test_max_pending_fits_counts_an_upload_from_before_its_body_is_read(tmp_path, rig, kind):
    # Issue 13, item 5: checked before the body, counted after it, so uploads sent together
    # all passed the check (10 at once: no 503, 330 MB more RSS). Raw rig uploads took no
    # slot at all.
    settings = Settings(rigs_dir=tmp_path / "rigs", max_pending_fits=1)
    if kind == "examples":
        write_example_folder(tmp_path / "set")
        body, suffix = zip_bytes(folder_members(tmp_path / "set")), "/examples"
    else:
        body, suffix = rig.to_bytes(), ""
    release = asyncio.Event()

    async def slow_body():
        yield body[:100]
        await release.wait()
        yield body[100:]

    async with run_server(settings) as server, client(server) as http:
        first = asyncio.create_task(http.put(f"/v1/rigs/first{suffix}", content=slow_body()))
        await wait_until(lambda: server.app.state.pending_fits == 1)
        second = await http.put(f"/v1/rigs/second{suffix}", content=body)
        release.set()
        first_response = await first
        third = await http.put(f"/v1/rigs/third{suffix}", content=body)

    assert (second.status_code, second.json()["code"]) == (503, "server_busy")
    assert second.headers["retry-after"] == "5"
    assert first_response.status_code == third.status_code == 201


async def test_a_trickled_body_is_cut_with_408_and_gives_its_slot_back(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_pending_fits=1, body_timeout=0.5)
    write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))

    async with run_server(settings) as server, client(server) as http:
        # A raw client: httpx would not read the answer before its body is sent.
        reader, writer = await asyncio.open_connection(server.host, server.port)
        head = (
            f"PUT /v1/rigs/slow/examples HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            f"Content-Type: application/zip\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        writer.write(head.encode() + body[:100])  # the rest never comes
        status_line = await asyncio.wait_for(reader.readline(), 10)
        answer = await asyncio.wait_for(reader.read(), 10)  # to the close
        writer.close()
        await wait_until(lambda: server.app.state.pending_fits == 0)
        after = await http.put("/v1/rigs/next/examples", content=body)

    assert status_line.split()[1] == b"408"
    assert b'"body_timeout"' in answer
    assert after.status_code == 201


# -- bad uploads --------------------------------------------------------------------------


def _bad_archives(tmp_path) -> dict[str, tuple[bytes, int, str]]:
    write_example_folder(tmp_path / "set")
    good = folder_members(tmp_path / "set")
    symlink = io.BytesIO()
    with zipfile.ZipFile(symlink, "w") as archive:
        info = zipfile.ZipInfo("facecast.toml")
        info.external_attr = (0o120777) << 16  # a symlink
        archive.writestr(info, "/etc/passwd")
    return {
        "zip-traversal": (zip_bytes({**good, "../evil.txt": b"x"}), 400, "unsafe_archive_member"),
        "zip-absolute": (zip_bytes({**good, "/tmp/evil": b"x"}), 400, "unsafe_archive_member"),
        "tar-traversal": (
            tar_bytes({**good, "a/../../evil": b"x"}, gz=True),
            400,
            "unsafe_archive_member",
        ),
        "zip-symlink": (symlink.getvalue(), 400, "unsafe_archive_member"),
        "zip-bomb": (zip_bytes({"bomb.bin": bytes(50_000_000)}), 413, "archive_ratio"),
        "tar-bomb": (tar_bytes({"bomb.bin": bytes(50_000_000)}, gz=True), 413, "archive_ratio"),
        "not-an-archive": (b"hello, world" * 100, 415, "unsupported_archive"),
        "truncated-zip": (zip_bytes(good)[:200], 400, "bad_archive"),
        "no-manifest": (zip_bytes({"readme.txt": b"hi"}), 422, "bad_example_set"),
        # Issue 13, item 7: these were 500s with a traceback.
        "zip-long-name": (zip_bytes({**good, "n" * 256: b"x"}), 400, _TOO_LONG),
        "tar-long-name": (tar_bytes({**good, "n" * 256: b"x"}, gz=True), 400, _TOO_LONG),
        "zip-deep-path": (zip_bytes({**good, _DEEP: b"x"}), 400, _TOO_LONG),
        "tar-deep-path": (tar_bytes({**good, _DEEP: b"x"}, gz=False), 400, _TOO_LONG),
        "zip-file-then-folder": (zip_bytes({**good, "x": b"1", "x/y": b"2"}), 400, _CLASH),
        "tar-file-then-folder": (tar_bytes({**good, "x": b"1", "x/y": b"2"}, gz=True), 400, _CLASH),
        "zip-folder-then-file": (zip_bytes({**good, "x/y": b"2", "x": b"1"}), 400, _CLASH),
    }


_TOO_LONG = "archive_member_name_too_long"
_CLASH = "archive_member_conflict"
#: Deeper than PATH_MAX (4096 bytes), each name within NAME_MAX (255).
_DEEP = "/".join(["d" * 200] * 25) + "/f"


@pytest.mark.parametrize(
    "case",
    [
        "zip-traversal",
        "zip-absolute",
        "tar-traversal",
        "zip-symlink",
        "zip-bomb",
        "tar-bomb",
        "not-an-archive",
        "truncated-zip",
        "no-manifest",
        "zip-long-name",
        "tar-long-name",
        "zip-deep-path",
        "tar-deep-path",
        "zip-file-then-folder",
        "tar-file-then-folder",
        "zip-folder-then-file",
    ],
)
async def test_bad_archive_is_refused_with_its_code_and_writes_nothing(settings, tmp_path, case):
    body, status, code = _bad_archives(tmp_path)[case]
    async with run_server(settings) as server, client(server) as http:
        with server_logs() as records:
            response = await http.put("/v1/rigs/evil/examples", content=body)
        listed = await http.get("/v1/rigs")

    assert (response.status_code, response.json()["code"]) == (status, code), response.text
    assert listed.json()["rigs"] == []
    assert not (tmp_path / "evil.txt").exists()
    assert errors_logged(records) == []


@pytest.mark.parametrize("clamp", [None, "unit"])
async def test_absurd_noise_is_422_naming_it_not_a_500(settings, tmp_path, clamp):
    write_example_folder(tmp_path / "set")
    body = zip_bytes(folder_members(tmp_path / "set"))
    params = {"noise": 1e300} if clamp is None else {"noise": 1e300, "clamp": clamp}
    async with run_server(settings) as server, client(server) as http:
        with server_logs() as records:
            response = await http.put("/v1/rigs/noisy/examples", params=params, content=body)

    assert (response.status_code, response.json()["code"]) == (422, "noise_too_large")
    assert "noise" in response.json()["detail"] and errors_logged(records) == []


@pytest.mark.parametrize("path", ["/v1/rigs/gone", "/v1/rigs/gone/examples"])
async def test_a_client_leaving_mid_body_is_logged_once_without_a_traceback(settings, path):
    async with run_server(settings) as server, client(server) as http:
        with server_logs() as records:
            _, writer = await asyncio.open_connection(server.host, server.port)
            writer.write(
                f"PUT {path} HTTP/1.1\r\nHost: {server.host}\r\nContent-Length: 100000\r\n\r\n"
                .encode() + bytes(1000)
            )  # fmt: skip
            await writer.drain()
            writer.close()
            await writer.wait_closed()
            await wait_for_record(records, "http.request")
        after = await http.get("/healthz")

    assert errors_logged(records) == []
    assert [getattr(r, "event", None) for r in records].count("http.client_disconnect") == 1
    assert after.status_code == 200


async def test_an_unexpected_failure_is_a_500_logged_once_with_its_traceback(settings):
    app = create_app(settings)

    @app.get("/v1/boom")
    async def boom() -> None:
        raise RuntimeError("a bug")

    async with run_server(settings, app=app) as server, client(server) as http:
        with server_logs() as records:
            response = await http.get("/v1/boom")
            await wait_for_record(records, "http.request")
        after = await http.get("/healthz")

    assert (response.status_code, response.json()["code"]) == (500, "internal_error")
    # Once by facecast's handler; before, uvicorn logged the same traceback again.
    assert errors_logged(records) == ["unhandled error"]
    assert after.status_code == 200


async def test_archive_over_member_limit_is_413(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_archive_members=5)
    body = zip_bytes({f"f{i}.txt": b"x" for i in range(6)})
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/many/examples", content=body)

    assert (response.status_code, response.json()["code"]) == (413, "archive_too_many_members")


async def test_archive_over_extracted_size_limit_is_413(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_extracted_bytes=10_000)
    rng = np.random.default_rng(0)
    body = zip_bytes({"big.bin": rng.bytes(20_000)})  # incompressible: ratio ~1
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/big/examples", content=body)

    assert (response.status_code, response.json()["code"]) == (413, "archive_too_large")


async def test_body_over_upload_limit_is_413_from_content_length(tmp_path, rig):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_upload_bytes=1000)
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/big", content=bytes(4000))

    assert (response.status_code, response.json()["code"]) == (413, "payload_too_large")


async def test_chunked_body_over_upload_limit_is_413_while_streaming(tmp_path):
    settings = Settings(rigs_dir=tmp_path / "rigs", max_upload_bytes=1000)

    async def chunks():
        for _ in range(8):
            yield bytes(500)

    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/big", content=chunks())

    assert "content-length" not in response.request.headers
    assert (response.status_code, response.json()["code"]) == (413, "payload_too_large")


@pytest.mark.parametrize(
    "rig_id", ["-leading-dash", ".hidden", "a" * 65, "sp ace", "semi;colon", "ü"]
)
async def test_bad_rig_id_is_400(settings, rig, rig_id):
    async with run_server(settings) as server, client(server) as http:
        response = await http.put(f"/v1/rigs/{rig_id}", content=rig.to_bytes())

    assert (response.status_code, response.json()["code"]) == (400, "invalid_rig_id")


async def test_traversal_in_rig_id_never_reaches_the_store(settings, rig, tmp_path):
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/..%2Fescaped", content=rig.to_bytes())

    assert response.status_code in (400, 404)
    assert not (tmp_path / "escaped.rig").exists()


@pytest.mark.parametrize("mangle", ["garbage", "truncated", "flipped-byte"])
async def test_corrupt_rig_file_is_422_and_nothing_is_stored(settings, rig, mangle):
    data = rig.to_bytes()
    body = {
        "garbage": b"not a rig at all",
        "truncated": data[: len(data) // 2],
        "flipped-byte": data[:100] + bytes([data[100] ^ 0xFF]) + data[101:],
    }[mangle]
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/corrupt", content=body)
        listed = await http.get("/v1/rigs")

    assert response.status_code == 422
    assert response.json()["code"] in {"bad_rig_file", "checksum_mismatch"}
    assert listed.json()["rigs"] == []


# -- rig files held to the protocol's limits (issue 13, item 8) ------------------------


def _example_set_with(*, names=None, k: int | None = None):
    es = tiny_example_set()
    if k is not None:
        rng = np.random.default_rng(5)
        m = len(es.names)
        source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
        source[1:] += rng.normal(scale=0.3, size=(m - 1, k, 3))
        es = dataclasses.replace(es, source_points=source)
    return es if names is None else dataclasses.replace(es, names=names)


@pytest.mark.parametrize("length,status", [(256, 201), (257, 422)])
async def test_example_names_up_to_the_protocols_256_characters_are_stored(
    settings, length, status
):
    named = fit(_example_set_with(names=("neutral", "s" * length, "frown", "jaw")))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/named", content=named.to_bytes())
        listed = await http.get("/v1/rigs")

    assert response.status_code == status, response.text
    if status == 422:
        assert response.json()["code"] == "rig_exceeds_limits"
        assert "over 256 characters" in response.json()["detail"]
        assert listed.json()["rigs"] == []


async def test_examples_with_more_feature_points_than_the_protocol_carries_are_refused(
    settings, tmp_path
):
    write_example_folder(tmp_path / "set", _example_set_with(k=4097))
    body = zip_bytes(folder_members(tmp_path / "set"))
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/wide/examples", content=body)
        listed = await http.get("/v1/rigs")

    assert (response.status_code, response.json()["code"]) == (422, "rig_exceeds_limits")
    assert "K=4097" in response.json()["detail"] and listed.json()["rigs"] == []


async def test_a_rig_file_with_a_nan_blend_basis_is_refused_naming_the_record(settings):
    spoiled = fit(tiny_example_set())
    spoiled._blend_basis[2, 5] = np.nan  # written with a valid checksum all the same
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/nan", content=spoiled.to_bytes())

    assert (response.status_code, response.json()["code"]) == (422, "rig_not_finite")
    assert "blend_basis" in response.json()["detail"]


async def test_a_rig_file_put_in_the_directory_by_hand_is_checked_on_load(settings):
    named = fit(_example_set_with(names=("neutral", "s" * 300, "frown", "jaw")))
    settings.rigs_dir.mkdir(parents=True)
    named.save(settings.rigs_dir / "byhand.rig")
    async with run_server(settings) as server, client(server) as http:
        response = await http.get("/v1/rigs/byhand")

    assert (response.status_code, response.json()["code"]) == (422, "rig_exceeds_limits")


async def test_empty_body_is_400(settings):
    async with run_server(settings) as server, client(server) as http:
        response = await http.put("/v1/rigs/empty", content=b"")

    assert (response.status_code, response.json()["code"]) == (400, "empty_body")


async def test_unknown_rig_is_404_on_every_read(settings):
    async with run_server(settings) as server, client(server) as http:
        responses = [
            await http.get("/v1/rigs/ghost"),
            await http.get("/v1/rigs/ghost/model.glb"),
            await http.get("/v1/rigs/ghost/rig"),
            await http.delete("/v1/rigs/ghost"),
        ]

    assert [(r.status_code, r.json()["code"]) for r in responses] == [(404, "rig_not_found")] * 4


async def test_ops_endpoints_answer_and_docs_are_served(settings, rig):
    async with run_server(settings) as server, client(server) as http:
        await http.put("/v1/rigs/face", content=rig.to_bytes())
        health = await http.get("/healthz")
        ready = await http.get("/readyz")
        metrics = await http.get("/metrics")
        docs = await http.get("/docs")
        openapi = await http.get("/openapi.json")

    assert health.status_code == ready.status_code == docs.status_code == 200
    assert 'facecast_http_requests_total{method="PUT",route="/v1/rigs/{rig_id}"' in metrics.text
    assert "/v1/rigs/{rig_id}/examples" in openapi.json()["paths"]


async def test_readyz_fails_when_the_rig_directory_is_gone(settings):
    async with run_server(settings) as server, client(server) as http:
        shutil.rmtree(settings.rigs_dir)  # its scratch folder too
        response = await http.get("/readyz")

    assert (response.status_code, response.json()["code"]) == (503, "not_ready")

"""`facecast rigs` against a real server, and `facecast serve`'s flags -> Settings."""

from __future__ import annotations

import argparse
import json

import pytest
from _server_helpers import write_example_folder

from facecast.cli.commands import rigs, serve
from facecast.cli.errors import CommandError
from facecast.rig import load_rig
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio


def parse(module, argv: list[str]) -> argparse.Namespace:
    # The command's own parser, as `facecast` builds it.
    parser = argparse.ArgumentParser(prog="facecast")
    module.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def run_rigs(server, *argv: str, token: str | None = None) -> int:
    extra = ["--token", token] if token else []
    action, *rest = argv
    args = parse(rigs, ["rigs", action, server.base_url, *rest, *extra])
    return args.func(args)


async def test_rigs_command_uploads_fits_lists_downloads_and_deletes(
    settings, rig, tmp_path, capsys
):
    rig.save(tmp_path / "face.rig")
    write_example_folder(tmp_path / "set")
    async with run_server(settings) as server:
        run_rigs(server, "put", "face", str(tmp_path / "face.rig"))
        run_rigs(server, "put", "fitted", str(tmp_path / "set"), "--noise", "0.01")
        capsys.readouterr()
        run_rigs(server, "list")
        listed = capsys.readouterr().out
        run_rigs(server, "show", "face")
        shown = json.loads(capsys.readouterr().out)
        run_rigs(server, "get", "face", str(tmp_path / "back.rig"))
        run_rigs(server, "get", "face", str(tmp_path / "face.glb"), "--glb")
        run_rigs(server, "rm", "face")
        remaining = server.app.state.store.list()

    assert [line.split("\t")[0] for line in listed.splitlines()] == ["face", "fitted"]
    assert shown["checksum"] == rig.checksum
    assert load_rig(tmp_path / "back.rig").checksum == rig.checksum
    assert (tmp_path / "face.glb").read_bytes()[:4] == b"glTF"
    assert [info.id for info in remaining] == ["fitted"]


async def test_rigs_put_fits_an_example_set_with_clamp_and_sparsity(settings, tmp_path, capsys):
    write_example_folder(tmp_path / "set")
    async with run_server(settings) as server:
        code = run_rigs(
            server,
            "put",
            "bounded",
            str(tmp_path / "set"),
            *("--noise", "0.05", "--clamp", "nonneg", "--sparsity", "0.5"),
        )
        stored = server.app.state.store.get("bounded")

    assert code == 0
    assert "clamp nonneg" in capsys.readouterr().out
    assert stored.model.clamp == "nonneg" and stored.fit_report["sparsity"] == 0.5


async def test_rigs_put_shows_the_servers_422_for_sparsity_without_clamp(settings, tmp_path):
    write_example_folder(tmp_path / "set")
    async with run_server(settings) as server:
        with pytest.raises(CommandError, match="422 sparsity_without_clamp"):
            run_rigs(server, "put", "bad", str(tmp_path / "set"), "--sparsity", "1")


@pytest.mark.parametrize("flags", [["--clamp", "nonneg"], ["--sparsity", "1"], ["--noise", "1"]])
def test_rigs_put_of_a_rig_file_refuses_fit_options(rig, tmp_path, flags):
    rig.save(tmp_path / "face.rig")
    # Refused before any request: the URL is never contacted.
    args = parse(
        rigs, ["rigs", "put", "http://127.0.0.1:9", "face", str(tmp_path / "face.rig"), *flags]
    )

    with pytest.raises(CommandError, match=f"{flags[0]}: fit options .* fitted rig file"):
        args.func(args)


async def test_rigs_command_reports_the_server_error_code(auth_settings):
    async with run_server(auth_settings) as server:
        with pytest.raises(CommandError, match="401 unauthorized"):
            run_rigs(server, "list")
        with pytest.raises(CommandError, match="404 rig_not_found"):
            run_rigs(server, "show", "ghost", token="viewer-token")


def test_rigs_command_reports_an_unreachable_server():
    args = parse(rigs, ["rigs", "list", "http://127.0.0.1:9"])

    with pytest.raises(CommandError, match="cannot reach"):
        args.func(args)


def test_rigs_put_of_a_missing_path_names_it(tmp_path):
    args = parse(rigs, ["rigs", "put", "http://127.0.0.1:9", "x", str(tmp_path / "nope")])

    with pytest.raises(CommandError, match="nope: no such file"):
        args.func(args)


def test_serve_flags_override_env_and_tokens_default_to_admin(tmp_path):
    args = parse(
        serve,
        [
            "serve",
            "--port",
            "9100",
            "--rigs",
            str(tmp_path),
            "--token",
            "abc",
            "--token",
            "s:stream",
            "--token",
            "p:performer:ann+publisher",
        ],
    )

    settings = serve.settings_from_args(
        args, env={"FACECAST_PORT": "9000", "FACECAST_WORKERS": "3"}
    )

    assert (settings.port, settings.workers, settings.rigs_dir) == (9100, 3, tmp_path)
    assert dict(settings.tokens) == {
        "abc": frozenset({"admin"}),
        "s": frozenset({"stream"}),
        "p": frozenset({"performer:ann", "publisher"}),
    }


def test_serve_refuses_public_bind_without_tokens_as_a_command_error(tmp_path, monkeypatch):
    for name in ("FACECAST_TOKENS", "FACECAST_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    args = parse(serve, ["serve", "--host", "0.0.0.0", "--rigs", str(tmp_path)])

    with pytest.raises(CommandError, match="no API tokens"):
        args.func(args)


@pytest.mark.parametrize("name", ["avatar.vrm", "avatar.bin"])
async def test_rigs_put_of_a_character_file_fits_it_and_prints_the_pairing(
    settings, tmp_path, capsys, name
):
    from tests.rig._avatars import avatar

    (tmp_path / name).write_bytes(avatar("vrm1"))
    async with run_server(settings) as server:
        code = run_rigs(server, "put", "ava", str(tmp_path / name), "--noise", "0.05")
        run_rigs(server, "show", "ava")

    out = capsys.readouterr().out
    assert code == 0
    assert "fitted ava from a vrm1 character: M=" in out and "K=26" in out
    assert "pairing with" in out and "paired   morph target 'jawOpen'" in out
    assert '"format": "vrm1"' in out  # rigs show: the character's description


async def test_rigs_put_of_a_gltf_sends_it_with_the_files_it_names(settings, tmp_path, capsys):
    from tests.rig._avatars import avatar
    from tests.rig.test_character import split

    doc, blob = split(avatar("arkit"))
    (tmp_path / "tex").mkdir()
    (tmp_path / "avatar.bin").write_bytes(blob)
    (tmp_path / "unrelated.bin").write_bytes(b"\0" * 1024)
    doc["buffers"] = [{"byteLength": len(blob), "uri": "avatar.bin"}]
    view = doc["bufferViews"][doc["images"][0]["bufferView"]]
    (tmp_path / "tex" / "skin map.png").write_bytes(
        blob[view["byteOffset"] : view["byteOffset"] + view["byteLength"]]
    )
    doc["images"][0] = {"uri": "tex/skin%20map.png"}
    (tmp_path / "avatar.gltf").write_text(json.dumps(doc))
    async with run_server(settings) as server:
        code = run_rigs(server, "put", "folder", str(tmp_path / "avatar.gltf"))

    assert code == 0
    assert "fitted folder from a gltf character" in capsys.readouterr().out


def test_rigs_put_of_a_gltf_naming_a_file_outside_its_folder_says_so(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "secret.bin").write_bytes(b"\0" * 8)
    gltf = {"asset": {"version": "2.0"}, "buffers": [{"byteLength": 8, "uri": "../secret.bin"}]}
    (tmp_path / "in" / "a.gltf").write_text(json.dumps(gltf))
    args = parse(rigs, ["rigs", "put", "http://127.0.0.1:9", "x", str(tmp_path / "in" / "a.gltf")])

    with pytest.raises(CommandError, match=r"outside the \.gltf's folder"):
        args.func(args)


@pytest.mark.ict
async def test_rigs_put_with_expressions_transfer_waits_for_the_job_and_prints_its_report(
    settings, tmp_path, capsys
):
    from tests.rig._avatars import avatar, face_mesh, require_ict

    require_ict()
    (tmp_path / "head.glb").write_bytes(avatar("neutral_only"))
    face_vertices = len(face_mesh()["vertices"])  # ICT's face part and its UV seam's copies
    async with run_server(settings) as server:
        code = run_rigs(
            server, "put", "ava", str(tmp_path / "head.glb"),
            "--expressions", "transfer", "--names", "jawOpen", "eyeBlinkLeft",
        )  # fmt: skip

    captured = capsys.readouterr()
    assert code == 0
    assert (
        f"transfer job for ava: 2 expression(s) onto {face_vertices} vertices (identity"
        in captured.out
    )
    assert "transferring: " in captured.err  # the progress line
    assert "transferred 2 expression(s) in" in captured.out
    assert "fitted ava from a gltf character: M=3 K=26" in captured.out


@pytest.mark.ict
async def test_rigs_put_sends_a_markers_file_beside_the_character_and_shows_its_error(
    settings, tmp_path
):
    from tests.rig._avatars import avatar, require_ict

    require_ict()
    (tmp_path / "head.glb").write_bytes(avatar("neutral_only"))
    (tmp_path / "markers.txt").write_text("0 0\n1 1\n2 999999\n")
    async with run_server(settings) as server:
        with pytest.raises(CommandError) as info:
            run_rigs(
                server, "put", "ava", str(tmp_path / "head.glb"),
                "--expressions", "transfer", "--markers", str(tmp_path / "markers.txt"),
            )  # fmt: skip

    assert "422 marker_out_of_range" in str(info.value)
    assert "target vertex 999999" in str(info.value)


def test_rigs_put_refuses_transfer_options_without_expressions_transfer(tmp_path):
    (tmp_path / "head.glb").write_bytes(b"glTF")
    args = parse(rigs, ["rigs", "put", "http://127.0.0.1:9", "ava", str(tmp_path / "head.glb"),
                        "--markers", "auto"])  # fmt: skip

    with pytest.raises(CommandError, match="--expressions transfer"):
        args.func(args)

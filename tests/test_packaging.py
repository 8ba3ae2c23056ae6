"""The distribution builds as a wheel holding every subpackage, the spec and the CLI entry point."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, str]:
    """The wheel, and what building it printed (setuptools' warnings included)."""
    out = tmp_path_factory.mktemp("wheel")
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(out),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    (path,) = out.glob("facecast-*.whl")
    return path, result.stdout + result.stderr


@pytest.fixture(scope="module")
def wheel(built) -> Path:
    return built[0]


def test_building_the_wheel_leaves_no_data_folder_unlisted(built):
    # setuptools warns (pip shows the backend's output, no -q) when package data sits in
    # a folder it would import as a package it was not told about.
    _, log = built
    assert "Building wheel for facecast" in log
    assert "is absent from the `packages` configuration" not in log


def test_wheel_holds_the_viewer_pages_and_every_built_viewer_file(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    viewer = ROOT / "client" / "viewer"
    for page in ("viewer.html", "overlay.html", "perform.html"):
        assert f"facecast/client/viewer/{page}" in names
    dist = viewer / "dist"
    if not (dist / "viewer.js").is_file():
        pytest.skip("the viewer is not built here (scripts/setup builds it with npm)")
    built_files = [p.relative_to(viewer).as_posix() for p in dist.rglob("*") if p.is_file()]
    missing = [f for f in built_files if f"facecast/client/viewer/{f}" not in names]
    assert "dist/perform/facemesh.bin" in built_files and not missing
    assert "dist/draco/draco_decoder.wasm" in built_files  # compressed characters (Draco)


def test_wheel_holds_every_package_and_the_protocol_spec(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for member in [
        "facecast/__init__.py",
        "facecast/protocol/PROTOCOL.md",
        "facecast/protocol/codec.py",
        "facecast/rig/fit.py",
        "facecast/rig/sources/layouts/mediapipe_face_mesh.json",
        "facecast/rig/characters/generic_arkit/points.npz",
        "facecast/rig/characters/generic_arkit/LICENSE-ICT-FaceKit",
        "facecast/rig/demo/scene.py",
        "facecast/server/app.py",
        "facecast/client/connection.py",
        "facecast/client/channel.py",
        "facecast/cli/main.py",
        "facecast/cli/commands/demo.py",
        "facecast/cli/bench/engine.py",
        "facecast/cli/bridges/vmc.py",
    ]:
        assert member in names, member


def test_wheel_declares_the_facecast_console_script(wheel):
    archive = zipfile.ZipFile(wheel)
    (entry_points,) = [n for n in archive.namelist() if n.endswith("entry_points.txt")]
    assert "facecast = facecast.cli.main:main" in archive.read(entry_points).decode()


def test_installed_wheel_imports_and_fits_the_demo(wheel, tmp_path):
    target = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "-q",
            "--target",
            str(target),
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        "import facecast.rig as r, facecast.rig.demo as d;"
        "assert r.__file__.startswith(sys.argv[1]), r.__file__;"
        "rig = r.fit(d.demo_example_set()); print(rig.num_examples)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(target)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "13"


def test_the_licence_is_an_spdx_expression_without_a_deprecation_warning(built):
    path, output = built
    with zipfile.ZipFile(path) as wheel:
        metadata = next(n for n in wheel.namelist() if n.endswith(".dist-info/METADATA"))
        text = wheel.read(metadata).decode()

    assert "License-Expression: MIT" in text.splitlines()
    assert "project.license` as a TOML table is deprecated" not in output

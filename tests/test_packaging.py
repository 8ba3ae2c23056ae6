"""The distribution builds as a wheel holding every subpackage, the spec and the CLI entry point."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    (path,) = out.glob("facecast-*.whl")
    return path


def test_wheel_holds_every_package_and_the_protocol_spec(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for member in [
        "facecast/__init__.py",
        "facecast/protocol/PROTOCOL.md",
        "facecast/protocol/codec.py",
        "facecast/rig/fit.py",
        "facecast/rig/sources/layouts/mediapipe_face_mesh.json",
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

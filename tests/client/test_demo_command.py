"""``facecast demo`` runs the main job end to end: fit, serve, stream, compare, viewer URL."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

from facecast.cli.main import main


def test_demo_streams_the_performance_and_matches_offline_cloning(capsys):
    status = main(["demo", "--port", "0", "--exit", "--seconds", "2"])
    out = capsys.readouterr().out
    assert status == 0
    assert re.search(r"streamed 120 frames .* as weights/f32", out)
    assert "results vs offline cloning: max difference 0 (exactly equal)" in out
    assert re.search(r"viewer: http://127\.0\.0\.1:\d+/viewer\?rig=demo", out)
    assert re.search(r"the API docs: http://127\.0\.0\.1:\d+/$", out, re.MULTILINE)


def test_demo_in_vertices_f16_matches_offline_cloning(capsys):
    status = main(
        [
            "demo",
            "--port",
            "0",
            "--exit",
            "--seconds",
            "1",
            "--output",
            "vertices",
            "--dtype",
            "f16",
        ]
    )
    assert status == 0
    assert "max difference 0 (exactly equal)" in capsys.readouterr().out


def test_demo_refuses_a_bad_port(capsys):
    assert main(["demo", "--port", "70000", "--exit"]) == 2
    assert "--port must be in 0..65535" in capsys.readouterr().err


def test_demo_stopped_by_sigterm_removes_its_temporary_folder(tmp_path):
    """Like Ctrl-C: the rig folder under TMPDIR is gone and the exit is clean."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = {**os.environ, "TMPDIR": str(scratch)}
    err = (tmp_path / "stderr.txt").open("w+")
    process = subprocess.Popen(
        [sys.executable, "-m", "facecast.cli", "demo", "--port", "0", "--seconds", "1"],
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
        env=env,
    )
    try:
        assert process.stdout is not None
        seen = []
        for line in process.stdout:  # serving: the folder exists now
            seen.append(line)
            if line.startswith("serving;"):
                break
        err.seek(0)
        assert seen and seen[-1].startswith("serving;"), ("".join(seen), err.read()[-2000:])
        assert list(scratch.glob("facecast-demo-*")), "no temporary folder while serving"
        process.send_signal(signal.SIGTERM)
        status = process.wait(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()

    assert status == 0
    assert list(scratch.glob("facecast-demo-*")) == []

"""Runs the viewer's own JavaScript unit tests (client/viewer/test, ``node --test``).

They check the browser protocol code against PROTOCOL.md's byte examples.
"""

from __future__ import annotations

import shutil
import subprocess

import pytest

from facecast.server.pages.viewer import viewer_dir


def test_viewer_javascript_unit_tests_pass():
    root = viewer_dir()
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    if not (root / "node_modules" / "@msgpack" / "msgpack").is_dir():
        pytest.skip("the viewer's npm packages are not installed (npm ci in client/viewer)")

    run = subprocess.run(
        [node, "--test", "test/"], cwd=root, capture_output=True, text=True, timeout=60
    )

    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]

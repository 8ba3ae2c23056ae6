"""ICT-FaceKit skips: taken on a machine without it, refused under CI=true."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ._ci_skips import fails_on_ci

ROOT = Path(__file__).resolve().parents[1]


def test_an_ict_skip_fails_only_under_ci():
    reason = "needs ../shared/data/ict-facekit (or FACECAST_ICT)"

    assert fails_on_ci(reason, {"CI": "true"}) is not None
    assert fails_on_ci("ICT-FaceKit not found", {"CI": "true"}) is not None
    assert fails_on_ci(reason, {}) is None
    assert fails_on_ci(reason, {"CI": "false"}) is None
    assert fails_on_ci("no Chromium at /usr/bin/chromium", {"CI": "true"}) is None


def test_the_suite_turns_an_ict_skip_into_a_failure_under_ci():
    """Through the real hook: a test of this suite that skips for ICT, with CI on and off."""
    # Under tests/ (its conftest holds the hook), named so no collection but this one's
    # picks it up (a path given on the command line is collected whatever its name).
    test = ROOT / "tests" / f"_ict_skip_probe_{os.getpid()}.py"
    test.write_text(
        "import pytest\n\n"
        "def test_probe():\n"
        "    pytest.skip('needs ../shared/data/ict-facekit (or FACECAST_ICT)')\n"
    )
    try:
        runs = {
            ci: subprocess.run(
                [sys.executable, "-m", "pytest", str(test), "-q", "-p", "no:cacheprovider"],
                capture_output=True, text=True, timeout=120, cwd=ROOT,
                env={**os.environ, "CI": ci},
            )
            for ci in ("true", "false")
        }  # fmt: skip
    finally:
        test.unlink()

    assert runs["true"].returncode == 1 and "1 failed" in runs["true"].stdout
    assert runs["false"].returncode == 0 and "1 skipped" in runs["false"].stdout

"""Under CI=true no skip passes silently: every kind of skip fails the run, naming its reason."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ._requires import skip_or_fail

REPO = Path(__file__).resolve().parent.parent

SKIPPING = """
import pytest

@pytest.mark.skipif(True, reason="no chromium here")
def test_marked():
    pass

def test_skips_itself():
    pytest.skip("no viewer build here")

@pytest.fixture
def kernel():
    pytest.skip("no kernel here")

def test_needs_a_fixture_that_skips(kernel):
    pass

@pytest.mark.xfail(reason="a known failure, not a skip", strict=True)
def test_expected_to_fail():
    assert False

def test_runs():
    pass
"""


def run_pytest(folder: Path, ci: str) -> str:
    (folder / "conftest.py").write_text(
        "from tests._requires import pytest_make_collect_report, pytest_runtest_makereport\n"
    )
    (folder / "test_skipping.py").write_text(SKIPPING)
    (folder / "test_module_skip.py").write_text(
        'import pytest\npytest.importorskip("no_such_mod")\n'
    )
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-rA",
            "-p",
            "no:cacheprovider",
            "--continue-on-collection-errors",
            str(folder),
        ],
        capture_output=True,
        text=True,
        cwd=folder,
        env={**os.environ, "CI": ci, "PYTHONPATH": str(REPO)},
        timeout=120,
    )
    return done.stdout


def test_under_ci_every_skip_fails_naming_its_reason_and_xfail_stays(tmp_path):
    out = run_pytest(tmp_path, "true")

    # Skips at set-up and collection report as errors, in the test's body as a failure.
    assert "1 failed, 1 passed, 1 xfailed, 3 errors" in out, out
    for reason in ("no chromium here", "no viewer build here", "no kernel here", "no_such_mod"):
        assert f"CI=true does not skip (Skipped: {reason}" in out.replace(
            "could not import 'no_such_mod'", "no_such_mod"
        ), reason


def test_elsewhere_the_skips_stand(tmp_path):
    out = run_pytest(tmp_path, "false")

    assert "1 passed, 4 skipped, 1 xfailed" in out, out


def test_skip_or_fail_skips_elsewhere_and_fails_under_ci():
    with pytest.raises(pytest.skip.Exception, match="no validator"):
        skip_or_fail("no validator", {"CI": "false"})
    with pytest.raises(pytest.fail.Exception, match="CI=true needs it: no validator"):
        skip_or_fail("no validator", {"CI": "true"})

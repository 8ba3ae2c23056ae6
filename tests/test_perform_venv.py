"""The perform venv: present and usable, numpy < 2 there and only there, and the rule that
CI fails, never skips, when it is missing."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ._perform_venv import perform_venv_problem, require_perform_venv


def test_a_missing_perform_venv_fails_under_ci(tmp_path):
    with pytest.raises(pytest.fail.Exception, match=r"CI=true needs it.*scripts/setup --test"):
        require_perform_venv(tmp_path / "bin" / "python", {"CI": "true"})


def test_a_missing_perform_venv_skips_elsewhere_saying_how_to_make_it(tmp_path):
    with pytest.raises(pytest.skip.Exception, match=r"no perform venv.*scripts/setup --test"):
        require_perform_venv(tmp_path / "bin" / "python", {"CI": "false"})


@pytest.mark.skipif(
    importlib.util.find_spec("mediapipe") is not None,
    reason="this .venv has the perform extra (scripts/setup --perform)",
)
def test_an_interpreter_without_mediapipe_is_no_perform_venv():
    problem = perform_venv_problem(Path(sys.executable))
    assert problem is not None and "cannot import" in problem and "mediapipe" in problem


def test_mediapipe_keeps_numpy_below_2_in_the_perform_venv_only(perform_python):
    versions = subprocess.run(
        [str(perform_python), "-c", "import numpy, mediapipe; print(numpy.__version__)"],
        capture_output=True,
        text=True,
        timeout=240,
        check=True,
    ).stdout.strip()
    assert versions.startswith("1."), versions
    assert int(np.__version__.split(".")[0]) >= 2, (
        f"this .venv has numpy {np.__version__}: scripts/setup --perform downgraded it; "
        "rm -rf .venv && scripts/setup --test"
    )

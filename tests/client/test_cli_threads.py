"""The CLI limits BLAS to one thread before numpy loads (bench figures depend on it)."""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = """
import sys
from facecast.cli import main as cli
assert "numpy" not in sys.modules, "importing the CLI loaded numpy"
cli.limit_blas_threads()
import numpy, os
print(os.environ["OPENBLAS_NUM_THREADS"])
"""


def test_importing_the_cli_leaves_numpy_unloaded_so_the_thread_limit_applies():
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    result = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "1"


def test_the_client_library_still_exports_connect():
    from facecast.client import StreamSession, connect

    assert callable(connect) and StreamSession.__name__ == "StreamSession"

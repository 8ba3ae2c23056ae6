"""Suite-wide set-up: one BLAS thread (as the CLI sets it) before numpy is imported, the
anyio backend and uvicorn's WebSocket implementations for the tests of real servers, the
perform venv's interpreter for the tests that run MediaPipe (``tests._perform_venv``), and
under CI=true every skip turned into a failure (``tests._requires``; tests/README.md)."""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from facecast.server.testing import WS_IMPLEMENTATIONS  # noqa: E402

from ._perform_venv import require_perform_venv  # noqa: E402
from ._requires import pytest_make_collect_report, pytest_runtest_makereport  # noqa: E402, F401


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture(params=WS_IMPLEMENTATIONS)
def ws_impl(request) -> str:
    """uvicorn's WebSocket implementation under test (every server test runs on each)."""
    return request.param


@pytest.fixture(scope="session")
def perform_python() -> Path:
    """The interpreter of .venv-perform, checked once a session (a missing one fails the
    test under CI=true and skips it elsewhere)."""
    return require_perform_venv()

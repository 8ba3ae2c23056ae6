"""Suite-wide set-up: one BLAS thread (as the CLI sets it) before numpy is imported, the
anyio backend and uvicorn's WebSocket implementations for the tests of real servers, the
perform venv's interpreter for the tests that run MediaPipe (``tests._perform_venv``), and
under CI=true every skip turned into a failure (``tests._requires``; tests/README.md), and
the files that take longest handed out first (``pytest_collection_modifyitems``)."""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from facecast.server.testing import WS_IMPLEMENTATIONS  # noqa: E402

from ._perform_venv import require_perform_venv  # noqa: E402
from ._requires import pytest_make_collect_report, pytest_runtest_makereport  # noqa: E402, F401

#: Test files that drive a real Chromium, render and track videos, build wheels or run
#: long searches: tens of seconds each, the longest first (CI replica, 2026-12-05).
#: pytest-xdist's ``--dist loadfile`` hands files out in collection order, so these go
#: first and the short ones fill in at the end, rather than one worker finishing a long file
#: alone while the others idle (scripts/test).
_LONG_FIRST = (
    "tests/perform/test_eyes_rig.py",
    "tests/perform/test_webcam_video.py",
    "tests/protocol/test_protocol_fuzz.py",
    "tests/perform/test_bench_live.py",
    "tests/perform/test_perform_generic.py",
    "tests/perform/test_perform_page.py",
    "tests/rig/test_temporal.py",
    "tests/perform/",
    "tests/viewer/",
    "tests/channels/test_channels_processes.py",
    "tests/client/test_bench_broadcast.py",
    "tests/client/test_loadtest.py",
    "tests/test_packaging.py",
)


def _rank(item: pytest.Item) -> int:
    return next(
        (i for i, prefix in enumerate(_LONG_FIRST) if item.nodeid.startswith(prefix)),
        len(_LONG_FIRST),
    )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long files first, each file's tests in their own order (a stable sort)."""
    items.sort(key=_rank)


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

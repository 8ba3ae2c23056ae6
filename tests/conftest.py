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
#: long searches: tens of seconds each, the longest first (their summed durations in a CI
#: replica, 2026-12-05). scripts/test runs pytest-xdist's ``--dist loadfile`` with
#: ``--no-loadscope-reorder``, so files are handed out in collection order: these first,
#: the short ones filling in at the end, rather than one worker finishing a long file alone
#: while the others idle. (Without that flag xdist hands out the files with the most tests
#: first: in the replica of 2026-12-05 the eyes rig and the generic page tests, ~100 s
#: each, started at 98 % of the run.)
_LONG_FIRST = (
    "tests/perform/test_perform_page.py",
    "tests/perform/test_perform_generic.py",
    "tests/perform/test_eyes_rig.py",
    "tests/perform/test_track.py",
    "tests/perform/test_bench_live.py",
    "tests/protocol/test_protocol_fuzz.py",
    "tests/viewer/test_viewer_compressed.py",
    "tests/viewer/test_viewer_character.py",
    "tests/bridges/test_bridges_head_pose.py",
    "tests/perform/test_perform_glass.py",
    "tests/viewer/test_viewer_pages.py",
    "tests/perform/test_webcam_video.py",
    "tests/perform/test_eyelids.py",
    "tests/rig/test_temporal.py",
    "tests/viewer/test_viewer_try_it.py",
    "tests/channels/test_channels_processes.py",
    "tests/client/test_loadtest.py",
    "tests/viewer/test_viewer_framing.py",
    "tests/server/test_server_process.py",
    "tests/perform/",
    "tests/viewer/",
    "tests/client/test_bench_broadcast.py",
    "tests/protocol/test_protocol_fastframe.py",
    "tests/hostile/test_hostile_connections.py",
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

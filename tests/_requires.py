"""The one rule for a test whose requirement is missing: skip here, fail under CI=true.

CI (``scripts/test``, CI=true) has everything the suite drives: ICT-FaceKit's data,
the compiled kernel, Chromium, the viewer's build, node with the glTF validator, the
perform venv. A skip there would hide a lost requirement behind a green run, so under
CI=true every skip fails with its reason: ``skip_or_fail`` where a test or fixture
decides, and the suite's hooks (``tests/conftest.py``) for every ``skipif`` mark,
``pytest.skip`` and ``importorskip`` alike. Elsewhere the skip stands, saying the remedy.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import NoReturn

import pytest

__all__ = [
    "failed_under_ci",
    "on_ci",
    "pytest_make_collect_report",
    "pytest_runtest_makereport",
    "skip_or_fail",
]


def on_ci(environ: Mapping[str, str] = os.environ) -> bool:
    """True when ``environ`` is CI's (CI=true)."""
    return environ.get("CI") == "true"


def skip_or_fail(reason: str, environ: Mapping[str, str] = os.environ) -> NoReturn:
    """Skip the test with ``reason``; fail it instead when ``environ`` is CI's."""
    if on_ci(environ):
        pytest.fail(f"CI=true needs it: {reason}", pytrace=False)
    pytest.skip(reason)


def failed_under_ci(report: pytest.TestReport | pytest.CollectReport) -> None:
    """Turn ``report``, when it is a skip (not an xfail), into a failure naming its reason.

    For the suite's report hooks under CI=true; a report from a worker process (xdist)
    arrives at the controller as it leaves here.
    """
    if not report.skipped or hasattr(report, "wasxfail"):
        return
    longrepr = report.longrepr
    # A skip's longrepr is (path, line, "Skipped: reason").
    reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
    report.outcome = "failed"
    report.longrepr = f"CI=true does not skip ({reason}): scripts/test provides this"


_CI = on_ci()


# The suite's hooks (imported by tests/conftest.py): every test's and collector's report.
@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    report = yield
    if _CI:
        failed_under_ci(report)
    return report


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector: pytest.Collector):  # type: ignore[no-untyped-def]
    report = yield
    if _CI:
        failed_under_ci(report)
    return report

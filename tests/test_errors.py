"""Every package's exceptions share the root FacecastError and carry distinct, stable codes.

The classes are found by importing every facecast module (pyproject's package list), not
from a hand-kept list, so a new exception that forgets its root or its code fails here.
"""

from __future__ import annotations

import asyncio
import importlib
import inspect
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from facecast.client.errors import ConnectionFailed, RigNotFound, ServerRequestError
from facecast.client.fetch import fetch_summary
from facecast.errors import FacecastError
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.server.settings import Settings
from facecast.server.testing import run_server

ROOT = Path(__file__).resolve().parents[1]

#: Exceptions that are not errors: raised and caught inside one module for control flow.
NOT_ERRORS = {
    "facecast.server.connection.closing.Closing": "a connection's tasks signalling its own close (control flow)",
}

#: What each exception also is, so that an ``except`` written before the root keeps
#: catching it: (module, class) -> built-in base.
BUILTIN_BASES = {
    ("facecast.protocol.errors", "ProtocolError"): ValueError,
    ("facecast.rig.errors", "ExampleSetError"): ValueError,
    ("facecast.rig.errors", "FitError"): ValueError,
    ("facecast.rig.errors", "RigFileError"): ValueError,
    ("facecast.rig.errors", "InputError"): ValueError,
    ("facecast.rig.errors", "MeshError"): ValueError,
    ("facecast.rig.errors", "MarkerError"): ValueError,
    ("facecast.rig.errors", "CorrespondenceError"): ValueError,
    ("facecast.client.errors", "ConnectionFailed"): ConnectionError,
    ("facecast.client.errors", "ServerRequestError"): ConnectionError,
    ("facecast.client.errors", "RigNotFound"): LookupError,
    ("facecast.server.errors", "SettingsError"): ValueError,
    ("facecast.server.errors", "RigNotFoundError"): LookupError,
    ("facecast.server.errors", "ProfileNotFoundError"): LookupError,
    ("facecast.server.errors", "ArchiveError"): ValueError,
    ("facecast.server.errors", "BusUnavailable"): ConnectionError,
    ("facecast.cli.errors", "RenderError"): ValueError,
    ("facecast.cli.errors", "TrackerUnavailable"): RuntimeError,
    ("facecast.cli.bridges.tracker", "TrackerPacketError"): ValueError,
}


def _module_names() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    names = []
    for package in config["packages"]:
        for path in sorted((ROOT / config["package-dir"][package]).glob("*.py")):
            if path.stem == "__main__":  # runs the command when imported
                continue
            names.append(package if path.stem == "__init__" else f"{package}.{path.stem}")
    return names


@pytest.fixture(scope="module")
def exceptions() -> list[type[BaseException]]:
    """Every public exception class defined in a facecast module (not re-exported ones)."""
    found = []
    for name in _module_names():
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if (
                inspect.isclass(value)
                and issubclass(value, BaseException)
                and not issubclass(value, Warning)  # warnings are not raised as errors
                and value.__module__ == name
                and not attr.startswith("_")
                and f"{name}.{attr}" not in NOT_ERRORS
            ):
                found.append(value)
    return found


def _qualname(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def test_the_search_finds_the_errors_of_every_package(exceptions):
    # Guards the search itself: finding nothing would make the tests below pass vacuously.
    packages = {cls.__module__.split(".")[1] for cls in exceptions}
    assert {"errors", "protocol", "rig", "server", "client", "cli"} <= packages
    assert {(cls.__module__, cls.__name__) for cls in exceptions} >= set(BUILTIN_BASES)


def test_every_facecast_exception_derives_from_facecast_error(exceptions):
    outside = [_qualname(cls) for cls in exceptions if not issubclass(cls, FacecastError)]
    assert not outside, f"not FacecastErrors: {outside}"


def test_every_class_names_its_own_code_and_no_two_share_one(exceptions):
    by_code: dict[object, list[str]] = {}
    for cls in exceptions:
        if cls is ProtocolError:
            continue  # its codes are the wire's numbers, tested below
        assert "code" in vars(cls), f"{_qualname(cls)} sets no code of its own"
        code = vars(cls)["code"]
        assert isinstance(code, str) and re.fullmatch(r"[a-z]+(_[a-z0-9]+)*", code), code
        by_code.setdefault(code, []).append(_qualname(cls))
    shared = {code: names for code, names in by_code.items() if len(names) > 1}
    assert not shared


def test_protocol_errors_carry_the_wire_codes_which_are_distinct():
    assert len({int(code) for code in ErrorCode}) == len(ErrorCode)
    error = ProtocolError(ErrorCode.UNKNOWN_RIG, "no rig 'x'", fatal=True)
    assert error.code is ErrorCode.UNKNOWN_RIG and isinstance(error, FacecastError)


@pytest.mark.parametrize(("where", "builtin"), list(BUILTIN_BASES.items()), ids=str)
def test_an_except_on_the_builtin_base_still_catches_it(where, builtin):
    module, name = where
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, builtin) and issubclass(cls, FacecastError)


def test_a_connection_failure_is_caught_as_oserror_and_as_a_facecast_error():
    with pytest.raises(OSError) as caught:
        raise ConnectionFailed("server gone", attempts=3)
    assert isinstance(caught.value, FacecastError) and caught.value.code == "connection_failed"


def test_an_unknown_rig_over_rest_is_rig_not_found_with_the_servers_code(tmp_path):
    async def run() -> BaseException:
        async with run_server(Settings(rigs_dir=tmp_path / "rigs")) as server:
            try:
                await asyncio.to_thread(fetch_summary, server.base_url, "no-such-rig")
            except ServerRequestError as exc:
                return exc
        raise AssertionError("fetch_summary of an unknown rig returned")

    error = asyncio.run(run())

    assert isinstance(error, RigNotFound) and isinstance(error, LookupError)
    assert (error.status, error.code) == (404, "rig_not_found")


def test_the_cli_errors_module_loads_nothing_heavy():
    # Every command imports it at module level, so ``facecast --help`` stays fast.
    probe = "import sys, facecast.cli.errors; print(sorted(m for m in ('numpy', 'facecast.rig', 'facecast.protocol') if m in sys.modules))"
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"

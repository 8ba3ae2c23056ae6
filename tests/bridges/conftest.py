"""Fixtures of the bridge tests."""

from __future__ import annotations

import pytest

from facecast.rig import fit
from facecast.rig.sources.source_rig import SourceRig

from ._helpers import arkit_example_set


@pytest.fixture(scope="session")
def example_set():
    return arkit_example_set()


@pytest.fixture(scope="session")
def source_rig(example_set) -> SourceRig:
    return SourceRig.from_example_set(example_set)


@pytest.fixture(scope="session")
def cloning_rig(example_set):
    return fit(example_set)

"""Every .npy header numpy parses for facecast is parsed under ``NPY_READS``.

numpy parses each array's header with ast.literal_eval, whose recursion depth CPython 3.11
shares between threads: a garbage collection inside one parse that runs a finalizer lets
another thread parse, and one of them fails with "SystemError: AST constructor recursion
depth mismatch" (rig/npy_reads.py; seen once in the suite as a 500 from a server reading
rigs in two threads). Whether two threads race there is chance, so these tests pin what
removes it: each parse facecast's readers start holds the lock.
"""

from __future__ import annotations

import ast
import io
import warnings

import numpy as np
import pytest

from facecast.rig import fit, load_example_set
from facecast.rig.demo import demo_example_set
from facecast.rig.npy_reads import NPY_READS
from facecast.rig.rigfile import rig_from_bytes
from facecast.rig.sources.ict import ict_example_set, locate_ict
from facecast.rig.sources.loading import load_source_animation


@pytest.fixture
def parses(monkeypatch) -> list[bool]:
    """Each literal_eval call from now on (the real one runs): whether the lock was held."""
    held: list[bool] = []
    real = ast.literal_eval

    def literal_eval(node_or_string):  # type: ignore[no-untyped-def]
        held.append(NPY_READS._is_owned())
        return real(node_or_string)

    monkeypatch.setattr(ast, "literal_eval", literal_eval)
    return held


def test_a_rig_file_is_read_under_the_lock(parses):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = fit(demo_example_set()).to_bytes()

    rig_from_bytes(data)

    assert parses and all(parses), parses


def test_an_example_set_and_an_animation_are_read_under_the_lock(parses, tmp_path):
    demo = demo_example_set()
    examples = tmp_path / "set.npz"
    np.savez(examples, source_points=demo.source_points, target_vertices=demo.target_vertices,
             target_faces=demo.target_faces, names=np.array(demo.names))  # fmt: skip
    frames = tmp_path / "frames.npy"
    np.save(frames, demo.source_points[:3])

    load_example_set(examples)
    load_source_animation(frames)

    assert len(parses) >= 5 and all(parses), parses


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_ict_facekits_archive_is_read_under_the_lock(parses):
    ict_example_set(locate_ict())

    assert parses and all(parses), parses


def test_the_lock_is_one_a_thread_may_take_again():
    with NPY_READS, NPY_READS:  # a reader that calls another reader
        out = io.BytesIO()
        np.save(out, np.zeros(2))
        out.seek(0)
        assert np.load(out).tolist() == [0.0, 0.0]

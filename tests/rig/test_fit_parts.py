"""The fit's two parts: the blend basis built in a worker thread beside the math, and the
noise-gain check's algebra. Results only: no timings."""

from __future__ import annotations

import importlib
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from facecast.rig import ExampleSet, FitError, IdentifiabilityWarning, fit
from facecast.rig.basis import build_blend_basis

basis_module = importlib.import_module("facecast.rig.basis")

# Report entries that are clocks, or say how the fit ran rather than what it found.
HOW_IT_RAN = {"fit_seconds", "math_seconds", "basis_seconds", "basis_overlapped"}


def make_set(m: int = 9, k: int = 6, v: int = 40, seed: int = 0) -> ExampleSet:
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(k, 3)) + np.concatenate(
        [np.zeros((1, k, 3)), rng.normal(size=(m - 1, k, 3))]
    )
    # Target coordinates far from 0 with small offsets: rounding the float64 difference
    # once differs from subtracting the float32-rounded vertices.
    target = 1e3 + rng.normal(size=(v, 3)) + rng.normal(scale=1e-3, size=(m, v, 3))
    names = [f"e{i}" if i else "neutral" for i in range(m)]
    return ExampleSet(names, source, target, np.array([[0, 1, 2], [1, 2, 3]]))


def _bits(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.float32).view(np.uint32)


def _basis_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "facecast-fit-basis"]


def test_blend_basis_is_each_target_difference_rounded_once_to_float32():
    target = make_set().target_vertices
    m, v, _ = target.shape

    basis = build_blend_basis(target)

    flat = target.reshape(m, 3 * v)
    assert basis.dtype == np.float32 and basis.shape == (m, 3 * v)
    np.testing.assert_array_equal(_bits(basis[0]), _bits(flat[0].astype(np.float32)))
    np.testing.assert_array_equal(_bits(basis[1:]), _bits((flat[1:] - flat[0]).astype(np.float32)))
    # Not the difference of the rounded vertices: the test set tells the two apart.
    rounded = flat.astype(np.float32)
    assert np.any(basis[1:] != rounded[1:] - rounded[0])


def test_blend_basis_leaves_the_callers_ufunc_buffer_size_alone():
    before = np.getbufsize()
    build_blend_basis(make_set().target_vertices)
    assert np.getbufsize() == before


@pytest.mark.parametrize("share_bytes", [1, 3 * 40 * 8 * 3, 10 << 20])
@pytest.mark.parametrize("thread", [True, False])
def test_a_basis_built_in_shares_by_two_threads_equals_the_whole_one(
    monkeypatch, share_bytes, thread
):
    # Shares of one row, of three and of the whole basis; the caller helps at once.
    monkeypatch.setattr(basis_module, "BASIS_CHUNK_BYTES", share_bytes)
    target = make_set(m=20, v=40).target_vertices
    building = basis_module.BasisBuild(target, thread=thread)

    building.help()
    building.wait()

    np.testing.assert_array_equal(_bits(building.result()), _bits(build_blend_basis(target)))
    assert building.seconds > 0
    assert _basis_threads() == []


@pytest.mark.parametrize("options", [{}, {"noise": 0.1}, {"noise": 0.1, "kernel": "gaussian"}])
def test_fit_with_the_basis_thread_equals_fit_without_bit_for_bit(options):
    example_set = make_set(m=20, k=2, seed=3)  # radial terms too

    beside = fit(example_set, **options)
    after = fit(example_set, basis_thread=False, **options)

    np.testing.assert_array_equal(_bits(beside.blend_basis), _bits(after.blend_basis))
    for name in ("mean", "features", "params", "linear_coeffs", "radial_coeffs", "alpha"):
        np.testing.assert_array_equal(getattr(beside.model, name), getattr(after.model, name))
    assert beside.fit_report["basis_overlapped"] and not after.fit_report["basis_overlapped"]
    assert {k: v for k, v in beside.fit_report.items() if k not in HOW_IT_RAN} == {
        k: v for k, v in after.fit_report.items() if k not in HOW_IT_RAN
    }


def test_fit_report_times_the_math_and_the_basis_within_the_wall_time():
    report = fit(make_set()).fit_report
    assert 0.0 < report["math_seconds"] <= report["fit_seconds"]
    assert 0.0 < report["basis_seconds"] <= report["fit_seconds"]


@pytest.mark.parametrize("basis_thread", [True, False])
def test_an_error_building_the_basis_reaches_the_caller(monkeypatch, basis_thread):
    def fail(target_vertices, basis, start, stop):
        raise MemoryError("no room for the blend basis")

    monkeypatch.setattr(basis_module, "_fill_rows", fail)

    with pytest.raises(MemoryError, match="no room for the blend basis"):
        fit(make_set(), basis_thread=basis_thread)
    assert _basis_threads() == []


def test_an_error_in_the_math_reaches_the_caller_and_leaves_no_thread():
    example_set = make_set()
    source = example_set.source_points.copy()
    source[5] = source[2]
    bad = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )

    with pytest.raises(FitError, match="coinciding"):
        fit(bad)
    assert _basis_threads() == []


def test_fits_running_in_a_pool_of_threads_equal_one_fit_alone():
    # The server's fit executor calls fit from several threads at once.
    example_set = make_set(m=20, k=2, seed=3)
    alone = fit(example_set)

    with ThreadPoolExecutor(4) as pool:
        rigs = list(pool.map(lambda _: fit(example_set), range(8)))

    for rig in rigs:
        np.testing.assert_array_equal(_bits(rig.blend_basis), _bits(alone.blend_basis))
        np.testing.assert_array_equal(rig.model.radial_coeffs, alone.model.radial_coeffs)
    assert _basis_threads() == []


def test_identifiability_warnings_point_at_the_line_that_called_fit():
    example_set = make_set()
    source = example_set.source_points.copy()
    source[5] = source[2] + 1e-3  # nearly collapsing
    close = ExampleSet(
        example_set.names, source, example_set.target_vertices, example_set.target_faces
    )

    with pytest.warns(IdentifiabilityWarning, match="nearly collapse") as caught:
        fit(close)
    assert {w.filename for w in caught} == {__file__}


def _jacobian_rms(rig, step: float) -> float:
    """RMS over the examples of |dw/dp|_F by central differences of eq. 3.8."""
    model = rig.model
    params = model.params
    m, n = params.shape
    total = 0.0
    for k in range(m):
        shifts = step * np.eye(n)
        ahead = model.weights_from_params(params[k] + shifts)
        behind = model.weights_from_params(params[k] - shifts)
        total += float(np.sum(((ahead - behind) / (2 * step)) ** 2))
    return float(np.sqrt(total / m))


@pytest.mark.parametrize(
    ("example_set", "options"),
    [
        (make_set(), {}),  # the hyperplanes interpolate: no radial terms
        (make_set(m=20, k=2, seed=3), {}),
        (make_set(m=20, k=2, seed=3), {"noise": 0.1}),
        (make_set(m=20, k=2, seed=3), {"noise": 0.1, "kernel": "gaussian"}),
    ],
)
def test_noise_gain_is_the_rms_jacobian_of_the_weights_over_the_examples(example_set, options):
    rig = fit(example_set, **options)
    spread = float(np.abs(rig.model.params).max())

    expected = _jacobian_rms(rig, 1e-6 * spread)

    assert rig.fit_report["noise_gain"] == pytest.approx(expected, rel=1e-6)

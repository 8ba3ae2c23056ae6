"""The compiled single-frame weight kernel (facecast.rig._kernel) against the numpy path.

The kernel must give eq. 3.8's weights to rounding, reject bad buffers with an error, keep NaN,
be safe under threads, and step aside cleanly when it is disabled or not built.
"""

from __future__ import annotations

import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from facecast.rig import FitError, InputError, Region, fit, fit_regions, rig_from_bytes
from facecast.rig import kernel as rig_kernel

from .test_fit import make_set

needs_kernel = pytest.mark.skipif(
    not rig_kernel.compiled(), reason="facecast.rig._kernel is not built (no C compiler?)"
)
EXTENDED = np.finfo(np.longdouble).eps < 1e-17  # x86 80-bit or quad long double


def quiet_fit(example_set, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(example_set, **options)


def frames_near(example_set, count: int, seed: int) -> np.ndarray:
    """(count, K, 3) mixes of the examples plus noise, then the examples themselves."""
    rng = np.random.default_rng(seed)
    m, k = example_set.num_examples, example_set.num_points
    source = example_set.source_points
    deltas = (source - source[0]).reshape(m, -1)
    mix = rng.uniform(0.0, 1.0, (count, m)) * (rng.random((count, m)) < 0.3)
    frames = (source[0].reshape(-1) + mix @ deltas).reshape(count, k, 3)
    frames += rng.normal(scale=0.05, size=frames.shape)
    return np.concatenate([frames, source])


def reference_weights(model, frames: np.ndarray) -> np.ndarray:
    """Eq. 3.7 and 3.8 term by term in extended precision, rounded to float64."""
    big = np.longdouble
    m, n = model.num_examples, model.params.shape[1]
    flat = frames.reshape(len(frames), -1).astype(big)
    p = flat @ model._project[:, m : m + n].astype(big) + model._offset[m : m + n].astype(big)
    linear = model.linear_coeffs[0].astype(big) + p @ model.linear_coeffs[1:].astype(big)
    diff = p[:, None, :] - model.params.astype(big)[None]
    t = np.sqrt((diff * diff).sum(axis=-1)) / model.alpha.astype(big)
    u = np.clip(2 - t, 0, None)
    v = np.clip(1 - t, 0, None)
    radial = ((u**3 - 4 * v**3) / 6) @ model.radial_coeffs.astype(big)
    return (linear + radial).astype(np.float64)


def single_frame_weights(rig, frames: np.ndarray) -> np.ndarray:
    return np.array([rig.weights(frame) for frame in frames])


def numpy_weights(rig, frames: np.ndarray) -> np.ndarray:
    """The numpy (BLAS) path's weights: the same rig rebuilt with the kernel disabled."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(rig_kernel.DISABLE_ENV, "1")
        numpy_rig = rig_from_bytes(rig.to_bytes())
    assert numpy_rig.model._kernel is None
    return numpy_rig.weights(frames)


@pytest.fixture(scope="module")
def big_set():
    # M = 41 and n > 8 leading components: two column panels, padding, a distance tail.
    return make_set(m=41, k=25, v=5, seed=3)


@pytest.fixture(scope="module")
def big_rig(big_set):
    return quiet_fit(big_set)


# -- agreement with the numpy path ------------------------------------------------------


@needs_kernel
def test_bspline_rigs_get_a_kernel_and_other_kernels_do_not(big_set, big_rig):
    assert big_rig.model._kernel is not None
    # Bounded rigs too: the kernel gives the unbounded weights, the box projection bounds them.
    assert quiet_fit(big_set, clamp="nonneg").model._kernel is not None
    assert quiet_fit(big_set, kernel="gaussian").model._kernel is None


@needs_kernel
@pytest.mark.parametrize(
    "options", [{}, {"noise": 0.05, "clamp": "nonneg"}], ids=["exact", "bounded"]
)
def test_batched_weights_equal_single_frame_weights_bit_for_bit(big_set, options):
    rig = quiet_fit(big_set, **options)
    frames = frames_near(big_set, 16, seed=12)

    np.testing.assert_array_equal(rig.weights(frames), single_frame_weights(rig, frames))


@needs_kernel
def test_bounded_kernel_weights_match_the_numpy_path(big_set):
    rig = quiet_fit(big_set, noise=0.05, clamp="nonneg")
    frames = frames_near(big_set, 16, seed=13)

    weights = rig.weights(frames)

    assert weights[:, 1:].min() >= 0.0
    np.testing.assert_allclose(weights, numpy_weights(rig, frames), rtol=0, atol=1e-9)


@needs_kernel
@pytest.mark.skipif(not EXTENDED, reason="long double is no wider than double here")
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    m=st.integers(3, 45),
    k=st.integers(2, 20),
    noise=st.sampled_from([0.0, 0.05]),
    seed=st.integers(0, 2**16),
)
def test_single_frame_weights_match_extended_precision_and_the_numpy_path(m, k, noise, seed):
    example_set = make_set(m=m, k=k, v=5, seed=seed)
    try:
        # Unbounded: the compiled kernel is the unbounded weights' path.
        rig = quiet_fit(example_set, noise=noise, clamp="none")
    except FitError:
        assume(False)
    frames = frames_near(example_set, 8, seed)

    kernel_weights = single_frame_weights(rig, frames)
    numpy_path = numpy_weights(rig, frames)
    reference = reference_weights(rig.model, frames)

    scale = max(1.0, float(np.abs(reference).max()))
    kernel_error = np.abs(kernel_weights - reference)
    numpy_error = np.abs(numpy_path - reference)
    assert kernel_error.max() <= 1e-13 * scale
    # The numpy path expands |p - p_j|^2 and can lose more than 1e-12 to cancellation on
    # such random rigs; the kernel is never farther from it than that loss.
    assert np.all(np.abs(kernel_weights - numpy_path) <= numpy_error + 1e-13 * scale)


@needs_kernel
def test_single_frame_weights_match_the_numpy_path_within_1e_12(big_set, big_rig):
    frames = frames_near(big_set, 32, seed=1)

    kernel_weights = single_frame_weights(big_rig, frames)

    np.testing.assert_allclose(kernel_weights, numpy_weights(big_rig, frames), rtol=0, atol=1e-12)


@needs_kernel
def test_cardinal_property_holds_through_the_kernel(big_set, big_rig):
    weights = single_frame_weights(big_rig, big_set.source_points)

    np.testing.assert_allclose(weights, np.eye(big_set.num_examples), atol=1e-10)


@needs_kernel
def test_the_same_frame_gives_the_same_bits_every_call_and_after_reload(big_set, big_rig):
    frame = frames_near(big_set, 1, seed=2)[0]
    first = big_rig.weights(frame)
    reloaded = rig_from_bytes(big_rig.to_bytes())

    again = [big_rig.weights(frame) for _ in range(50)]

    assert all(np.array_equal(first, w) for w in again)
    assert np.array_equal(first, reloaded.weights(frame))


@needs_kernel
def test_float32_and_float16_frames_equal_their_float64_widening(big_set, big_rig):
    frame = frames_near(big_set, 1, seed=4)[0]

    for dtype in (np.float32, np.float16):
        narrow = frame.astype(dtype)
        assert np.array_equal(big_rig.weights(narrow), big_rig.weights(narrow.astype(np.float64)))


@needs_kernel
def test_calibrated_rig_kernel_matches_its_numpy_path(big_set, big_rig):
    rng = np.random.default_rng(5)
    performer = big_set.source_neutral * 1.1 + rng.normal(
        scale=0.01, size=big_set.source_neutral.shape
    )
    rig = big_rig.calibrated(performer)
    frames = frames_near(big_set, 8, seed=6)

    np.testing.assert_allclose(
        single_frame_weights(rig, frames), numpy_weights(rig, frames), atol=1e-12
    )


@needs_kernel
def test_one_region_rig_single_frames_match_its_batches(big_set):
    names = big_set.names
    region = Region("all", range(big_set.num_points), names[1:], np.ones(big_set.num_vertices))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = fit_regions(big_set, [region])
    frames = frames_near(big_set, 8, seed=7)

    np.testing.assert_allclose(single_frame_weights(rig, frames), rig.weights(frames), atol=1e-12)


@needs_kernel
def test_the_generic_build_agrees_with_the_default_build(big_set, big_rig):
    from facecast.rig import _kernel

    model = big_rig.model
    m, n = model.num_examples, model.params.shape[1]
    arrays = (
        np.ascontiguousarray(model._project[:, m : m + n]),
        model._offset[m : m + n].copy(),
        np.ascontiguousarray(model.linear_coeffs[1:]),
        model.linear_coeffs[0].copy(),
        model.params,
        model.alpha,
        model.radial_coeffs,
    )
    generic = _kernel.BsplineKernel(*arrays, generic=True)
    frames = frames_near(big_set, 16, seed=12)

    weights = np.array([generic.weights(frame) for frame in frames])

    np.testing.assert_allclose(weights, single_frame_weights(big_rig, frames), rtol=0, atol=1e-13)


# -- bad input ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def handle(big_rig):
    return big_rig.model._kernel


@needs_kernel
@pytest.mark.parametrize(
    ("x", "error"),
    [
        (np.zeros(74), ValueError),  # 3K = 75
        (np.zeros(76), ValueError),
        (np.zeros((5, 15)), ValueError),
        (np.zeros(150)[::2], ValueError),  # not contiguous
        (np.zeros(75, dtype=np.float32), TypeError),  # evaluate takes float64 only
        (np.zeros(75, dtype=np.int64), TypeError),
        ([0.0] * 75, TypeError),
        (b"\0" * 600, TypeError),
    ],
)
def test_evaluate_rejects_bad_points(handle, x, error):
    with pytest.raises(error):
        handle.evaluate(x, np.empty(41))


@needs_kernel
@pytest.mark.parametrize(
    ("out", "error"),
    [
        (np.empty(40), ValueError),
        (np.empty(82)[::2], ValueError),
        (np.empty(41, dtype=np.float32), TypeError),
        (np.frombuffer(b"\0" * 328), ValueError),  # read-only
    ],
)
def test_evaluate_rejects_bad_output(handle, out, error):
    with pytest.raises(error):
        handle.evaluate(np.zeros(75), out)


@needs_kernel
@pytest.mark.parametrize(
    "points",
    [
        np.zeros(75),
        np.zeros((1, 25, 3)),
        np.zeros((25, 3), dtype=np.int32),
        np.zeros((25, 6))[:, :3],
    ],
)
def test_weights_rejects_anything_but_one_contiguous_float_frame(handle, points):
    with pytest.raises((TypeError, ValueError)):
        handle.weights(points)


@needs_kernel
def test_wrong_argument_counts_raise_type_error(handle):
    with pytest.raises(TypeError):
        handle.evaluate(np.zeros(75))
    with pytest.raises(TypeError):
        handle.weights()


@needs_kernel
@pytest.mark.parametrize(
    "change",
    [
        {"project": np.zeros((75, 3, 1))},
        {"param_offset": np.zeros(3)},
        {"linear": np.zeros((2, 2))},
        {"radial": np.zeros((41, 40))},
        {"centres": np.zeros((41, 3), dtype=np.float32)},
        {"alpha": np.zeros(41)},
        {"alpha": np.full(41, np.nan)},
    ],
)
def test_kernel_construction_validates_every_array(big_rig, change):
    from facecast.rig import _kernel

    model = big_rig.model
    m, n = model.num_examples, model.params.shape[1]
    arrays = {
        "project": np.ascontiguousarray(model._project[:, m : m + n]),
        "param_offset": model._offset[m : m + n].copy(),
        "linear": np.ascontiguousarray(model.linear_coeffs[1:]),
        "linear_offset": model.linear_coeffs[0].copy(),
        "centres": model.params,
        "alpha": model.alpha,
        "radial": model.radial_coeffs,
    }
    arrays.update(change)

    with pytest.raises((TypeError, ValueError)):
        _kernel.BsplineKernel(**arrays)


@needs_kernel
def test_rig_weights_still_converts_and_rejects_what_the_kernel_declines(big_set, big_rig):
    frame = frames_near(big_set, 1, seed=8)[0]
    expected = big_rig.weights(frame)

    np.testing.assert_array_equal(big_rig.weights(frame.tolist()), expected)
    np.testing.assert_array_equal(big_rig.weights(np.asfortranarray(frame)), expected)
    with pytest.raises(InputError):
        big_rig.weights(frame.reshape(-1))


@needs_kernel
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.float16])
def test_weights_with_a_limit_decline_frames_whose_sum_of_squares_is_past_it(handle, dtype):
    points = np.random.default_rng(2).uniform(-2, 2, (25, 3)).astype(dtype)
    squares = float(np.sum(points.astype(np.float64) ** 2))
    expected = handle.weights(points)
    np.testing.assert_array_equal(handle.weights(points, squares), expected)  # at the limit
    np.testing.assert_array_equal(handle.weights(points, np.inf), expected)
    assert handle.weights(points, np.nextafter(squares, 0.0)) is None
    assert handle.weights(points, np.nan) is None
    with pytest.raises(TypeError):
        handle.weights(points, "far")


@needs_kernel
def test_rig_weights_of_a_frame_past_the_shortcut_but_in_range_take_the_exact_check(
    big_set, big_rig
):
    # The kernel declines a frame past the range check's shortcut (``_fast2``); the general
    # path checks it exactly and gives the same weights as the batch path.
    # Every point at distance s from the centre c, away from the origin: RMS |x - c| = s
    # within the range R, RMS |x| = |c| + s past the shortcut's R - |c|.
    centre = big_rig._centre
    reach = np.sqrt(big_rig._range2 / big_set.num_points)
    s = reach - np.linalg.norm(centre) / 2
    frame = np.tile(centre + s * centre / np.linalg.norm(centre), (big_set.num_points, 1))
    assert float(np.sum(frame**2)) > big_rig._fast2
    big_rig._check_range(frame[None], single=True)  # in range all the same
    np.testing.assert_array_equal(big_rig.weights(frame), big_rig.weights(frame[None])[0])


# -- NaN and Inf --------------------------------------------------------------------------


@needs_kernel
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_points_propagate_through_the_kernel(handle, bad):
    x = np.zeros(75)
    x[7] = bad
    out = np.empty(41)

    total = handle.evaluate(x, out)

    assert not np.isfinite(total)
    assert not np.isfinite(out).all()
    assert handle.weights(x.reshape(25, 3)) is None


@needs_kernel
@pytest.mark.parametrize("bad", [np.nan, -np.inf])
def test_rig_weights_reports_non_finite_single_frames(big_set, big_rig, bad):
    frame = big_set.source_neutral.copy()
    frame[3, 1] = bad

    with pytest.raises(InputError) as caught:
        big_rig.weights(frame)

    assert caught.value.code == "non_finite"


# -- fallback -----------------------------------------------------------------------------


def test_disabling_the_kernel_gives_the_numpy_path(monkeypatch, big_set):
    monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    rig = quiet_fit(big_set)
    frames = frames_near(big_set, 4, seed=9)

    single = single_frame_weights(rig, frames)

    assert rig.model._kernel is None
    assert "numpy" in rig_kernel.description()
    np.testing.assert_allclose(single, rig.weights(frames), atol=1e-12)
    np.testing.assert_allclose(
        single_frame_weights(rig, big_set.source_points), np.eye(41), atol=1e-10
    )


def test_a_missing_extension_gives_the_numpy_path(monkeypatch, big_set):
    monkeypatch.setattr(rig_kernel, "_kernel", None)
    rig = quiet_fit(big_set)

    assert not rig_kernel.compiled()
    assert rig.model._kernel is None
    assert "not built" in rig_kernel.description()
    frame = frames_near(big_set, 1, seed=10)[0]
    np.testing.assert_allclose(rig.weights(frame), rig.weights(frame[None])[0], atol=0)


@needs_kernel
def test_description_names_the_compiled_kernel(monkeypatch):
    monkeypatch.delenv(rig_kernel.DISABLE_ENV, raising=False)

    assert rig_kernel.description().startswith("compiled")


# -- threads ------------------------------------------------------------------------------


@needs_kernel
def test_many_threads_at_once_get_the_single_threaded_answers(big_set, big_rig):
    frames = frames_near(big_set, 64, seed=11)
    expected = single_frame_weights(big_rig, frames)
    threads = 8
    start = threading.Barrier(threads)

    def work(offset: int) -> bool:
        start.wait(timeout=10)
        ok = True
        for round_ in range(20):
            for i in range(len(frames)):
                j = (i + offset + round_) % len(frames)
                ok &= np.array_equal(big_rig.weights(frames[j]), expected[j])
        return ok

    with ThreadPoolExecutor(threads) as pool:
        results = list(pool.map(work, range(threads)))

    assert all(results)

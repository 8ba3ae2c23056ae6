"""The compiled row blend ``_kernel.blend_rows``: weights @ basis to float32 rounding."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig import fit
from facecast.rig import kernel as rig_kernel
from facecast.rig.blend import Placement

from .test_blend import make_set, sparse_weights

pytestmark = pytest.mark.skipif(not rig_kernel.compiled(), reason="extension not built")
PATHS = [pytest.param(False, id="dispatched"), pytest.param(True, id="generic")]
M = 20
UNIT = 2.0**-24  # float32's unit roundoff


def make_weights(frames: int, kind: str, seed: int = 0) -> np.ndarray:
    """(frames, M) float32: every weight ("dense"), ~a quarter ("sparse"), or both by turns."""
    rng = np.random.default_rng(seed)
    weights = rng.normal(size=(frames, M)).astype(np.float32)
    sparse = rng.random((frames, M)) < 0.75
    if kind == "mixed":
        sparse[::2] = False
    if kind != "dense":
        weights[sparse] = 0.0
    weights[:, 0] = 1.0
    return weights


def make_basis(cols: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(M, cols)).astype(np.float32)


def blend(weights, basis, generic=False, tile=0) -> np.ndarray:
    out = np.full((weights.shape[0], basis.shape[1]), np.nan, np.float32)
    rig_kernel._kernel.blend_rows(weights, basis, out, None, generic, tile)
    return out


def assert_within_float32_bound(out, weights, basis):
    """|out - exact| <= n u sum_m |w_m b_m| (n: a frame's non-zero weights; Higham's gamma_n)."""
    exact = weights.astype(np.float64) @ basis.astype(np.float64)
    terms = np.count_nonzero(weights, axis=1)[:, None]
    scale = np.abs(weights.astype(np.float64)) @ np.abs(basis.astype(np.float64))
    bound = terms * UNIT / (1 - terms * UNIT) * scale
    assert np.all(np.abs(out - exact) <= bound)


@pytest.mark.parametrize("generic", PATHS)
@pytest.mark.parametrize("tile", [0, 40])
@pytest.mark.parametrize("kind", ["dense", "sparse", "mixed"])
@pytest.mark.parametrize("frames", range(1, 34))
def test_product_is_weights_at_basis_within_float32_rounding(frames, kind, tile, generic):
    weights, basis = make_weights(frames, kind, seed=frames), make_basis(1001)
    assert_within_float32_bound(blend(weights, basis, generic, tile), weights, basis)


@pytest.mark.parametrize("generic", PATHS)
@pytest.mark.parametrize("cols", [1, 7, 9, 31, 33, 517, 1037])
def test_odd_column_counts_are_blended_to_the_last_column(cols, generic):
    weights, basis = make_weights(5, "mixed"), make_basis(cols)
    assert_within_float32_bound(blend(weights, basis, generic), weights, basis)


@pytest.mark.parametrize("generic", PATHS)
def test_frames_weighing_only_the_neutral_are_the_neutral_bit_for_bit(generic):
    weights = make_weights(7, "mixed")
    weights[[1, 4, 5], 1:] = 0.0
    basis = make_basis(531)
    out = blend(weights, basis, generic, 64)
    np.testing.assert_array_equal(out[[1, 4, 5]], np.broadcast_to(basis[0], (3, 531)))
    assert_within_float32_bound(out, weights, basis)


@pytest.mark.parametrize("generic", PATHS)
def test_a_frame_of_zero_weights_is_zero(generic):
    weights = make_weights(3, "dense")
    weights[1] = 0.0
    out = blend(weights, make_basis(100), generic)
    np.testing.assert_array_equal(out[1], np.zeros(100, np.float32))


@pytest.mark.parametrize("generic", PATHS)
def test_a_row_no_frame_weighs_is_not_read(generic):
    weights, basis = make_weights(4, "dense"), make_basis(300)
    weights[:, 6] = 0.0
    basis[6] = np.nan
    assert np.isfinite(blend(weights, basis, generic)).all()


@pytest.mark.parametrize("generic", PATHS)
def test_a_nan_weight_reaches_its_frame_only(generic):
    weights = make_weights(3, "dense")
    weights[2, 3] = np.nan
    out = blend(weights, make_basis(50), generic)
    assert np.isnan(out[2]).all() and np.isfinite(out[:2]).all()


@pytest.mark.parametrize("generic", PATHS)
@pytest.mark.parametrize("tile", [0, 24, 40, 1000])
def test_a_column_does_not_depend_on_the_columns_beside_it(tile, generic):
    # What lets Rig.blend's moving and full outputs agree bit for bit whatever the tiles.
    weights, basis = make_weights(6, "mixed"), make_basis(777)
    columns = np.array([0, 3, 8, 9, 10, 100, 511, 512, 513, 776])
    whole = blend(weights, basis, generic, tile)
    part = blend(weights, np.ascontiguousarray(basis[:, columns]), generic, tile)
    np.testing.assert_array_equal(part.view(np.uint32), whole[:, columns].view(np.uint32))


@pytest.mark.parametrize("generic", PATHS)
@pytest.mark.parametrize("tile", [0, 24])
def test_runs_place_the_product_in_a_wider_output_bit_for_bit(tile, generic):
    weights, basis = make_weights(5, "mixed"), make_basis(300)
    columns = np.concatenate([np.arange(3, 40), [41, 43], np.arange(100, 361)])
    placement = Placement.of(columns)
    out = np.full((5, 400), -7.0, np.float32)
    rig_kernel._kernel.blend_rows(weights, basis, out, placement.runs, generic, tile)
    product = blend(weights, basis, generic, tile)
    np.testing.assert_array_equal(out[:, columns].view(np.uint32), product.view(np.uint32))
    still = np.setdiff1d(np.arange(400), columns)
    np.testing.assert_array_equal(out[:, still], np.full((5, still.size), -7.0, np.float32))


@pytest.mark.parametrize("generic", PATHS)
@pytest.mark.parametrize("tile", [0, 1, 3, 24])
def test_runs_in_any_order_and_length_place_their_columns_bit_for_bit(tile, generic):
    # Runs whose basis columns follow one another are tiled together (a span, through a
    # scratch tile), others each on its own; empty runs, runs across tiles, in any order.
    weights, basis = make_weights(4, "mixed"), make_basis(60)
    runs = np.array([[0, 10, 5], [5, 0, 3], [8, 70, 0], [20, 30, 7], [8, 50, 12],
                     [27, 90, 33], [40, 123, 1]], np.int64)  # fmt: skip
    out = np.full((4, 130), -7.0, np.float32)
    rig_kernel._kernel.blend_rows(weights, basis, out, runs, generic, tile)
    product = blend(weights, basis, generic, tile)
    expected = np.full((4, 130), -7.0, np.float32)
    for c0, d0, count in runs:
        expected[:, d0 : d0 + count] = product[:, c0 : c0 + count]
    np.testing.assert_array_equal(out.view(np.uint32), expected.view(np.uint32))


def test_place_columns_copies_each_run_bit_for_bit_and_leaves_the_rest():
    src = make_basis(60)[:3]
    src[1, 7] = np.nan
    src[2, 0] = -0.0
    runs = np.array([[0, 10, 5], [5, 0, 3], [8, 70, 0], [20, 30, 7], [27, 90, 33]], np.int64)
    out = np.full((3, 130), -7.0, np.float32)
    rig_kernel.place_columns()(src, out, runs)
    expected = np.full((3, 130), -7.0, np.float32)
    for c0, d0, count in runs:
        expected[:, d0 : d0 + count] = src[:, c0 : c0 + count]
    np.testing.assert_array_equal(out.view(np.uint32), expected.view(np.uint32))


def test_place_columns_refuses_what_it_cannot_copy():
    place = rig_kernel._kernel.place_columns
    src, out = make_basis(8)[:2], np.zeros((2, 12), np.float32)
    with pytest.raises(ValueError, match=r"runs\[0\]: \(src column, .* inside src \(8 columns\)"):
        place(src, out, np.array([[0, 0, 9]], np.int64))
    with pytest.raises(ValueError, match="as many rows"):
        place(src, np.zeros((3, 12), np.float32), np.zeros((0, 3), np.int64))
    with pytest.raises(ValueError, match="must not overlap"):
        place(src, src, np.zeros((0, 3), np.int64))
    with pytest.raises(TypeError, match="float32"):
        place(src.astype(np.float64), out, np.zeros((0, 3), np.int64))
    with pytest.raises(TypeError, match="3 arguments"):
        place(src, out)


def test_placement_finds_the_runs_of_consecutive_columns():
    placement = Placement.of(np.array([3, 4, 5, 9, 11, 12]))
    np.testing.assert_array_equal(placement.runs, [[0, 3, 3], [3, 9, 1], [4, 11, 2]])
    assert Placement.of(np.array([], np.int64)).runs.shape == (0, 3)


@pytest.mark.parametrize(
    ("runs", "error", "match"),
    [
        (np.array([[0, 0, 9]]), ValueError, r"runs\[0\]: .* inside basis \(8 columns\)"),
        (np.array([[0, 0, 4], [4, 9, 4]]), ValueError, r"runs\[1\]: .* and out \(12\)"),
        (np.array([[0, -1, 2]]), ValueError, r"runs\[0\]"),
        (np.array([[0, 0, 4]], np.int32), TypeError, "runs: expected int64"),
        (np.array([0, 0, 4]), ValueError, r"runs: expected a C-contiguous \(R, 3\)"),
    ],
)
def test_runs_outside_the_arrays_are_refused(runs, error, match):
    weights, basis = make_weights(2, "dense"), make_basis(8)
    with pytest.raises(error, match=match):
        rig_kernel._kernel.blend_rows(weights, basis, np.zeros((2, 12), np.float32), runs)


def test_without_runs_out_must_have_the_basis_columns():
    weights, basis = make_weights(2, "dense"), make_basis(8)
    with pytest.raises(ValueError, match=r"out: expected shape \(B, C\)"):
        rig_kernel._kernel.blend_rows(weights, basis, np.zeros((2, 12), np.float32), None)


def test_the_generic_path_agrees_with_the_dispatched_one():
    weights, basis = make_weights(9, "mixed"), make_basis(1001)
    np.testing.assert_allclose(
        blend(weights, basis, True), blend(weights, basis), rtol=0, atol=1e-5
    )


def test_an_empty_batch_or_basis_is_nothing_to_do():
    blend(np.zeros((0, M), np.float32), make_basis(10))
    assert blend(make_weights(2, "dense"), make_basis(0)).shape == (2, 0)


@pytest.mark.parametrize(
    ("weights", "basis", "out", "error", "match"),
    [
        ((2, M), (M, 8), (2, 8), TypeError, "weights: expected float32"),
        ((2, M), (M + 1, 8), (2, 8), ValueError, "basis: expected one row per weight"),
        ((2, M), (M, 8), (3, 8), ValueError, r"out: expected shape \(B, C\)"),
        ((2, M), (M, 8), (2, 9), ValueError, r"out: expected shape \(B, C\)"),
        ((M,), (M, 8), (1, 8), ValueError, "weights: expected a 2-D array"),
    ],
)
def test_bad_arrays_are_refused(weights, basis, out, error, match):
    dtype = np.float64 if error is TypeError else np.float32
    with pytest.raises(error, match=match):
        rig_kernel._kernel.blend_rows(
            np.zeros(weights, dtype), np.zeros(basis, np.float32), np.zeros(out, np.float32)
        )


def test_strided_read_only_or_overlapping_arrays_are_refused():
    weights, basis = make_weights(2, "dense"), make_basis(16)
    out = np.empty((2, 16), np.float32)
    with pytest.raises(ValueError, match="C-contiguous"):
        rig_kernel._kernel.blend_rows(weights, make_basis(32)[:, ::2], out)
    out.flags.writeable = False
    with pytest.raises(ValueError, match=r"read-only|writable"):
        rig_kernel._kernel.blend_rows(weights, basis, out)
    with pytest.raises(ValueError, match="must not overlap"):
        rig_kernel._kernel.blend_rows(weights, basis, basis[:2])
    with pytest.raises(TypeError, match="3 to 6 positional arguments"):
        rig_kernel._kernel.blend_rows(weights, basis)


@pytest.mark.parametrize("disabled", [False, True], ids=["row-blend", "numpy"])
@pytest.mark.parametrize("rows", [1, 2, 3, 5, 17])
def test_rig_moving_blend_is_its_full_blend_bit_for_bit_either_way(monkeypatch, disabled, rows):
    if disabled:
        monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    rig = fit(make_set())
    for used in (1, 3, 8):
        weights = sparse_weights(rows, used)
        full = rig.blend(weights)
        moving = rig.blend(weights, moving=True)
        np.testing.assert_array_equal(
            moving.view(np.uint32), full[:, rig.moving_vertices].view(np.uint32)
        )
        dense = weights.copy()
        dense[:, 0] = 1.0
        expected = (dense @ rig.blend_basis.astype(np.float64)).reshape(full.shape)
        np.testing.assert_allclose(full, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("disabled", [False, True], ids=["row-blend", "numpy"])
@pytest.mark.parametrize("rows", [1, 2, 7, 16])
def test_rig_moving_blend_of_dense_weights_is_its_full_blend_bit_for_bit(
    monkeypatch, disabled, rows
):
    # Dense weights: every row, so BLAS and the row blend both come into play by batch size.
    if disabled:
        monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    rig = fit(make_set(seed=3))
    weights = np.random.default_rng(rows).normal(size=(rows, rig.num_examples))
    full = rig.blend(weights)
    moving = rig.blend(weights, moving=True)
    np.testing.assert_array_equal(
        moving.view(np.uint32), full[:, rig.moving_vertices].view(np.uint32)
    )

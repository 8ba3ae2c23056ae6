"""The blend's two economies: moving vertices only (lossless) and sparse weights (rounding)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse

from facecast.rig import ExampleSet, InputError, fit
from facecast.rig import kernel as rig_kernel
from facecast.rig.blend import Placement, blend_into, blend_plan
from facecast.rig.sources.ict import ict_animation, ict_example_set, locate_ict

M, K, V = 9, 6, 50
#: Vertices no example moves in the synthetic set (a head's back, say).
STILL = np.array([0, 7, 8, 9, 30, 49])
ARCHIVE = locate_ict()


def make_set(seed=0) -> ExampleSet:
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(K, 3))
    source = neutral + np.concatenate([np.zeros((1, K, 3)), rng.normal(size=(M - 1, K, 3))])
    target_neutral = rng.normal(size=(V, 3))
    deltas = rng.normal(size=(M - 1, V, 3))
    deltas[:, STILL] = 0.0
    deltas[:, 20] = 0.0
    deltas[4, 20, 2] = 0.25  # moved in one coordinate by one example: still moving
    target = target_neutral + np.concatenate([np.zeros((1, V, 3)), deltas])
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    return ExampleSet([f"e{i}" if i else "neutral" for i in range(M)], source, target, faces)


@pytest.fixture(scope="module")
def rig():
    return fit(make_set())


def sparse_weights(rows: int, used: int, seed: int = 1) -> np.ndarray:
    """(rows, M) weights with ``used`` non-zero non-neutral weights per frame."""
    rng = np.random.default_rng(seed)
    weights = np.zeros((rows, M))
    for row in weights:
        row[1 + rng.choice(M - 1, size=used, replace=False)] = rng.random(used)
    weights[:, 0] = 1.0 - weights[:, 1:].sum(axis=1)
    return weights


def test_moving_vertices_are_those_some_example_moves(rig):
    expected = np.setdiff1d(np.arange(V), STILL)
    np.testing.assert_array_equal(rig.moving_vertices, expected)


def test_still_vertices_are_the_target_neutral_bit_for_bit(rig):
    vertices = rig.blend(sparse_weights(5, 3))
    neutral = np.broadcast_to(rig.target_neutral[STILL], (5, STILL.size, 3))
    np.testing.assert_array_equal(vertices[:, STILL], neutral)


@pytest.mark.parametrize("rows", [1, 2, 4, 17])
@pytest.mark.parametrize("used", [1, 3, M - 1])
def test_moving_blend_equals_full_blend_on_moving_vertices_bit_for_bit(rig, rows, used):
    weights = sparse_weights(rows, used)
    full = rig.blend(weights)
    moving = rig.blend(weights, moving=True)
    assert moving.dtype == np.float32
    assert moving.shape == (rows, rig.moving_vertices.size, 3)
    np.testing.assert_array_equal(
        moving.view(np.uint32), full[:, rig.moving_vertices].view(np.uint32)
    )


def test_moving_blend_of_one_frame_equals_its_full_blend(rig):
    weights = sparse_weights(1, 2)[0]
    out = np.empty((rig.moving_vertices.size, 3), np.float32)
    result = rig.blend(weights, out=out, moving=True)
    assert result is out
    np.testing.assert_array_equal(out, rig.blend(weights)[rig.moving_vertices])


def test_moving_blend_refuses_an_output_of_the_full_size(rig):
    with pytest.raises(InputError, match="out must be"):
        rig.blend(sparse_weights(1, 2)[0], out=np.empty((V, 3), np.float32), moving=True)


def test_calibrated_rig_shares_the_moving_vertices(rig):
    calibrated = rig.calibrated(rig.source_neutral + 0.01)
    np.testing.assert_array_equal(calibrated.moving_vertices, rig.moving_vertices)
    weights = sparse_weights(3, 2)
    np.testing.assert_array_equal(
        calibrated.blend(weights, moving=True), rig.blend(weights, moving=True)
    )


@pytest.mark.parametrize("rows", [1, 3, 16])
@pytest.mark.parametrize("used", [1, 2, 3])
def test_sparse_blend_equals_dense_product_within_rounding(rig, rows, used):
    weights = sparse_weights(rows, used, seed=rows + used)
    dense = weights.copy()
    dense[:, 0] = 1.0
    expected = (dense @ rig.blend_basis.astype(np.float64)).reshape(rows, V, 3)
    np.testing.assert_allclose(rig.blend(weights), expected, rtol=1e-5, atol=1e-5)


@pytest.fixture
def without_kernel(monkeypatch):
    """numpy's and scipy's products only (as without the extension)."""
    monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")


def _plan_weights(plan: str) -> np.ndarray:
    """(B, 12) weights that ``blend_plan`` multiplies the way ``plan`` says."""
    rng = np.random.default_rng(3)
    if plan == "dense":  # every row used by every frame
        return rng.random((4, 12)).astype(np.float32)
    if plan == "rows":  # two frames, every row
        return rng.random((2, 12)).astype(np.float32)
    weights = np.zeros((16, 12), np.float32)
    weights[:, 0] = 1.0
    if plan == "gathered":  # 16 frames sharing 3 rows: 48 non-zeros, 9 rows gathered
        weights[:, [2, 7]] = rng.random((16, 2))
    else:  # one frame, two rows
        weights = weights[:1]
        weights[0, 5] = 0.5
    return weights


@pytest.mark.parametrize(
    "plan",
    [
        pytest.param(
            "rows",
            marks=pytest.mark.skipif(
                rig_kernel.blend_rows() is None, reason="extension not built or disabled"
            ),
        ),
        "dense",
        "gathered",
        "sparse",
    ],
)
def test_every_blend_plan_equals_the_dense_product_within_rounding(plan, monkeypatch):
    if plan != "rows":  # numpy's and scipy's products: as without the extension
        monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    weights = _plan_weights(plan)
    basis = np.random.default_rng(4).normal(size=(12, 300)).astype(np.float32)
    assert blend_plan(weights)[0] == plan
    result = blend_into(weights, basis, np.empty((len(weights), 300), np.float32))
    expected = weights.astype(np.float64) @ basis.astype(np.float64)
    np.testing.assert_allclose(result, expected, rtol=1e-5, atol=1e-5)
    # Without ``out`` the same product comes back as a new float32 array, bit for bit.
    fresh = blend_into(weights, basis, None)
    assert fresh.dtype == np.float32 and fresh.shape == result.shape
    np.testing.assert_array_equal(fresh, result)


@pytest.mark.skipif(not rig_kernel.compiled(), reason="extension not built")
@pytest.mark.parametrize("batch", [2, 6, 16])
def test_with_the_extension_small_batches_take_the_row_blend_large_ones_blas(batch):
    rng = np.random.default_rng(batch)
    dense = rng.random((batch, 56)).astype(np.float32)
    bounded = np.where(rng.random((batch, 56)) < 0.5, dense, 0).astype(np.float32)
    assert blend_plan(dense, compiled=True)[0] == ("rows" if batch <= 6 else "dense")
    assert blend_plan(bounded, compiled=True)[0] == "rows"
    # One frame: BLAS's matrix-vector product where nearly every row is used, else the rows.
    assert blend_plan(dense[:1], compiled=True)[0] == "dense"
    assert blend_plan(bounded[:1], compiled=True)[0] == "rows"


@pytest.mark.usefixtures("without_kernel")
def test_sparse_plan_adds_each_frames_rows_as_scipys_csr_product_does():
    # Frames 1 and 3 weigh only the neutral row: empty CSR rows between full ones.
    weights = np.zeros((4, 12), np.float32)
    weights[:, 0] = 1.0
    weights[0, [3, 7]] = [0.25, 0.5]
    weights[2, 11] = 0.75
    basis = np.random.default_rng(5).normal(size=(12, 300)).astype(np.float32)
    assert blend_plan(weights)[0] == "sparse"
    result = blend_into(weights, basis, np.empty((4, 300), np.float32))
    np.testing.assert_array_equal(result, scipy.sparse.csr_array(weights) @ basis)


@pytest.mark.usefixtures("without_kernel")
def test_a_sparse_frame_reads_only_its_rows():
    plan, used = blend_plan(_plan_weights("sparse"))
    assert plan == "sparse"
    np.testing.assert_array_equal(used, [0, 5])


@pytest.mark.ict
@pytest.mark.skipif(ARCHIVE is None, reason="ICT-FaceKit not found ($FACECAST_ICT)")
def test_ict_moving_vertices_stream_a_performance_losslessly():
    example_set = ict_example_set(ARCHIVE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = fit(example_set, noise=0.01, clamp="nonneg")
    _, animation = ict_animation(example_set, seconds=0.5, fps=30.0, seed=5)
    weights = rig.weights(animation.points)
    # Bounded weights are sparse: a frame alone is blended from its non-zero rows only
    # (the compiled row blend, or without it scipy's CSR product).
    for compiled in (True, False):
        assert all(
            blend_plan(w[None].astype(np.float32), compiled=compiled)[0] in ("rows", "sparse")
            for w in weights
        )
    moving = rig.moving_vertices
    assert 0 < moving.size < rig.num_vertices
    full = rig.blend(weights)
    np.testing.assert_array_equal(rig.blend(weights, moving=True), full[:, moving])
    still = np.setdiff1d(np.arange(rig.num_vertices), moving)
    np.testing.assert_array_equal(
        full[:, still], np.broadcast_to(rig.target_neutral[still], (len(weights), still.size, 3))
    )
    for frame in weights[:3]:
        np.testing.assert_array_equal(rig.blend(frame, moving=True), rig.blend(frame)[moving])


def test_without_the_extension_blends_take_numpys_products(monkeypatch):
    monkeypatch.setattr(rig_kernel, "_kernel", None)
    weights = _plan_weights("rows")
    basis = np.random.default_rng(6).normal(size=(12, 300)).astype(np.float32)
    assert blend_plan(weights)[0] == "dense"
    result = blend_into(weights, basis, None)
    np.testing.assert_array_equal(result, weights @ basis)


@pytest.mark.parametrize("plan", ["dense", "gathered", "sparse"])
def test_numpys_products_are_scattered_into_a_placement(plan, monkeypatch):
    monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    weights = _plan_weights(plan)
    basis = np.random.default_rng(7).normal(size=(12, 300)).astype(np.float32)
    columns = np.concatenate([np.arange(10, 110), np.arange(200, 400)])
    out = np.zeros((len(weights), 450), np.float32)
    blend_into(weights, basis, out, placement=Placement.of(columns))
    np.testing.assert_array_equal(out[:, columns], blend_into(weights, basis, None))
    assert not out[:, :10].any() and not out[:, 400:].any()

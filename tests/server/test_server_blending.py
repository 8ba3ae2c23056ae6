"""The blend batcher: frames of many sessions on one rig blended together, each into its buffer."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from _server_helpers import frame_points, tiny_rig

from facecast.rig import kernel as rig_kernel
from facecast.rig.errors import InputError
from facecast.server.compute.blending import (
    MAX_BATCH,
    MIN_BATCH,
    MIN_BATCH_WITHOUT_KERNEL,
    BlendBatcher,
    min_batch,
)

pytestmark = pytest.mark.anyio


@pytest.fixture(scope="module")
def big_rig():
    return tiny_rig(num_vertices=3000)


@pytest.fixture
def executor():
    with ThreadPoolExecutor(2) as pool:
        yield pool


def _weights(rig, count: int) -> list[np.ndarray]:
    return [rig.weights(frame_points(rig, i)) for i in range(count)]


@pytest.mark.parametrize("kernel", [True, False], ids=["row-blend", "numpy"])
@pytest.mark.parametrize("concurrency", [1, 2])
@pytest.mark.parametrize("count", [1, 2, 3, MIN_BATCH_WITHOUT_KERNEL, MAX_BATCH + 3])
async def test_each_frame_gets_its_own_blend_in_f32(
    big_rig, executor, count, concurrency, kernel, monkeypatch
):
    if not kernel:
        monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    batcher = BlendBatcher(executor, concurrency=concurrency)
    weights = _weights(big_rig, count)
    outs = [np.empty((big_rig.num_vertices, 3), np.float32) for _ in weights]

    await asyncio.gather(
        *(batcher.blend(big_rig, w, o) for w, o in zip(weights, outs, strict=True))
    )

    for w, out in zip(weights, outs, strict=True):
        np.testing.assert_allclose(out, big_rig.blend(w), rtol=1e-6, atol=1e-6)
    assert batcher.frames == count and batcher.active_groups == 0


async def test_f16_buffers_get_the_blend_cast_to_f16(big_rig, executor):
    batcher = BlendBatcher(executor)
    weights = _weights(big_rig, MIN_BATCH + 1)
    outs = [np.empty((big_rig.num_vertices, 3), np.float16) for _ in weights]

    await asyncio.gather(
        *(batcher.blend(big_rig, w, o) for w, o in zip(weights, outs, strict=True))
    )

    for w, out in zip(weights, outs, strict=True):
        expected = big_rig.blend(w).astype(np.float16)
        np.testing.assert_allclose(out.astype(np.float32), expected.astype(np.float32), rtol=1e-3)


async def test_frames_waiting_together_are_blended_in_one_batch(big_rig, executor):
    batcher = BlendBatcher(executor)
    weights = _weights(big_rig, 9)
    outs = [np.empty((big_rig.num_vertices, 3), np.float32) for _ in weights]

    await asyncio.gather(
        *(batcher.blend(big_rig, w, o) for w, o in zip(weights, outs, strict=True))
    )

    assert (batcher.batches, batcher.frames) == (1, 9)


async def test_a_calibrated_rig_shares_the_batch_of_its_base_rig(big_rig, executor):
    calibrated = big_rig.calibrated(frame_points(big_rig, 50))
    batcher = BlendBatcher(executor)
    weights = _weights(big_rig, MIN_BATCH)
    outs = [np.empty((big_rig.num_vertices, 3), np.float32) for _ in weights]
    rigs = [big_rig, calibrated] * (MIN_BATCH // 2)

    await asyncio.gather(
        *(batcher.blend(r, w, o) for r, w, o in zip(rigs, weights, outs, strict=True))
    )

    assert batcher.batches == 1
    np.testing.assert_allclose(outs[1], calibrated.blend(weights[1]), rtol=1e-6, atol=1e-6)


async def test_a_failing_blend_raises_in_every_caller_and_the_next_batch_works(big_rig, executor):
    batcher = BlendBatcher(executor)
    bad = np.zeros(big_rig.num_examples + 1)
    out = np.empty((big_rig.num_vertices, 3), np.float32)

    with pytest.raises(InputError):
        await batcher.blend(big_rig, bad, out)
    await batcher.blend(big_rig, _weights(big_rig, 1)[0], out)

    np.testing.assert_allclose(out, big_rig.blend(_weights(big_rig, 1)[0]), rtol=1e-6, atol=1e-6)
    assert batcher.active_groups == 0


def test_small_batches_are_blended_together_with_the_row_blend_only(monkeypatch):
    expected = MIN_BATCH if rig_kernel.blend_rows() is not None else MIN_BATCH_WITHOUT_KERNEL
    assert min_batch() == expected
    monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    assert min_batch() == MIN_BATCH_WITHOUT_KERNEL


def test_concurrency_below_one_is_refused(executor):
    with pytest.raises(ValueError, match="concurrency"):
        BlendBatcher(executor, concurrency=0)

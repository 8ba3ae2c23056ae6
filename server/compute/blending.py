"""Vertex blends of all streaming sessions on one rig, batched: one pass over the basis per batch.

Sessions hand in weights and an output buffer; the blends run in the clone pool, one
batch at a time per blend basis. Arrays only: no sockets, no sessions, no math of its own
(``Rig.blend`` does the blending).
"""

from __future__ import annotations

import asyncio
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facecast.rig.kernel import blend_rows, to_float16

from .stages import CPU_CLOCK, StageTimes

__all__ = ["MAX_BATCH", "MIN_BATCH", "MIN_BATCH_WITHOUT_KERNEL", "BlendBatcher", "min_batch"]

#: Most frames blended in one ``Rig.blend`` call (bounds the scratch buffer: ICT's
#: 27k vertices take 320 kB a frame).
MAX_BATCH = 32
#: Fewer waiting frames are blended one by one. With the compiled row blend
#: (``rig.kernel.blend_rows``, which reads each used basis row once per batch) a batch costs
#: less per frame than single blends from 2 frames on (ICT's moving columns, one thread:
#: exact weights 1 frame 510 us, 2 frames 300 us each, 4 frames 200; bounded 322, 156,
#: 135), so every batch is blended together.
MIN_BATCH = 2
#: The same without the extension: a (B, M) @ (M, 3V) product of a small B costs BLAS a
#: copy ("packing") of the whole basis, so on ICT's (56, 80157) basis a batch of 2 or 3
#: costs more per frame than single blends; from 4 on batches win (measured, one OpenBLAS
#: thread, cold cache: 1 frame 740 us, 4 frames 590 us each, 8 frames 370, 16 frames 240).
MIN_BATCH_WITHOUT_KERNEL = 4


def min_batch() -> int:
    """Fewest waiting frames blended together (``MIN_BATCH`` with the row blend, else 4)."""
    return MIN_BATCH if blend_rows() is not None else MIN_BATCH_WITHOUT_KERNEL


@dataclass
class _Request:
    weights: np.ndarray  # (M,) float
    out: np.ndarray  # (V, 3) or (N, 3) (moving) float16 or float32, C-contiguous
    done: asyncio.Future[None]


@dataclass
class _Group:
    """Requests for one blend basis and the runners (at most ``concurrency``) serving them."""

    rig: Any
    moving: bool  # every request of the group blends only the rig's moving vertices
    waiting: list[_Request] = field(default_factory=list)
    runners: set[asyncio.Task[None]] = field(default_factory=set)


class _Scratch:
    """One runner's (B, V, 3) float32 blend output, grown on demand."""

    def __init__(self) -> None:
        self.array: np.ndarray | None = None

    def blend(self, rig: Any, batch: list[_Request], moving: bool) -> tuple[float, float]:
        """Fill every request's ``out`` (worker thread; numpy releases the GIL in matmul).

        Returns the CPU seconds (this worker thread's) spent blending and casting to the
        wire dtype.
        """
        clock = CPU_CLOCK
        started = clock()
        cast = 0.0
        together = len(batch) >= min_batch()
        rows = len(batch) if together else 1
        if self.array is None or self.array.shape[0] < rows:
            self.array = np.empty((rows, *batch[0].out.shape), np.float32)
        if not together:
            for request in batch:
                if request.out.dtype == np.float32:
                    rig.blend(request.weights, out=request.out, moving=moving)
                else:
                    frame = rig.blend(request.weights, out=self.array[0], moving=moving)
                    cast -= clock()
                    to_float16(frame, request.out)
                    cast += clock()
            return clock() - started - cast, cast
        weights = np.stack([request.weights for request in batch])
        vertices = rig.blend(weights, out=self.array[: len(batch)], moving=moving)
        blended = clock()
        for request, frame in zip(batch, vertices, strict=True):
            if request.out.dtype == np.float32:
                np.copyto(request.out, frame)
            else:
                to_float16(frame, request.out)
        return blended - started, clock() - blended


class BlendBatcher:
    """Blend frames of many sessions together when they share a rig's blend basis.

    A group's runner takes every frame waiting when it starts a batch, so batches grow
    exactly when frames arrive faster than single blends finish, and a lone frame is
    never held back. Rigs derived from one another (calibration) share a basis and so
    a group.

    Parameters
    ----------
    executor : the clone thread pool
    concurrency : int
        Batches of one basis running at once (the pool's thread count: a lone rig can
        then use every clone thread).
    stages : StageTimes, optional
        Where the blend and cast times and the batch sizes are added.
    """

    def __init__(
        self, executor: Executor, *, concurrency: int = 1, stages: StageTimes | None = None
    ) -> None:
        if concurrency < 1:
            raise ValueError(f"concurrency must be >= 1, got {concurrency}")
        self._executor = executor
        self._concurrency = concurrency
        self._stages = stages
        self._groups: dict[tuple[int, tuple[int, ...], bool], _Group] = {}
        #: Batches run and frames blended so far (single blends count as batches of one).
        self.batches = 0
        self.frames = 0

    async def blend(
        self, rig: Any, weights: np.ndarray, out: np.ndarray, *, moving: bool = False
    ) -> None:
        """Write ``rig.blend(weights, moving=moving)`` into ``out`` (V, 3) or (N, 3).

        ``out`` is float16 or float32. Raises whatever ``rig.blend`` raises for this
        frame's batch.
        """
        basis = rig.blend_basis
        key = (basis.__array_interface__["data"][0], basis.shape, moving)
        loop = asyncio.get_running_loop()
        request = _Request(weights, out, loop.create_future())
        group = self._groups.get(key)
        if group is None:
            # The group keeps ``rig`` (so its basis) alive while it exists: the key's
            # address cannot be reused by another basis meanwhile.
            group = self._groups[key] = _Group(rig, moving)
        group.waiting.append(request)
        if len(group.runners) < self._concurrency:
            runner = asyncio.create_task(self._run(key, group), name="facecast-blend")
            group.runners.add(runner)
        await request.done

    @property
    def active_groups(self) -> int:
        """Bases with frames waiting or being blended."""
        return len(self._groups)

    async def _run(self, key: tuple[int, tuple[int, ...], bool], group: _Group) -> None:
        loop = asyncio.get_running_loop()
        scratch = _Scratch()
        batch: list[_Request] = []
        try:
            while group.waiting:
                batch = group.waiting[:MAX_BATCH]
                del group.waiting[:MAX_BATCH]
                self.batches += 1
                self.frames += len(batch)
                try:
                    blend, cast = await loop.run_in_executor(
                        self._executor, scratch.blend, group.rig, batch, group.moving
                    )
                except Exception as exc:
                    for request in batch:
                        if not request.done.done():
                            request.done.set_exception(exc)
                else:
                    if self._stages is not None:
                        self._stages.add("blend", blend, len(batch))
                        self._stages.add("cast", cast, len(batch))
                        self._stages.batch_sizes[len(batch)] += 1
                    for request in batch:
                        if not request.done.done():
                            request.done.set_result(None)
                batch = []
        finally:
            group.runners.discard(asyncio.current_task())
            for request in batch:  # only when cancelled mid-batch (the loop is closing)
                if not request.done.done():
                    request.done.cancel()
            if not group.runners:
                # Nothing waits now (or the loop is going away): the group ends with its
                # last runner.
                del self._groups[key]
                for request in group.waiting:
                    if not request.done.done():
                        request.done.cancel()

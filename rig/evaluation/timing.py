"""How fast a rig is: the thesis's Table 4.4 (fit, weights, blend; one frame and batched).

Median wall times by ``time.perf_counter``; no errors measured here (error_metrics.py).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from ..examples import ExampleSet
from ..fit import fit
from ..rig import Rig
from .error_metrics import CHUNK

__all__ = ["median_call_seconds", "timing_table"]


def median_call_seconds(
    function: Callable[[], object], *, repeat: int = 5, min_run_seconds: float = 0.02
) -> float:
    """Median over ``repeat`` runs of the mean time of one call (time.perf_counter).

    Each run makes as many calls as fill about ``min_run_seconds`` (found by a first
    timed call), so short calls are averaged over many repetitions.
    """
    started = time.perf_counter()
    function()
    once = max(time.perf_counter() - started, 1e-9)
    number = max(1, int(min_run_seconds / once))
    runs = []
    for _ in range(max(1, int(repeat))):
        started = time.perf_counter()
        for _ in range(number):
            function()
        runs.append((time.perf_counter() - started) / number)
    return float(np.median(runs))


def timing_table(
    example_set: ExampleSet,
    rig: Rig,
    points: np.ndarray,
    *,
    repeat: int = 3,
    fit_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The thesis's Table 4.4 for one rig on one animation's points (F, K, 3).

    Returns
    -------
    dict
        ``fit_seconds`` (median of ``repeat`` fits), ``weights_single_seconds`` (one frame),
        ``weights_batched_per_frame_seconds`` and ``weights_total_seconds`` (the whole
        animation in one call), ``blend_single_seconds``, ``blend_batched_per_frame_seconds``,
        ``frames_per_second`` (one frame at a time, weights + blend), ``num_frames``.
    """
    points = np.asarray(points, dtype=np.float64)
    frames = points.shape[0]
    kwargs = dict(fit_kwargs or {})
    fit_runs = []
    for _ in range(max(1, repeat)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            started = time.perf_counter()
            fit(example_set, **kwargs)
            fit_runs.append(time.perf_counter() - started)
    frame = points[0]
    single = median_call_seconds(lambda: rig.weights(frame), repeat=repeat)
    total = median_call_seconds(lambda: rig.weights(points), repeat=repeat, min_run_seconds=0.0)
    weights = rig.weights(points[: min(frames, CHUNK)])
    out_one = np.empty((rig.num_vertices, 3), dtype=np.float32)
    out_batch = np.empty((weights.shape[0], rig.num_vertices, 3), dtype=np.float32)
    blend_single = median_call_seconds(lambda: rig.blend(weights[0], out=out_one), repeat=repeat)
    blend_batch = median_call_seconds(
        lambda: rig.blend(weights, out=out_batch), repeat=repeat, min_run_seconds=0.0
    )
    return {
        "num_frames": int(frames),
        "fit_seconds": float(np.median(fit_runs)),
        "weights_single_seconds": single,
        "weights_total_seconds": total,
        "weights_batched_per_frame_seconds": total / frames,
        "blend_single_seconds": blend_single,
        "blend_batched_per_frame_seconds": blend_batch / weights.shape[0],
        "frames_per_second": 1.0 / (single + blend_single),
    }

"""Measuring a rig as the thesis does: cloning error (eq. 4.1), peers, and timing (Table 4.4).

Compares fitted rigs with plain least-squares and non-negative least-squares blend weights
on clean and noisy input and returns JSON-able numbers; it must not plot, print or do I/O.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import scipy.optimize

from ..bounds import project_box, sparsity_penalty, stream_sparsity, weight_metric
from ..errors import FitError, InputError
from ..examples import ExampleSet
from ..filters import OneEuroFilter
from ..fit import fit
from ..radial import KERNELS
from ..rig import Rig

if TYPE_CHECKING:
    from ..sources.animation import SourceAnimation

__all__ = [
    "cloning_error",
    "default_settings",
    "evaluate",
    "jitter",
    "least_squares_weights",
    "median_call_seconds",
    "nnls_weights",
    "smoothing_report",
    "timing_table",
]

AXES = ("x", "y", "z")
# ``sparsity`` of a setting whose prior's rate is estimated from the stream (empirical Bayes,
# bounds.stream_sparsity) over the STREAM_WINDOW frames before each frame.
STREAM = "stream"
STREAM_WINDOW = 60
# Frames blended at once while measuring errors: bounds the (B, V, 3) scratch arrays.
_CHUNK = 256


# -- errors -------------------------------------------------------------------------------
def _sanitize_frames(
    name: str, frames: npt.ArrayLike, shape: tuple[int, ...] | None = None
) -> np.ndarray:
    array = np.asarray(frames)
    if array.dtype.kind not in "fiu":
        raise InputError(f"{name}: not a numeric array", code="bad_evaluation_input")
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1:
        raise InputError(
            f"{name}: expected shape (F, V, 3) with F >= 1, got {array.shape}",
            code="bad_evaluation_input",
        )
    if shape is not None and array.shape != shape:
        raise InputError(
            f"{name}: expected shape {shape} (the truth's), got {array.shape}",
            code="bad_evaluation_input",
        )
    return array


class _ErrorSums:
    """Per-frame error terms of one method, accumulated a chunk of frames at a time."""

    def __init__(self, num_frames: int) -> None:
        self.eq41_numerator = np.zeros((num_frames, 3))
        self.mean_sq = np.zeros(num_frames)
        self.max_dist = np.zeros(num_frames)
        # Jitter (``jitter``) of the cloned vertices across chunks: the last two frames of
        # the chunk before, and the running sum of squared second differences.
        self._tail: np.ndarray | None = None
        self._second_sq = 0.0
        self._second_count = 0

    def add(self, start: int, truth: np.ndarray, pred: np.ndarray) -> None:
        # float32 when both are: the differences of float32 vertices are exact enough
        # (relative 1e-7), and it halves the memory traffic of the largest arrays here.
        diff = np.subtract(truth, pred, dtype=np.result_type(truth.dtype, pred.dtype, np.float32))
        stop = start + truth.shape[0]
        ones = np.ones(3, dtype=diff.dtype)
        # Products with vectors of ones are the fastest reductions over these axes.
        dist2 = np.matmul(diff * diff, ones)
        np.abs(diff, out=diff)
        self._add_jitter(pred)
        self.eq41_numerator[start:stop] = np.matmul(np.ones(diff.shape[1], diff.dtype), diff)
        self.mean_sq[start:stop] = dist2.mean(axis=1)
        self.max_dist[start:stop] = np.sqrt(dist2.max(axis=1))

    def _add_jitter(self, pred: np.ndarray) -> None:
        run = pred if self._tail is None else np.concatenate([self._tail, pred])
        if len(run) >= 3:
            second = run[2:] - 2.0 * run[1:-1] + run[:-2]
            self._second_sq += float(np.square(second, dtype=np.float64).sum())
            self._second_count += second.size
        self._tail = run[-2:].copy()

    def result(
        self, eq41_denominator: np.ndarray, diagonal: float, *, series: bool = True
    ) -> dict[str, Any]:
        with np.errstate(divide="ignore", invalid="ignore"):
            per_axis = 100.0 * self.eq41_numerator / eq41_denominator  # eq. 4.1, (F, 3)
        scale = 100.0 / diagonal if diagonal > 0 else float("nan")
        rms_frames = np.sqrt(self.mean_sq) * scale
        max_frames = self.max_dist * scale
        out = {
            "eq41_percent": {a: float(v) for a, v in zip(AXES, per_axis.mean(axis=0), strict=True)},
            "rms_percent": float(np.sqrt(self.mean_sq.mean()) * scale),
            "max_percent": float(max_frames.max()),
            # RMS second difference of the cloned vertices (``jitter``), % of the diagonal.
            "jitter_percent": (
                float(np.sqrt(self._second_sq / self._second_count) * scale)
                if self._second_count
                else float("nan")
            ),
        }
        if series:
            out["per_frame"] = {
                "eq41_percent": _rounded(per_axis),
                "rms_percent": _rounded(rms_frames),
                "max_percent": _rounded(max_frames),
            }
        return out


def _rounded(array: np.ndarray) -> list[Any]:
    """A list of floats with 6 significant digits (a compact JSON series)."""
    rounded: list[Any] = np.vectorize(lambda x: float(f"{x:.6g}"), otypes=[float])(array).tolist()
    return rounded


def _truth_terms(truth: np.ndarray) -> tuple[np.ndarray, float]:
    """Eq. 4.1's per-frame denominators sum_j |v_j| (F, 3) and the bounding-box diagonal."""
    denominator = np.empty((truth.shape[0], 3))
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for start in range(0, truth.shape[0], _CHUNK):
        chunk = truth[start : start + _CHUNK]
        denominator[start : start + len(chunk)] = np.abs(chunk).sum(axis=1, dtype=np.float64)
        low = np.minimum(low, chunk.min(axis=(0, 1)))
        high = np.maximum(high, chunk.max(axis=(0, 1)))
    return denominator, float(np.linalg.norm(high - low))


def cloning_error(truth: npt.ArrayLike, pred: npt.ArrayLike) -> dict[str, Any]:
    """Errors of a cloned animation against the ideal one.

    Parameters
    ----------
    truth, pred : (F, V, 3) float
        Ideal and cloned vertices per frame, the same vertex order.

    Returns
    -------
    dict
        ``eq41_percent`` {x, y, z}: thesis eq. 4.1 per axis, sum_j |v_j - v'_j| /
        sum_j |v_j| * 100, averaged over the frames (it depends on where the origin is,
        as the thesis's does); ``rms_percent`` and ``max_percent``: RMS and largest vertex
        distance relative to the truth's bounding-box diagonal (all frames), in %;
        ``per_frame``: the same three as series of F values ((F, 3) for eq41_percent).
    """
    truth = _sanitize_frames("truth", truth)
    pred = _sanitize_frames("pred", pred, truth.shape)
    denominator, diagonal = _truth_terms(truth)
    sums = _ErrorSums(truth.shape[0])
    for start in range(0, truth.shape[0], _CHUNK):
        sums.add(start, truth[start : start + _CHUNK], pred[start : start + _CHUNK])
    return sums.result(denominator, diagonal)


# -- peers ----------------------------------------------------------------------------------
def _peer_system(
    example_set: ExampleSet, points: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The example displacements D (M-1, 3K) and the frames' displacements (B, 3K)."""
    if not isinstance(example_set, ExampleSet):
        raise TypeError(f"expected an ExampleSet, got {type(example_set).__name__}")
    x = np.asarray(points, dtype=np.float64)
    k = example_set.num_points
    if x.ndim not in (2, 3) or x.shape[-2:] != (k, 3):
        raise InputError(
            f"expected feature points of shape ({k}, 3) or (B, {k}, 3), got {x.shape}",
            code="wrong_point_count",
        )
    if not np.isfinite(x).all():
        raise InputError("feature points hold NaN or Inf", code="non_finite")
    single = x.ndim == 2
    neutral = example_set.source_neutral
    m = example_set.num_examples
    displacements = (example_set.source_points[1:] - neutral).reshape(m - 1, 3 * k)
    frames = (x.reshape(-1, k, 3) - neutral).reshape(-1, 3 * k)
    return displacements, frames, single


def _with_neutral(rest: np.ndarray, single: bool) -> np.ndarray:
    weights = np.empty((rest.shape[0], rest.shape[1] + 1))
    weights[:, 1:] = rest
    weights[:, 0] = 1.0 - rest.sum(axis=1)
    return weights[0] if single else weights


def least_squares_weights(example_set: ExampleSet, points: npt.ArrayLike) -> np.ndarray:
    """Plain least-squares blend weights read off the feature points (the simplest peer).

    Minimises |sum_i w_i (S_i - S_B) - (x - S_B)| over w_1..w_{M-1}; w_0 = 1 - sum.

    Parameters
    ----------
    example_set : ExampleSet
    points : (K, 3) or (B, K, 3) float

    Returns
    -------
    (M,) or (B, M) float64
    """
    displacements, frames, single = _peer_system(example_set, points)
    # One pseudo-inverse for all frames: the batch is a single product.
    rest = frames @ np.linalg.pinv(displacements)
    return _with_neutral(rest, single)


def nnls_weights(example_set: ExampleSet, points: npt.ArrayLike) -> np.ndarray:
    """Non-negative least-squares blend weights: as ``least_squares_weights`` with w_i >= 0.

    Solved frame by frame with ``scipy.optimize.nnls`` (a reference, not a hot path).

    Returns
    -------
    (M,) or (B, M) float64
    """
    displacements, frames, single = _peer_system(example_set, points)
    system = displacements.T
    rest = np.empty((frames.shape[0], displacements.shape[0]))
    for i, frame in enumerate(frames):
        rest[i] = scipy.optimize.nnls(system, frame)[0]
    return _with_neutral(rest, single)


PEERS: dict[str, Callable[[ExampleSet, np.ndarray], np.ndarray]] = {
    "least squares": least_squares_weights,
    "nnls": nnls_weights,
}


# -- timing ---------------------------------------------------------------------------------
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
    weights = rig.weights(points[: min(frames, _CHUNK)])
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


# -- the comparison -------------------------------------------------------------------------
def _label(setting: dict[str, Any]) -> str:
    if "label" in setting:
        return str(setting["label"])
    parts = ["rig"]
    if setting.get("kernel", "bspline") != "bspline":
        parts.append(str(setting["kernel"]))
    if setting.get("clamp"):
        parts.append(f"clamp={setting['clamp']}")
    if setting.get("sparsity") == STREAM:
        parts.append(f"sparsity={STREAM}")
    elif setting.get("sparsity") is not None:
        parts.append(f"sparsity={float(setting['sparsity']):g}")
    if setting.get("pca_threshold") is not None:
        parts.append(f"pca={float(setting['pca_threshold']):g}")
    parts.append(f"noise={float(setting.get('noise', 0.0)):g}")
    return " ".join(parts)


def default_settings(noise: float = 0.0, kernels: Sequence[str] = KERNELS) -> list[dict[str, Any]]:
    """Rig settings worth comparing at input noise ``noise`` (std, source units).

    The thesis's rig (B-spline, no regularisation); with noise, the regularised unbounded
    rig (``clamp`` "none") at noise/2, noise and 2 noise; every other kernel in ``kernels``
    (with fit's default bounds); the bounded rigs
    (``clamp`` nonneg and unit, the plain metric projection, the default) at the input noise
    and twice it; and, with noise, the nonneg rig with a sparsity prior of rate 1 and with
    its rate estimated from the stream (``sparsity`` "stream"), to show what a prior adds.
    """
    noise = float(noise)
    settings: list[dict[str, Any]] = [{"noise": 0.0}]
    if noise > 0:
        settings += [{"clamp": "none", "noise": s * noise} for s in (0.5, 1.0, 2.0)]
    for kernel in kernels:
        if kernel != "bspline":
            settings.append({"kernel": kernel, "noise": noise})
    for clamp in ("nonneg", "unit"):
        settings.append({"clamp": clamp, "noise": noise})
        if noise > 0:
            settings.append({"clamp": clamp, "noise": 2.0 * noise})
    if noise > 0:
        settings.append({"clamp": "nonneg", "sparsity": 1.0, "noise": noise})
        settings.append({"clamp": "nonneg", "sparsity": STREAM, "noise": noise})
    return settings


def _sanitize_settings(settings: Iterable[object]) -> list[tuple[str, dict[str, Any]]]:
    allowed = {"noise", "kernel", "clamp", "sparsity", "pca_threshold", "ridge", "label"}
    out = []
    seen = set()
    for setting in settings:
        if not isinstance(setting, dict):
            raise InputError(f"settings: expected dicts of fit arguments, got {setting!r}")
        unknown = set(setting) - allowed
        if unknown:
            raise InputError(
                f"settings: unknown fit argument {sorted(unknown)[0]!r}; "
                f"expected some of {sorted(allowed)}"
            )
        label = _label(setting)
        if label in seen or label in PEERS:
            raise InputError(f"settings: label {label!r} is used twice")
        seen.add(label)
        out.append((label, {k: v for k, v in setting.items() if k != "label"}))
    return out


def _fit_setting(
    example_set: ExampleSet, kwargs: dict[str, Any]
) -> tuple[Rig | None, dict[str, Any]]:
    entry: dict[str, Any] = {"kind": "rig", "settings": dict(kwargs), "failed": None}
    if kwargs.get("sparsity") == STREAM:
        kwargs = {**kwargs, "sparsity": 0.0}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rig = fit(example_set, **kwargs)
    except FitError as exc:
        entry["failed"] = f"{exc.code}: {exc.message}"
        return None, entry
    report = rig.fit_report
    entry["fit"] = {
        "fit_seconds": report["fit_seconds"],
        "components_kept": report["components_kept"],
        "condition_number": report["condition_number"],
        "noise_gain": report["noise_gain"],
        "warnings": len(report["warnings"]),
    }
    return rig, entry


def _rig_weights(rig: Rig, points: np.ndarray, setting: dict[str, Any]) -> np.ndarray:
    """The rig's weights; with ``sparsity`` "stream", the MAP weights under a prior whose
    rate is re-estimated for every frame from the frames before it (bounds.stream_sparsity).

    The plain projection's weights feed the estimate; the exponential prior's linear term
    lambda_t then shifts each frame's unbounded weights by (lambda_t / 2) H^-1 1 before the
    same projection, which is that MAP problem.
    """
    if setting.get("sparsity") != STREAM:
        return rig.weights(points)
    model = rig.model
    plain = rig.weights(points)
    rates = stream_sparsity(plain[:, 1:], STREAM_WINDOW)
    unbounded = rig.with_clamp(None).weights(points)[:, 1:]
    metric = weight_metric(model.params, model.ridge)
    unit_shift = 0.5 * np.linalg.solve(metric, np.ones(len(metric)))
    noise = float(setting.get("noise", 0.0))
    penalties = np.array([sparsity_penalty(noise, r, rig.num_examples) for r in rates])
    upper = 1.0 if model.clamp == "unit" else None
    rest = project_box(unbounded - penalties[:, None] * unit_shift, metric, upper)
    weights = np.empty_like(plain)
    weights[:, 1:] = rest
    weights[:, 0] = 1.0 - rest.sum(axis=1)
    return weights


def _blend_with(rig: Rig) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    return lambda weights, out: rig.blend(weights, out=out)


def evaluate(
    example_set: ExampleSet,
    animation: SourceAnimation | npt.ArrayLike,
    truth_vertices: npt.ArrayLike | None,
    *,
    settings: Sequence[dict[str, Any]] | None = None,
    noise: float = 0.0,
    seed: int = 0,
    timing: bool = True,
    series: bool = True,
) -> dict[str, Any]:
    """Clone an animation with rigs of several settings and with the peers; measure each.

    Parameters
    ----------
    example_set : ExampleSet
    animation : SourceAnimation or (F, K, 3) float
        Source feature points per frame.
    truth_vertices : (F, V, 3) float or None
        The ideal clone; None skips the error tables (timing only).
    settings : sequence of dict, optional
        ``fit`` keyword arguments per rig (``noise``, ``kernel``, ``clamp``, ``sparsity``,
        ``pca_threshold``, ``ridge``) and an optional ``label``; default
        ``default_settings(noise)``. A setting that cannot be fitted is reported as failed.
    noise : float
        Standard deviation of the Gaussian noise added to every source coordinate for the
        "noisy" condition; 0 measures the clean input only.
    seed : int
        Seed of that noise.
    timing : bool
        Also measure Table 4.4 for the first setting that fits.
    series : bool
        Keep the per-frame error series in the report.

    Returns
    -------
    dict (JSON-able)
        ``num_examples``, ``num_points``, ``num_vertices``, ``num_frames``, ``noise``,
        ``seed``; ``methods`` {label: {kind, settings, failed, fit}}; ``errors``
        {"clean" | "noisy": {label: cloning_error(...)}} or None without truth; ``timing``
        (``timing_table``) or None.
    """
    points = np.asarray(getattr(animation, "points", animation), dtype=np.float64)
    k = example_set.num_points
    if points.ndim != 3 or points.shape[1:] != (k, 3) or points.shape[0] < 1:
        raise InputError(
            f"animation: expected points of shape (F, {k}, 3), got {points.shape}",
            code="wrong_point_count",
        )
    if not np.isfinite(points).all():
        raise InputError("animation: points hold NaN or Inf", code="non_finite")
    frames = points.shape[0]
    truth = None
    if truth_vertices is not None:
        truth = _sanitize_frames("truth", truth_vertices, (frames, example_set.num_vertices, 3))
    noise = float(noise)
    if not np.isfinite(noise) or noise < 0:
        raise InputError(f"noise must be a finite number >= 0, got {noise}")
    chosen = _sanitize_settings(default_settings(noise) if settings is None else settings)
    settings_by_label = dict(chosen)

    methods: dict[str, dict[str, Any]] = {}
    rigs: dict[str, Rig] = {}
    for label, kwargs in chosen:
        rig, entry = _fit_setting(example_set, kwargs)
        methods[label] = entry
        if rig is not None:
            rigs[label] = rig
    for label in PEERS:
        methods[label] = {"kind": "peer", "settings": {}, "failed": None}
    if not rigs:
        raise FitError(
            "no rig setting could be fitted: "
            + "; ".join(
                f"{label}: {entry['failed']}" for label, entry in methods.items() if entry["failed"]
            )
        )
    blend_rig = next(iter(rigs.values()))

    inputs = {"clean": points}
    if noise > 0:
        rng = np.random.default_rng(seed)
        inputs["noisy"] = points + rng.normal(0.0, noise, size=points.shape)

    errors = None
    if truth is not None:
        denominator, diagonal = _truth_terms(truth)
        errors = {}
        for condition, x in inputs.items():
            table = {}
            weights_by_label = {
                label: _rig_weights(rig, x, settings_by_label[label]) for label, rig in rigs.items()
            }
            weights_by_label.update({label: peer(example_set, x) for label, peer in PEERS.items()})
            scratch = np.empty((min(frames, _CHUNK), example_set.num_vertices, 3), np.float32)
            for label, weights in weights_by_label.items():
                blend = _blend_with(rigs.get(label, blend_rig))
                sums = _ErrorSums(frames)
                for start in range(0, frames, _CHUNK):
                    w = weights[start : start + _CHUNK]
                    pred = blend(w, scratch[: len(w)])
                    sums.add(start, truth[start : start + len(w)], pred)
                table[label] = sums.result(denominator, diagonal, series=series)
            errors[condition] = table

    first = next(iter(rigs))
    timing_report = None
    if timing:
        timing_report = timing_table(
            example_set, rigs[first], points, fit_kwargs=dict(chosen)[first]
        )
        timing_report["rig"] = first
    return {
        "num_examples": example_set.num_examples,
        "num_points": k,
        "num_vertices": example_set.num_vertices,
        "num_frames": frames,
        "noise": noise,
        "seed": int(seed),
        "methods": methods,
        "errors": errors,
        "timing": timing_report,
    }


def jitter(frames: np.ndarray | Sequence[Any]) -> float:
    """RMS second difference between consecutive frames: how much a series shakes.

    Parameters
    ----------
    frames : (F, ...) float
        Any per-frame quantity (weights, vertices); F >= 3.

    Returns
    -------
    float, in the frames' units per frame^2 (0 for a series moving at constant speed).
    """
    x = np.asarray(frames, dtype=np.float64).reshape(len(frames), -1)
    if len(x) < 3:
        raise InputError(f"jitter needs at least 3 frames, got {len(x)}")
    second = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(np.sqrt(np.mean(second * second)))


def smoothing_report(
    rig: Rig,
    clean_points: npt.ArrayLike,
    noisy_points: npt.ArrayLike,
    truth_vertices: npt.ArrayLike,
    *,
    fps: float,
    min_cutoff: float = 2.0,
    beta: float = 2.0,
    d_cutoff: float = 1.0,
) -> dict[str, Any]:
    """Jitter and error of a noisy take cloned raw and through the one-euro filter.

    The filter runs on the source feature points, as a streaming session does with
    ``smoothing`` in its ``hello``. Jitter is of the cloned target vertices, in % of the
    truth's bounding-box diagonal per frame^2; ``error`` is ``cloning_error``'s RMS %.

    Returns
    -------
    dict (JSON-able): ``settings``, and for ``truth``, ``clean``, ``noisy`` and ``filtered``
    the ``jitter`` (and ``rms_percent`` error for the cloned ones).
    """
    clean = np.asarray(clean_points, dtype=np.float64)
    noisy = np.asarray(noisy_points, dtype=np.float64)
    truth = _sanitize_frames("truth", truth_vertices, (len(clean), rig.num_vertices, 3))
    if noisy.shape != clean.shape:
        raise InputError(f"noisy points {noisy.shape} differ from clean points {clean.shape}")
    times = np.arange(len(clean)) / float(fps)
    one_euro = OneEuroFilter(min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff)
    filtered = one_euro.filter_series(noisy.reshape(len(noisy), -1), times).reshape(noisy.shape)
    _, diagonal = _truth_terms(truth)
    report = {
        "settings": {"min_cutoff": min_cutoff, "beta": beta, "d_cutoff": d_cutoff, "fps": fps},
        "truth": {"jitter": jitter(truth) / diagonal * 100.0},
    }
    for name, points in (("clean", clean), ("noisy", noisy), ("filtered", filtered)):
        vertices = rig.blend(rig.weights(points))
        report[name] = {
            "jitter": jitter(vertices) / diagonal * 100.0,
            "rms_percent": cloning_error(truth, vertices)["rms_percent"],
        }
    return report

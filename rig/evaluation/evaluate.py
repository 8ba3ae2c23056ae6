"""Measuring a rig as the thesis does: rigs of several settings against the peers (ch. 4).

Compares fitted rigs with plain least-squares and non-negative least-squares blend weights
on clean and noisy input and returns JSON-able numbers; it must not plot, print or do I/O.
The measures are error_metrics.py's, the peers peers.py's, Table 4.4 timing.py's; their
public names are re-exported here.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ..bounds import project_box, sparsity_penalty, stream_sparsity, weight_metric
from ..errors import FitError, InputError
from ..examples import ExampleSet
from ..filters import OneEuroFilter
from ..fit import fit
from ..fit_options import NOISE_CLAMP
from ..radial import KERNELS
from ..rig import Rig
from .error_metrics import CHUNK, ErrorSums, cloning_error, jitter, sanitize_frames, truth_terms
from .peers import PEERS, least_squares_weights, nnls_weights
from .timing import median_call_seconds, timing_table

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

# ``sparsity`` of a setting whose prior's rate is estimated from the stream (empirical Bayes,
# bounds.stream_sparsity) over the STREAM_WINDOW frames before each frame.
STREAM = "stream"
STREAM_WINDOW = 60


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
    (with fit's default bounds, named in its label: ``clamp`` nonneg with noise); the
    bounded rigs
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
            # fit's default bound, named: with noise it is nonneg, whose projection can make
            # kernels' rows alike (the demo's three are identical), and the label says why.
            bound = {"clamp": NOISE_CLAMP} if noise > 0 else {}
            settings.append({"kernel": kernel, **bound, "noise": noise})
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
        truth = sanitize_frames("truth", truth_vertices, (frames, example_set.num_vertices, 3))
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
        denominator, diagonal = truth_terms(truth)
        errors = {}
        for condition, x in inputs.items():
            table = {}
            weights_by_label = {
                label: _rig_weights(rig, x, settings_by_label[label]) for label, rig in rigs.items()
            }
            weights_by_label.update({label: peer(example_set, x) for label, peer in PEERS.items()})
            scratch = np.empty((min(frames, CHUNK), example_set.num_vertices, 3), np.float32)
            for label, weights in weights_by_label.items():
                blend = _blend_with(rigs.get(label, blend_rig))
                sums = ErrorSums(frames)
                for start in range(0, frames, CHUNK):
                    w = weights[start : start + CHUNK]
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
    truth = sanitize_frames("truth", truth_vertices, (len(clean), rig.num_vertices, 3))
    if noisy.shape != clean.shape:
        raise InputError(f"noisy points {noisy.shape} differ from clean points {clean.shape}")
    times = np.arange(len(clean)) / float(fps)
    one_euro = OneEuroFilter(min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff)
    filtered = one_euro.filter_series(noisy.reshape(len(noisy), -1), times).reshape(noisy.shape)
    _, diagonal = truth_terms(truth)
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

"""The fit's options, checked and normalised before any math (the scipy ``_sanitize`` habit).

Kernel, noise, PCA threshold, ridge, clamp and sparsity: every bad value is refused here
with a ``FitError`` that names the remedy, so the weight-function solve assumes clean input.
"""

from __future__ import annotations

import numpy as np

from .errors import FitError
from .examples import ExampleSet
from .radial import KERNELS

__all__ = [
    "CLAMP_MODES",
    "DEFAULT_SPARSITY",
    "NOISE_CLAMP",
    "NOISE_MAX_RELATIVE",
    "feature_extent",
    "sanitize_fit_options",
]

CLAMP_MODES = (None, "none", "nonneg", "unit")
# clamp None (the default) chooses: bounded ("nonneg") when fitted for noise, where every
# unbounded noise rig cloned real takes worse than NNLS (README "Real takes"); unbounded
# without noise, where exact interpolation needs no bounds. "none" asks for unbounded.
NOISE_CLAMP = "nonneg"
# The sparsity prior's default: none, the plain metric projection. Chosen on real takes
# (tests/data/livelink, README "Real takes"): an iPhone's ARKit weights hold 4-10
# expressions' worth a frame, many small weights at once, and every exponential prior tried
# (1, the take's own rate, per-shape rates) cloned them worse than none at sigma = 0.5 mm.
# On synthetic sparse mixes the prior helps; --sparsity 1 asks for it.
DEFAULT_SPARSITY = 0.0
# Landmark noise above this many times the feature points' extent is refused: it could not
# be told from no tracking at all, and its square overflows the regularised fit.
NOISE_MAX_RELATIVE = 10.0


def sanitize_fit_options(
    example_set: object,
    kernel: str,
    noise: float,
    pca_threshold: float | None,
    ridge: float | None,
    clamp: str | None,
    sparsity: float | None,
) -> tuple[str, float, float | None, float | None, str | None, float]:
    """Checked and normalised ``fit`` options: kernel, noise, pca_threshold, ridge, clamp
    (None or a bound), sparsity."""
    if not isinstance(example_set, ExampleSet):
        raise TypeError(f"expected an ExampleSet, got {type(example_set).__name__}")
    if kernel not in KERNELS:
        raise FitError(f"unknown kernel {kernel!r}; expected one of {', '.join(KERNELS)}")
    noise = float(noise)
    if not np.isfinite(noise) or noise < 0:
        raise FitError(f"noise must be a finite number >= 0, got {noise}")
    extent = feature_extent(example_set.source_points)
    if noise > NOISE_MAX_RELATIVE * extent:
        # Noise beyond the face itself means nothing, and its square overflows the fit.
        raise FitError(
            f"noise {noise:g} is more than {NOISE_MAX_RELATIVE:g}x the feature points' extent "
            f"{extent:.3g}: give the landmark noise in the source's units",
            code="noise_too_large",
        )
    if pca_threshold is not None:
        pca_threshold = float(pca_threshold)
    if pca_threshold is not None and not (0.0 <= pca_threshold < 1.0):
        raise FitError(
            f"pca_threshold is relative to the largest eigenvalue: expected [0, 1), got "
            f"{pca_threshold}"
        )
    if ridge is not None:
        ridge = float(ridge)
        if not np.isfinite(ridge) or ridge < 0:
            raise FitError(f"ridge must be a finite number >= 0, got {ridge}")
    if clamp not in CLAMP_MODES:
        raise FitError(f"clamp must be one of {CLAMP_MODES}, got {clamp!r}")
    explicit_clamp = clamp
    if clamp is None:
        clamp = NOISE_CLAMP if noise > 0 else None
    elif clamp == "none":
        clamp = None
    if sparsity is None:
        sparsity = DEFAULT_SPARSITY
    else:
        sparsity = float(sparsity)
        if not np.isfinite(sparsity) or sparsity < 0:
            raise FitError(f"sparsity must be a finite number >= 0, got {sparsity}")
        if sparsity > 0 and explicit_clamp in (None, "none"):
            raise FitError(
                "sparsity is a prior on bounded weights: it needs clamp 'nonneg' or 'unit'",
                code="sparsity_without_clamp",
            )
    return kernel, noise, pca_threshold, ridge, clamp, sparsity


def feature_extent(source_points: np.ndarray) -> float:
    """The diagonal of the feature points' bounding box over every example."""
    flat = source_points.reshape(-1, 3)
    return float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))

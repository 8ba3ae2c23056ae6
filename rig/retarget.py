"""A character's rig refitted on a performer's own source examples (thesis section 3, user-defined).

Pairs a performer's captured feature points for some of a fitted rig's key-expressions with
the target examples that rig already holds, and fits a new rig; no file or network I/O.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .errors import InputError
from .examples import ExampleSet
from .fit import fit
from .rig import Rig

__all__ = ["NEUTRAL", "fit_performer", "shared_names", "target_examples"]

#: The name of the neutral example in a capture; a rig's names[0] is its neutral whatever
#: it is called.
NEUTRAL = "neutral"


def target_examples(rig: Rig) -> np.ndarray:
    """(M, V, 3) float64: the rig's target examples T_i, rebuilt from its blend basis.

    The rig stores T_B in row 0 and T_i - T_B in rows i > 0 (float32), so T_i is exact to
    the precision the rig blends with.
    """
    basis = rig.blend_basis.astype(np.float64)
    vertices = basis + basis[0]
    vertices[0] = basis[0]
    examples: np.ndarray = vertices.reshape(rig.num_examples, rig.num_vertices, 3)
    return examples


def shared_names(rig: Rig, captured: Mapping[str, object]) -> tuple[str, ...]:
    """The rig's key-expressions the capture holds, in the rig's order (its neutral first).

    The capture names the neutral ``"neutral"``; the rig's own neutral name (``names[0]``)
    is accepted as well.
    """
    rest = tuple(name for name in rig.names[1:] if name in captured)
    return (rig.names[0], *rest)


def _sanitize(
    rig: Rig, points: Mapping[str, object], noise: float | None
) -> tuple[dict[str, np.ndarray], float | None]:
    if not isinstance(rig, Rig):
        raise TypeError(f"expected a Rig, got {type(rig).__name__}")
    k = rig.num_points
    neutral_key = NEUTRAL if NEUTRAL in points else rig.names[0]
    if neutral_key not in points:
        raise InputError("the capture has no 'neutral': it is needed first", code="no_neutral")
    if NEUTRAL in points and rig.names[0] != NEUTRAL and rig.names[0] in points:
        raise InputError(
            f"the capture names the neutral twice ('neutral' and {rig.names[0]!r})",
            code="no_neutral",
        )
    known = {NEUTRAL, *rig.names}
    unknown = sorted(name for name in points if name not in known)
    if unknown:
        raise InputError(
            f"the character has no expression named {unknown[0]!r}; its expressions are "
            f"{', '.join(rig.names[1:6])}{' ...' if rig.num_examples > 6 else ''}",
            code="unknown_expression",
        )
    clean: dict[str, np.ndarray] = {}
    count: int | None = None  # the capture's own point count, k or more
    for name, value in points.items():
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(
                f"points[{name!r}] is not a list of [x, y, z] numbers", code="wrong_point_count"
            ) from None
        if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < k:
            raise InputError(
                f"points[{name!r}]: expected shape ({k}, 3) for this rig's {k} feature points "
                f"(or more: a later layout's), got {array.shape}",
                code="wrong_point_count",
            )
        if count is not None and array.shape[0] != count:
            raise InputError(
                f"points[{name!r}] has {array.shape[0]} feature points, the capture's others "
                f"{count}",
                code="wrong_point_count",
            )
        count = array.shape[0]
        if not np.isfinite(array).all():
            raise InputError(f"points[{name!r}] holds NaN or Inf", code="non_finite")
        clean[rig.names[0] if name == neutral_key else name] = array
    if len(clean) < 2:
        raise InputError(
            "the capture has only the neutral: capture at least one key-expression",
            code="too_few_examples",
        )
    if noise is not None:
        noise = float(noise)
        if not (np.isfinite(noise) and noise >= 0):
            raise InputError(f"noise must be a finite number >= 0, got {noise}", code="bad_noise")
    return clean, noise


def fit_performer(rig: Rig, points: Mapping[str, object], *, noise: float | None = None) -> Rig:
    """Fit a rig from a performer's source examples and ``rig``'s target examples.

    Parameters
    ----------
    rig : Rig
        The character: its names, target examples (from the blend basis), kernel, stable
        points and alignment settings are kept.
    points : mapping of name -> (K', 3) float
        The performer's feature points for ``"neutral"`` and any of the rig's
        key-expressions (skipped ones are left out of the fit). K' is the rig's K, or more:
        a later version of its layout appends points (the iris centres), which the
        performer's rig is fitted on too (its first K are the rig's, so its stable points
        and a stream's first K stay as they were).
    noise : float, optional
        The capture's measured landmark spread (standard deviation per coordinate, in the
        points' units). Given and above 0: the fit is regularised for it and the weights
        are bounded to [0, 1] (``fit(noise=..., clamp="unit")``), and each captured blink
        is read as closed: the new rig's reading of the performer's own captured blink maps
        to 1 and of their neutral to 0 (``closure``; its ``fit_report["closure"]``); else
        exact interpolation, unbounded, as the thesis.

    Returns
    -------
    Rig
        Its names are the captured subset, in the rig's order, the neutral first; its
        feature points the capture's K'.

    Raises
    ------
    InputError
        ``no_neutral``, ``unknown_expression``, ``wrong_point_count``, ``non_finite``,
        ``too_few_examples``, ``bad_noise``.
    ExampleSetError
        ``degenerate_neutral``: the captured neutral has no extent (its points coincide,
        ``examples.MIN_NEUTRAL_RADIUS``).
    FitError
        From ``fit``: e.g. ``examples_coincide`` naming two captures the feature points
        cannot tell apart.
    """
    clean, noise = _sanitize(rig, points, noise)
    names = shared_names(rig, clean)
    index = {name: i for i, name in enumerate(rig.names)}
    pick = np.asarray([index[name] for name in names])
    example_set = ExampleSet(
        names=names,
        source_points=np.stack([clean[name] for name in names]),
        target_vertices=target_examples(rig)[pick],
        target_faces=rig.target_faces,
    )
    bounded = noise is not None and noise > 0
    fitted = fit(
        example_set,
        noise=noise or 0.0,
        kernel=rig.model.kernel,
        clamp="unit" if bounded else None,
        stable_points=rig.stable_points,
        align_scale=rig.align_scale,
    )
    if not bounded:
        return fitted  # exact interpolation reads every key as itself
    return fitted.with_closed_eyes(clean[names[0]], {name: clean[name] for name in names[1:]})

"""How well transferred expressions match a target's true ones, beside a naive baseline.

Per-vertex error relative to the true displacement, per expression and overall, for
deformation transfer and for copying each target vertex's nearest corresponding source
vertex's displacement; and the end-to-end cloning error (eq. 4.1) of a take cloned
through generated versus true examples. Computes and returns numbers; it must not print.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..examples import ExampleSet
from ..fit import fit
from ..transfer.correspondence import Correspondence
from ..transfer.expressions import GeneratedExpressions, SourceExpressions
from ..transfer.mesh import nearest_vertices
from .evaluate import cloning_error
from .takes import take_experiment

__all__ = [
    "TransferScore",
    "end_to_end",
    "naive_transfer",
    "relative_errors",
    "score_transfer",
]


def relative_errors(predicted: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, float]:
    """Σ_v |p_v − t_v| / Σ_v |t_v − t_neutral| per expression (M − 1,), and over all.

    ``predicted``, ``truth`` : (M, V, 3), example 0 the neutral (the same in both).
    """
    error = np.linalg.norm(predicted[1:] - truth[1:], axis=2).sum(axis=1)
    moved = np.linalg.norm(truth[1:] - truth[0], axis=2).sum(axis=1)
    per: np.ndarray = error / np.where(moved > 0, moved, 1.0)
    return per, float(error.sum() / moved.sum())


def naive_transfer(
    correspondence: Correspondence, source_vertices: np.ndarray, target_neutral: np.ndarray
) -> np.ndarray:
    """The baseline: each target vertex moves as its nearest fitted-source vertex does.

    ``source_vertices`` (M, Vs, 3), neutral first; the displacements are turned and scaled
    into the target's frame by the correspondence's similarity. Returns (M, Vt, 3).
    """
    nearest = nearest_vertices(target_neutral, correspondence.fitted_source)
    displacement = source_vertices[:, nearest] - source_vertices[0, nearest]
    turned = correspondence.scale * displacement @ correspondence.rotation.T
    out: np.ndarray = target_neutral + turned
    return out


@dataclass(frozen=True)
class TransferScore:
    """Relative errors (fractions) of transfer and baseline, per expression and overall."""

    names: tuple[str, ...]
    transfer: np.ndarray
    naive: np.ndarray
    transfer_overall: float
    naive_overall: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "overall": {"transfer": self.transfer_overall, "naive": self.naive_overall},
            "per_expression": {
                name: {"transfer": float(t), "naive": float(n)}
                for name, t, n in zip(self.names, self.transfer, self.naive, strict=True)
            },
        }


def score_transfer(
    generated: GeneratedExpressions, source: SourceExpressions, truth: npt.ArrayLike
) -> TransferScore:
    """Score ``generated`` and the naive baseline against ``truth`` (M, Vt, 3), same names."""
    true = np.asarray(truth, dtype=np.float64)
    picked = [source.names.index(n) for n in generated.names]
    naive = naive_transfer(
        generated.correspondence, source.vertices[picked], generated.target_vertices[0]
    )
    per_dt, all_dt = relative_errors(generated.target_vertices, true)
    per_naive, all_naive = relative_errors(naive, true)
    return TransferScore(generated.names[1:], per_dt, per_naive, all_dt, all_naive)


def end_to_end(
    generated: GeneratedExpressions,
    true_examples: ExampleSet,
    arkit_weights: npt.ArrayLike,
    fps: float,
    *,
    noise: float = 0.0,
    seed: int = 0,
    names: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Eq. 4.1 of a take cloned through the generated and through the true examples.

    Both rigs see the same feature points (the take on the source's expressions, with
    Gaussian landmark noise of std ``noise`` if given, and fitted with ``noise=noise``);
    both are compared with the take driven through the true examples.
    """
    generated_set = ExampleSet(
        names=generated.names,
        source_points=generated.source_points,
        target_vertices=generated.target_vertices,
        target_faces=generated.target_faces,
    )
    true_set = true_examples.subset(list(names or generated.names[1:]))
    experiment = take_experiment(true_set, arkit_weights, fps)
    points = experiment.points
    if noise > 0:
        points = points + np.random.default_rng(seed).normal(0.0, noise, points.shape)
    result: dict[str, Any] = {"noise": noise}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for label, examples in (("true", true_set), ("generated", generated_set)):
            rig = fit(examples, noise=noise)
            error = cloning_error(experiment.truth, rig.clone(points))
            result[label] = {
                "eq41_percent": error["eq41_percent"],
                "rms_percent": error["rms_percent"],
            }
    return result

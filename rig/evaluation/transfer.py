"""How well transferred expressions match a target's true ones, beside a naive baseline.

Per-vertex error relative to the true displacement, per expression and overall, for
deformation transfer and for copying each target vertex's nearest corresponding source
vertex's displacement; the lids' gap a transferred blink leaves; and the end-to-end cloning
error (eq. 4.1) of a take cloned through generated versus true examples. Computes and
returns numbers; it must not print.
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
from ..transfer.contact import closing_pairs
from ..transfer.correspondence import Correspondence
from ..transfer.expressions import GeneratedExpressions, SourceExpressions
from ..transfer.mesh import nearest_vertices
from .evaluate import cloning_error
from .takes import take_experiment

__all__ = [
    "LidGap",
    "TransferScore",
    "closing_pairs",
    "end_to_end",
    "gap_share",
    "lids_gap",
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


#: The blinks whose lids' gap ``lids_gap`` measures.
BLINKS = ("eyeBlinkLeft", "eyeBlinkRight")


def gap_share(neutral: npt.ArrayLike, deformed: npt.ArrayLike, pairs: np.ndarray) -> float:
    """The pairs' mean distance in ``deformed`` over their mean distance in ``neutral``
    (NaN without pairs): 1 leaves the gap as it was, 0 closes it."""
    if len(pairs) == 0:
        return float("nan")
    rest = np.asarray(neutral, dtype=np.float64)
    moved = np.asarray(deformed, dtype=np.float64)
    now = np.linalg.norm(moved[pairs[:, 0]] - moved[pairs[:, 1]], axis=1).mean()
    before = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1).mean()
    return float(now / before)


@dataclass(frozen=True)
class LidGap:
    """One blink's lids' gap as a share of the neutral's: truth's and the transfer's."""

    name: str
    pairs: int
    truth: float
    generated: float


def lids_gap(
    generated: GeneratedExpressions,
    truth: npt.ArrayLike,
    *,
    names: Sequence[str] = BLINKS,
    meet: float = 0.03,
    apart: float = 0.3,
) -> list[LidGap]:
    """The gap each blink leaves between the lids, on the vertex pairs the true shape closes.

    ``truth`` (M, Vt, 3) as in ``score_transfer``. For each of ``names`` (skipped when not
    generated): the target vertex pairs the true shape brings within ``meet`` that lie at
    least ``apart`` apart at neutral (``closing_pairs``; defaults in ICT's centimetres:
    0.3 mm and 3 mm), and their ``gap_share`` in the true and in the generated shape.
    Without such pairs (the truth leaves every pair apart) both are NaN.
    """
    true = np.asarray(truth, dtype=np.float64)
    neutral = true[0]
    gaps = []
    for name in names:
        if name not in generated.names:
            continue
        index = generated.names.index(name)
        pairs = closing_pairs(neutral, true[index], meet=meet, apart=apart)
        gaps.append(
            LidGap(
                name,
                len(pairs),
                gap_share(neutral, true[index], pairs),
                gap_share(neutral, generated.target_vertices[index], pairs),
            )
        )
    return gaps


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

"""The bundled real take driving ICT-FaceKit, with landmark noise: the temporal tests' data.

Test data only: no assertion lives here.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facecast.rig import Rig, fit
from facecast.rig.evaluation.takes import TakeExperiment, take_experiment
from facecast.rig.sources.ict import locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set
from facecast.rig.sources.trackers import read_livelink_csv

ARCHIVE = locate_ict()
TAKE = Path(__file__).parents[1] / "data" / "livelink" / "llv_dao.csv"


@dataclass(frozen=True, eq=False)
class NoisyTake:
    """The take as an experiment, its points with noise, and a rig fitted for that noise."""

    experiment: TakeExperiment
    fps: float
    noisy: np.ndarray  # (F, K, 3)
    rig: Rig


def noisy_take(sigma: float, seed: int = 0) -> NoisyTake:
    """llv_dao on ICT's ARKit shapes, Gaussian landmark noise ``sigma`` (cm) added."""
    assert ARCHIVE is not None
    examples = arkit_example_set(ARCHIVE)
    livelink = read_livelink_csv(TAKE)
    experiment = take_experiment(examples, livelink.weights, livelink.fps)
    rng = np.random.default_rng(seed)
    noisy = experiment.points + rng.normal(0.0, sigma, experiment.points.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit's advice about the chosen noise
        rig = fit(examples, noise=sigma)
    return NoisyTake(experiment, livelink.fps, noisy, rig)

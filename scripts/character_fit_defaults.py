"""Measure the fit defaults of a character on the generic ARKit set (docs/characters.md).

A character rig's weights depend on its source side alone: here the generic set's 20
ICT-FaceKit landmarks, fitted with each (noise, clamp) setting. Each rig is scored by its
weights' RMS error against the true ARKit weights of the bundled real take (llv_dao,
180 frames), on three inputs:

- the ground-truth webcam benchmark's landmarks (``facecast bench webcam --videos DIR``
  keeps them: ICT person07 rendered with the take's weights and tracked by the /perform
  page's model), exact and tracked, re-based on the captured neutral exactly (a client's
  ``calibrate`` without noise) and with the held frames' noise (what /perform sends);
- the take on the generic face's own landmarks with Gaussian landmark noise, uncalibrated.

Floors printed beside: the performer's own calibrated rig on the same points, and the
error of always answering the neutral. Run from the repository after a bench run::

    .venv/bin/python scripts/character_fit_defaults.py --videos DIR
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from facecast.cli.bench import webcam as bench
from facecast.rig import fit
from facecast.rig.characters.generic import generic_sources
from facecast.rig.evaluation.takes import take_experiment
from facecast.rig.evaluation.webcam import captured_keys, hold_last_found
from facecast.rig.examples import ExampleSet
from facecast.rig.rebase import calibrate
from facecast.rig.retarget import fit_performer
from facecast.rig.sources.ict import locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set
from facecast.rig.sources.trackers import read_livelink_csv
from facecast.server.storage.profiles import held_noise

SETTINGS = [(0.0, "none"), (0.0, "nonneg"), (0.005, "nonneg"), (0.01, "nonneg"),
            (0.02, "unit"), (0.03, "unit"), (0.05, "unit"), (0.05, "nonneg"), (0.07, "unit"),
            (0.1, "unit")]  # fmt: skip
GAUSSIAN = (0.02, 0.05)  # cm: 0.2 and 0.5 mm
SEEDS = 3


def weight_error(names, weights, truth: dict[str, np.ndarray]) -> tuple[float, float]:
    """RMS error of the non-neutral weights against the truth, and the largest |weight|."""
    columns = [i for i, n in enumerate(names) if n != "neutral"]
    est = weights[:, columns]
    true = np.stack([truth.get(names[i], np.zeros(len(weights))) for i in columns], axis=1)
    return float(np.sqrt(np.mean((est - true) ** 2))), float(np.abs(est).max())


def generic_rigs():
    generic = generic_sources()
    examples = ExampleSet(
        names=generic.names,
        source_points=generic.points,
        target_vertices=generic.points.copy(),  # the weights do not depend on the target
        target_faces=np.array([[0, 1, 2]]),
        stable_points=generic.stable_points,
    )
    rigs = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact fits' noise-gain advice: measured here
        for noise, clamp in SETTINGS:
            rigs[noise, clamp] = fit(examples, noise=noise, clamp=clamp)
    return rigs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--videos", required=True, type=Path,
                        help="the folder `facecast bench webcam --videos` kept")  # fmt: skip
    args = parser.parse_args()
    setup = bench._setup(SimpleNamespace(ict=None, take=None, performer=None, target=None,
                                         frames=None, keys=None, ramp=None, hold=None))  # fmt: skip
    truth = dict(zip(setup.character.names, setup.experiment.activations.T, strict=True))
    zero = weight_error(setup.character.names, np.zeros_like(setup.experiment.activations), truth)
    print(f"always the neutral: RMS {zero[0]:.3f}")
    rigs = generic_rigs()
    inputs = {
        "exact landmarks": (
            setup.performer.landmark_points(setup.experiment.activations),
            setup.performer.landmark_points(setup.clips.activations),
            None,
        )
    }
    for take in sorted(args.videos.glob("llv_dao-*-wasm.npz")):
        sway = take.stem.split("-sway")[1].removesuffix("-wasm")
        keys = next(args.videos.glob(f"keys*-sway{sway}-wasm.npz"), None)
        if keys is None or not take.stem.startswith(f"llv_dao-{len(truth['jawOpen'])}-"):
            continue
        with np.load(take) as t, np.load(keys) as k:
            inputs[f"tracked, sway {sway} deg"] = (
                hold_last_found(t["points"], t["found"]),
                k["points"].astype(np.float64),
                k["found"].astype(bool),
            )
    for label, (take_points, key_points, found) in inputs.items():
        keys, held = captured_keys(key_points, setup.clips, found)
        sigma, frames = held_noise(held)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            personal = fit_performer(setup.character, keys, noise=sigma)
        floor = weight_error(personal.names, personal.weights(take_points), truth)
        print(f"\n{label}: held noise {sigma * 10:.2f} mm ({frames} frames); the performer's "
              f"own rig: RMS {floor[0]:.3f}, max {floor[1]:.2f}")  # fmt: skip
        print(f"  {'noise cm':>8} {'clamp':>7} {'gain':>8} | {'exact calibrate':>15} {'max':>6}"
              f" | {'/perform calibrate':>18} {'max':>6}")  # fmt: skip
        for (noise, clamp), rig in rigs.items():
            exact = calibrate(rig, keys["neutral"], None)
            noisy = calibrate(rig, keys["neutral"], sigma)
            a = weight_error(exact.names, exact.weights(take_points), truth)
            b = weight_error(noisy.names, noisy.weights(take_points), truth)
            print(f"  {noise:>8g} {clamp:>7} {rig.fit_report['noise_gain']:>8.4g} | {a[0]:>15.3f}"
                  f" {a[1]:>6.2f} | {b[0]:>18.3f} {b[1]:>6.2f}")  # fmt: skip
    generic = arkit_example_set(locate_ict(), identity=None)
    take = read_livelink_csv(bench.BUNDLED_TAKE)
    experiment = take_experiment(generic, take.weights, take.fps)
    truth = dict(zip(generic.names, experiment.activations.T, strict=True))
    print(f"\nuncalibrated: the take on the generic face's landmarks + Gaussian noise, "
          f"{SEEDS} seeds (mean, spread)")  # fmt: skip
    for sigma in GAUSSIAN:
        print(f"  landmark noise {sigma * 10:.1f} mm")
        for (noise, clamp), rig in rigs.items():
            rows = np.array([
                weight_error(rig.names, rig.weights(experiment.points + np.random.default_rng(
                    seed).normal(0.0, sigma, experiment.points.shape)), truth)
                for seed in range(SEEDS)
            ])  # fmt: skip
            print(f"  {noise:>8g} {clamp:>7}: RMS {rows[:, 0].mean():.3f} "
                  f"(spread {np.ptp(rows[:, 0]):.3f}), max {rows[:, 1].max():.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())

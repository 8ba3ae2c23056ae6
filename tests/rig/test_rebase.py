"""The generic-rig re-base (rig.rebase): noise-aware and bounded on another face's neutral.

A synthetic performer: the demo's source face with its own identity (every point moved),
seen in another frame (pitched, scaled, moved), whose tracker loses most of the depth of
every expression and adds landmark noise: what a webcam makes of a face that is not the
rig's own.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facecast.rig import InputError, fit, fit_regions
from facecast.rig.demo import demo_example_set
from facecast.rig.rebase import (
    DEPTH_NOISE_FACTOR,
    IDENTITY_NOISE_FACTOR,
    MAX_NOISE_RELATIVE,
    calibrate,
    identity_noise,
    rebase,
)
from facecast.rig.regions import Region
from facecast.rig.smoothing import smooth_take

#: What viewers may be sent: every non-neutral weight within these (issue 21).
PLAUSIBLE = (-0.25, 1.25)
PITCH = Rotation.from_euler("x", 20.0, degrees=True).as_matrix()
SCALE = 1.3
DEPTH_SEEN = 0.25  # the share of an expression's depth motion the tracker reports
NOISE = 0.01  # landmark noise, relative to the source face's radius


@pytest.fixture(scope="module")
def example_set():
    return demo_example_set()


@pytest.fixture(scope="module")
def rig(example_set):
    return fit(example_set)  # exact, as 'facecast fit' with defaults


class Performer:
    """Frames of a face that is not the rig's source face, in its tracker's frame."""

    def __init__(self, example_set, seed: int = 1) -> None:
        self.seed = seed
        source = example_set.source_points
        self.names = list(example_set.names)
        self.displacements = source - source[0]
        self.centre = source[0].mean(axis=0)
        self.radius = float(np.sqrt(((source[0] - self.centre) ** 2).sum(axis=1).mean()))
        rng = np.random.default_rng(seed)
        identity = rng.normal(size=source[0].shape) * 0.05 * self.radius
        self.neutral = self._frame(source[0] + identity)

    def _frame(self, points: np.ndarray) -> np.ndarray:
        return SCALE * (points - self.centre) @ PITCH.T + np.array([0.5, -0.2, 3.0])

    def perform(self, name: str, weight: float, frames: int) -> np.ndarray:
        """``frames`` noisy frames of expression ``name`` at ``weight`` (F, K, 3)."""
        index = self.names.index(name)
        delta = weight * self.displacements[index]
        seen = 0.8 * SCALE * (delta @ PITCH.T) * np.array([1.0, 1.0, DEPTH_SEEN])
        rng = np.random.default_rng((self.seed, index))  # the same frames in every test
        noise = rng.normal(size=(frames, *delta.shape)) * NOISE * self.radius
        return self.neutral + seen + noise


@pytest.fixture(scope="module")
def performer(example_set):
    return Performer(example_set)


def _every_expression(performer: Performer, frames: int = 40) -> dict[str, np.ndarray]:
    return {name: performer.perform(name, 0.7, frames) for name in performer.names[1:]}


def test_the_exact_re_base_extrapolates_on_another_face(rig, performer):
    # The behaviour the re-base replaces: exact weights turn identity and noise into
    # weights far outside any plausible face (ICT-FaceKit on a webcam: -1,205 .. +380).
    calibrated = rig.calibrated(performer.neutral)
    weights = np.concatenate([calibrated.weights(x) for x in _every_expression(performer).values()])

    assert weights[:, 1:].min() < PLAUSIBLE[0] or weights[:, 1:].max() > PLAUSIBLE[1]


def test_every_weight_of_the_re_based_rig_is_within_the_unit_bounds(rig, performer):
    rebased = rebase(rig, performer.neutral, noise=NOISE * performer.radius)
    weights = np.concatenate([rebased.weights(x) for x in _every_expression(performer).values()])

    assert weights[:, 1:].min() >= 0.0
    assert weights[:, 1:].max() <= 1.0
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_expression_performed_weighs_most_on_the_re_based_rig(rig, example_set, seed):
    performer = Performer(example_set, seed)
    rebased = rebase(rig, performer.neutral, noise=NOISE * performer.radius)
    names = performer.names
    ranks = []
    for name, frames in _every_expression(performer).items():
        median = np.median(rebased.weights(frames)[:, 1:], axis=0)
        ranks.append(list(np.argsort(-median)).index(names.index(name) - 1))

    # The largest for all but at most one, second at worst: 'fv' (a bite) lies within
    # about 3 sigma of 'mbp' and of the neutral at the identity noise the re-base uses.
    assert sum(rank == 0 for rank in ranks) >= len(ranks) - 1
    assert max(ranks) <= 1


def test_without_the_depth_weighting_a_mouth_opening_without_depth_is_misread(rig, example_set):
    # The tracker reports no depth motion at all: a jaw opening then is, to the source
    # face's examples, something else; taking z as noisier than x and y reads it right.
    performer = Performer(example_set)
    frames = performer.perform("aa", 0.7, 40)
    frames[..., 2] = performer.neutral[..., 2]
    sigma = NOISE * performer.radius

    def top(rebased) -> str:
        median = np.median(rebased.weights(frames)[:, 1:], axis=0)
        return performer.names[1 + int(np.argmax(median))]

    assert top(rebase(rig, performer.neutral, noise=sigma, depth_factor=1.0)) != "aa"
    assert top(rebase(rig, performer.neutral, noise=sigma)) == "aa"  # DEPTH_NOISE_FACTOR


def test_the_neutral_gives_the_neutral_exactly(rig, performer):
    rebased = rebase(rig, performer.neutral, noise=0.0)

    weights = rebased.weights(performer.neutral)

    np.testing.assert_allclose(weights, np.eye(rig.num_examples)[0], atol=1e-9)


@pytest.mark.filterwarnings("ignore::facecast.rig.IdentifiabilityWarning")
def test_the_noise_used_is_the_largest_of_tracker_identity_and_rig(example_set, performer):
    identity = identity_noise(fit(example_set), performer.neutral)
    noisy_rig = fit(example_set, noise=0.5)  # source units; the performer's are 1.3x

    quiet = rebase(fit(example_set), performer.neutral, noise=0.0).fit_report["rebase"]
    loud = rebase(fit(example_set), performer.neutral, noise=10 * identity).fit_report["rebase"]
    from_rig = rebase(noisy_rig, performer.neutral, noise=0.0).fit_report["rebase"]

    assert quiet["noise"] == pytest.approx(IDENTITY_NOISE_FACTOR * identity) and identity > 0
    assert loud["noise"] == pytest.approx(10 * identity)
    # The rig's noise in the performer's units: about SCALE times (the identity moves the
    # similarity's scale a little).
    assert from_rig["noise"] == pytest.approx(0.5 * SCALE, rel=0.01) and identity < 0.5 * SCALE
    assert (quiet["clamp"], quiet["depth_factor"]) == ("unit", DEPTH_NOISE_FACTOR)


def test_an_offline_smoother_leaves_what_the_re_base_added_to_the_noise(rig, performer):
    """A smoother removes frame noise, not how this face differs from the source face: a
    re-based rig smoothed offline (``facecast clone``'s RTS) is smoothed at the tracker's
    noise and keeps its re-base sigma, here the identity share (refitted at the smoothed
    tracker noise, the eyes clip's generic offline blinks fell to 0.03 of the truth)."""
    identity = IDENTITY_NOISE_FACTOR * identity_noise(rig, performer.neutral)
    tracker = NOISE * performer.radius * SCALE
    rebased = rebase(rig, performer.neutral, noise=tracker)
    assert rebased.fit_report["rebase"]["noise"] == pytest.approx(identity)
    assert identity > 1.25 * tracker  # the re-base's sigma is the identity share (1.46x)
    frames = np.concatenate([performer.perform(n, 0.7, 20) for n in performer.names[1:4]])
    times = np.arange(len(frames)) / 30.0

    take = smooth_take(rebased, frames, times, smoothing="rts", noise=tracker)
    inferred = smooth_take(rebased, frames, times, smoothing="auto")  # the rig's own record

    assert take.method == "rts" and take.noise < tracker
    assert (inferred.method, inferred.noise) == ("rts", take.noise)  # the tracker's noise
    assert take.rig is rebased  # not refitted below the identity share
    np.testing.assert_array_equal(take.rig.weights(frames[:5]), rebased.weights(frames[:5]))


def test_identity_noise_is_zero_for_the_source_face_in_another_frame(rig, performer):
    moved = performer._frame(rig.source_neutral)

    assert identity_noise(rig, moved) == pytest.approx(0.0, abs=1e-9)


def test_head_pose_removal_still_works_on_the_re_based_rig(rig, performer):
    rebased = rebase(rig, performer.neutral, noise=0.0)
    turn = Rotation.from_euler("y", 12.0, degrees=True).as_matrix()
    centre = performer.neutral.mean(axis=0)
    turned = (performer.neutral - centre) @ turn.T + centre + 0.3

    weights = rebased.weights(turned, align=True)

    np.testing.assert_allclose(weights, np.eye(rig.num_examples)[0], atol=1e-6)


def test_a_region_rig_is_re_based_region_by_region(example_set, performer):
    k = example_set.num_points
    upper = example_set.target_vertices[0, :, 1] > np.median(example_set.target_vertices[0, :, 1])
    names = list(example_set.names[1:])
    regions = [
        Region("upper", range(k // 2), names[: len(names) // 2], upper.astype(float)),
        Region("lower", range(k // 2, k), names[len(names) // 2 :], (~upper).astype(float)),
    ]
    region_rig = fit_regions(example_set, regions)
    rebased = rebase(region_rig, performer.neutral, noise=NOISE * performer.radius)
    weights = np.concatenate([rebased.weights(x) for x in _every_expression(performer).values()])

    assert rebased.num_points == k
    assert weights[:, 1:].min() >= 0.0 and weights[:, 1:].max() <= 1.0


@pytest.mark.parametrize("noise", [-0.1, float("nan"), float("inf"), "loud", 1e300, 1e3])
def test_a_bad_noise_is_refused(rig, performer, noise):
    with pytest.raises(InputError) as raised:
        rebase(rig, performer.neutral, noise=noise)

    assert raised.value.code == "bad_noise"


def test_the_largest_noise_accepted_gives_finite_bounded_weights(rig, performer):
    noise = MAX_NOISE_RELATIVE * performer.radius * SCALE * 0.99
    rebased = rebase(rig, performer.neutral, noise=noise)
    weights = rebased.weights(performer.perform("happy", 0.7, 3))

    assert np.isfinite(weights).all()
    assert weights[:, 1:].min() >= 0.0 and weights[:, 1:].max() <= 1.0


def test_a_neutral_of_the_wrong_shape_is_refused_as_calibrated_refuses_it(rig):
    with pytest.raises(InputError) as raised:
        rebase(rig, np.zeros((3, 3)), noise=0.1)

    assert raised.value.code == "wrong_point_count"


def test_calibrate_is_exact_without_noise_and_rebases_with_it(rig, performer):
    frames = performer.perform("happy", 0.7, 5)

    exact = calibrate(rig, performer.neutral, None).weights(frames)
    bounded = calibrate(rig, performer.neutral, 0.0).weights(frames)

    np.testing.assert_array_equal(exact, rig.calibrated(performer.neutral).weights(frames))
    assert bounded[:, 1:].min() >= 0.0 and bounded[:, 1:].max() <= 1.0

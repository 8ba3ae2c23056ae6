"""A performer's own closed eye read as closed: the blink weights' map (issue 34)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facecast.rig import InputError, fit, load_rig
from facecast.rig.closure import MIN_CLOSED, ClosureMap, closure_ranges
from facecast.rig.demo import demo_example_set
from facecast.rig.evaluation.webcam import generic_rig, ict_performer
from facecast.rig.fit import refit_noise
from facecast.rig.rebase import (
    REBASE_BLINK_CONTRAST,
    REBASE_BLINK_CONTRAST_GAZELESS,
    calibrate,
    default_contrast,
)
from facecast.rig.retarget import fit_performer
from facecast.rig.sources.ict import locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set

NAMES = ("neutral", "eyeBlinkLeft", "eyeLookDownLeft", "eyeBlinkRight")


def test_ranges_are_the_readings_of_the_neutral_and_each_captured_blink():
    readings = {
        "neutral": np.array([1.0, -0.02, 0.01, 0.03]),
        "eyeBlinkLeft": np.array([0.2, 0.74, 0.06, 0.0]),
        "eyeBlinkRight": np.array([0.9, 0.0, 0.0, 0.03 + MIN_CLOSED / 2]),  # barely moves
    }
    ranges = closure_ranges(readings, NAMES)
    # The neutral's negative reading counts as 0; a blink read less than MIN_CLOSED above
    # the neutral is left alone (the map would multiply its noise by more than 5).
    assert ranges == {"eyeBlinkLeft": [0.0, 0.74]}
    assert closure_ranges({"eyeBlinkLeft": readings["eyeBlinkLeft"]}, NAMES) == {}


def test_the_map_reads_the_closed_eye_as_1_clips_and_keeps_the_sum():
    closure = ClosureMap.from_report({"closure": {"eyeBlinkLeft": [0.1, 0.6]}}, NAMES)
    assert closure is not None
    weights = np.array([[0.3, 0.6, 0.1, 0.0], [0.2, 0.35, 0.1, 0.35], [0.0, 0.9, 0.1, 0.0]])
    mapped = closure.apply(weights.copy())
    np.testing.assert_allclose(mapped[:, 1], [1.0, 0.5, 1.0])  # (w - 0.1) / 0.5, clipped
    np.testing.assert_allclose(mapped[:, 2:], weights[:, 2:])  # other weights untouched
    np.testing.assert_allclose(mapped.sum(axis=1), 1.0)
    # A single frame (the live path's own branch) maps as the batch does.
    np.testing.assert_allclose([closure.apply(w.copy()) for w in weights], mapped, atol=1e-15)


def test_the_contrast_curve_opens_a_partly_read_blink_and_closes_a_mostly_read_one():
    ranges = {"closure": {"eyeBlinkLeft": [0.1, 0.6]}}
    curved = ClosureMap.from_report({**ranges, "closure_contrast": [0.4, 0.8]}, NAMES)
    linear = ClosureMap.from_report(ranges, NAMES)
    assert curved is not None and linear is not None and curved.contrast == (0.4, 0.8)
    raw = np.linspace(0.0, 0.8, 81)  # the rig's reading of the left blink
    weights = np.stack([1.0 - raw - 0.1, raw, np.full_like(raw, 0.1), np.zeros_like(raw)], 1)
    mapped = curved.apply(weights.copy())
    lin = linear.apply(weights.copy())[:, 1]
    got = mapped[:, 1]
    # Mapped 0.3 (a held gaze's closing) opens, 0.6 stays, 0.9 (a quick blink's) closes.
    np.testing.assert_allclose(
        got[np.searchsorted(raw, [0.25, 0.40, 0.55])], [0.0, 0.5, 1.0], atol=1e-12
    )
    assert np.all(got[lin <= 0.4] == 0.0) and np.all(got[lin >= 0.8] == 1.0)
    assert np.all(np.diff(got) >= 0.0)  # monotone: a closing eye never reads opening
    np.testing.assert_allclose(mapped.sum(axis=1), 1.0)
    np.testing.assert_allclose(mapped[:, 2:], weights[:, 2:])
    np.testing.assert_allclose([curved.apply(w.copy()) for w in weights], mapped, atol=1e-15)


@pytest.mark.parametrize(
    "contrast", [None, "x", [0.4], [0.8, 0.4], [0.4, 0.4], [-0.1, 0.5], [0.5, 1.5], [0.4, "a"],
                 [float("nan"), 0.8]],
)  # fmt: skip
def test_an_unusable_contrast_leaves_the_map_linear(contrast):
    report = {"closure": {"eyeBlinkLeft": [0.1, 0.6]}, "closure_contrast": contrast}
    closure = ClosureMap.from_report(report, NAMES)
    assert closure is not None and closure.contrast is None


@pytest.mark.parametrize(
    "report",
    [None, {}, {"closure": "x"}, {"closure": {"other": [0, 1]}},
     {"closure": {"eyeBlinkLeft": [0.5, 0.55]}}, {"closure": {"eyeBlinkLeft": ["a", 1]}}],
)  # fmt: skip
def test_no_map_without_a_usable_closure_entry(report):
    assert ClosureMap.from_report(report, NAMES) is None


needs_ict = pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
SIGMA = 0.033  # cm: the tracker's landmark noise on the webcam benchmark's held frames


@pytest.fixture(scope="module")
def character():
    """person01's ARKit shapes fitted exactly, as ``facecast import ict-facekit`` stores them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exact ICT rig warns to fit with noise: known
        return fit(arkit_example_set(locate_ict(), identity="person01"))


@pytest.fixture(scope="module")
def performer_rig(character):
    """ICT person12's exact keys (a held capture's leftover noise on each) fitted onto
    person01 at the tracker's measured noise, and person12's exact key points."""
    performer = ict_performer(locate_ict(), identity="person12")
    exact = performer.landmark_points(np.eye(len(performer.names)))  # row i: key i alone
    rng = np.random.default_rng(0)
    keys = {("neutral" if i == 0 else name): exact[i] + rng.normal(0.0, 0.4 * SIGMA, exact[i].shape)
            for i, name in enumerate(performer.names)}  # fmt: skip
    return fit_performer(character, keys, noise=SIGMA), performer, exact


@pytest.fixture(scope="module")
def generic_calibrate(character, performer_rig):
    """What /perform's calibrate carries for the character's rig: person12's exact neutral
    and closed eyes, on the character's points."""
    _, performer, exact = performer_rig
    k = character.num_points
    blinks = {
        name: exact[performer.names.index(name)][:k] for name in ("eyeBlinkLeft", "eyeBlinkRight")
    }
    return exact[0][:k], blinks


@pytest.mark.ict
@needs_ict
def test_a_noisy_performers_wink_reads_closed_and_stays_one_sided(performer_rig):
    rig, performer, exact = performer_rig
    assert set(rig.fit_report["closure"]) == {"eyeBlinkLeft", "eyeBlinkRight"}
    unmapped = rig.with_weight_models(
        rig.models, {k: v for k, v in rig.fit_report.items() if k != "closure"}
    )
    left, right = rig.names.index("eyeBlinkLeft"), rig.names.index("eyeBlinkRight")
    rng = np.random.default_rng(1)
    wink = exact[performer.names.index("eyeBlinkLeft")] + rng.normal(
        0.0, SIGMA, (50, *exact[0].shape)
    )
    rest = exact[0] + rng.normal(0.0, SIGMA, (50, *exact[0].shape))

    mapped, plain = rig.weights(wink), unmapped.weights(wink)
    # Fitted for the noise, the rig reads the performer's own closed eye at about 0.8 (it
    # splits the lids' motion with the look down's); the map reads it closed.
    assert plain[:, left].mean() < 0.8  # measured 0.756
    assert mapped[:, left].mean() > 0.9  # measured 0.925
    assert mapped[:, right].max() < 0.15  # the other eye stays open (0.090; 0.071 unmapped)
    assert rig.weights(rest)[:, left].max() < 0.15  # and so does a resting face (0.086)
    np.testing.assert_allclose(mapped.sum(axis=1), 1.0)


@pytest.mark.ict
@needs_ict
def test_the_map_travels_with_the_rig_file_and_a_refit(performer_rig, tmp_path):
    rig, performer, exact = performer_rig
    frames = exact[[performer.names.index("eyeBlinkLeft"), 0]]
    path = tmp_path / "performer.rig"
    rig.save(path)
    np.testing.assert_allclose(load_rig(path).weights(frames), rig.weights(frames), atol=1e-6)
    refitted = refit_noise(rig, SIGMA / 2)
    assert refitted.fit_report["closure"] == rig.fit_report["closure"]
    assert rig.with_clamp("unit").fit_report["closure"] == rig.fit_report["closure"]


@pytest.mark.ict
@needs_ict
def test_a_rebased_rig_opens_a_half_closed_eye_and_closes_a_closed_one(
    character, performer_rig, generic_calibrate, tmp_path
):
    """The generic path: the character's own rig re-based on the performer's neutral with
    their captured closed eyes takes the contrast curve; their own rig keeps the linear map."""
    rig, performer, _ = performer_rig
    neutral, blinks = generic_calibrate
    k = character.num_points
    rebased = calibrate(character, neutral, SIGMA, blinks)
    assert rebased.fit_report["closure_contrast"] == list(REBASE_BLINK_CONTRAST)
    assert "closure_contrast" not in rig.fit_report
    linear = rebased.with_weight_models(
        rebased.models, {n: v for n, v in rebased.fit_report.items() if n != "closure_contrast"}
    )
    left = rebased.names.index("eyeBlinkLeft")
    shares = np.array([0.0, 0.3, 1.0])  # the left blink's weight in the performer's face
    act = np.zeros((len(shares), len(performer.names)))
    act[:, performer.names.index("eyeBlinkLeft")] = shares
    frames = performer.landmark_points(act)[:, :k]
    plain, curved = linear.weights(frames)[:, left], rebased.weights(frames)[:, left]
    assert 0.15 < plain[1] < 0.45  # the linear map reads the third-closed eye about so
    assert curved[1] < 0.05  # the curve opens it
    assert curved[2] > 0.99 and curved[0] < 0.01  # and reads closed and open as they are
    # The curve travels with the rig's file, as the map does.
    path = tmp_path / "rebased.rig"
    rebased.save(path)
    np.testing.assert_allclose(load_rig(path).weights(frames)[:, left], curved, atol=1e-6)


@pytest.mark.ict
@needs_ict
def test_closed_eyes_are_read_on_the_rig_without_its_map(performer_rig):
    """Reading the closed eyes again (a re-base of a rig that has a map) reads the rig
    itself, not its map: the same ranges, however often."""
    rig, performer, exact = performer_rig
    blinks = {
        name: exact[performer.names.index(name)] for name in ("eyeBlinkLeft", "eyeBlinkRight")
    }
    plain = rig.with_weight_models(
        rig.models, {n: v for n, v in rig.fit_report.items() if n != "closure"}
    )
    again = rig.with_closed_eyes(exact[0], blinks).fit_report["closure"]
    assert again == plain.with_closed_eyes(exact[0], blinks).fit_report["closure"]
    assert all(closed < 0.9 for _, closed in again.values())  # the rig's, not its map's 1


@pytest.mark.ict
@needs_ict
def test_a_performers_own_contrast_replaces_the_default_curve(
    character, performer_rig, generic_calibrate
):
    """calibrate's ``contrast`` (a calibrate's ``blink_contrast``, §5.1.3): a performer whose
    looks down read as half-closed raises the curve's low end, and a blink still reads
    closed."""
    _, performer, _ = performer_rig
    neutral, blinks = generic_calibrate
    k = character.num_points
    own = calibrate(character, neutral, SIGMA, blinks, contrast=(0.6, 0.9))
    default = calibrate(character, neutral, SIGMA, blinks)
    assert own.fit_report["closure_contrast"] == [0.6, 0.9]
    left = own.names.index("eyeBlinkLeft")
    shares = np.array([0.6, 1.0])  # the left blink 60 % and fully closed
    act = np.zeros((len(shares), len(performer.names)))
    act[:, performer.names.index("eyeBlinkLeft")] = shares
    frames = performer.landmark_points(act)[:, :k]
    part_own, closed_own = own.weights(frames)[:, left]
    part_default, _ = default.weights(frames)[:, left]
    assert part_default > 0.4 and part_own < 0.05  # measured 0.50 and 0.00: it reads open
    assert closed_own > 0.99  # and the closed eye still closed


@pytest.mark.ict
@needs_ict
def test_the_benchmarks_generic_path_reads_the_blinks_through_the_clients_curve(
    character, generic_calibrate
):
    """``bench webcam``'s generic rows (``webcam.generic_rig``) re-base as the client's
    calibrate asks: through the performer's own curve when one is sent (``?blink=``), the
    server's when none is, and no curve without captured closed eyes (the calibrate then
    carries none)."""
    neutral, blinks = generic_calibrate
    keys = {"neutral": neutral, **blinks}
    own = generic_rig(character, neutral, SIGMA, keys, (0.5, 0.85))
    server = generic_rig(character, neutral, SIGMA, keys)
    alone = generic_rig(character, neutral, SIGMA, {"neutral": neutral}, (0.5, 0.85))
    assert own.fit_report["closure_contrast"] == [0.5, 0.85]
    assert server.fit_report["closure_contrast"] == list(REBASE_BLINK_CONTRAST)
    assert "closure" not in alone.fit_report and "closure_contrast" not in alone.fit_report


def test_the_servers_curve_depends_on_whether_the_rig_reads_gaze():
    # README, issue 34's option (ak): a rig without eye-look examples (an uploaded
    # character's: its look-at turns its eyes) reads a blink less whole, so its high end is
    # lower; ARKit's eye-look shapes and VRM's look presets both count as gaze.
    assert default_contrast(("neutral", "eyeBlinkLeft", "eyeLookDownLeft")) == REBASE_BLINK_CONTRAST
    assert default_contrast(("neutral", "blink", "lookUp")) == REBASE_BLINK_CONTRAST
    assert default_contrast(("neutral", "eyeBlinkLeft", "jawOpen")) == (
        REBASE_BLINK_CONTRAST_GAZELESS
    )
    low, high = REBASE_BLINK_CONTRAST_GAZELESS
    assert low == REBASE_BLINK_CONTRAST[0] and high < REBASE_BLINK_CONTRAST[1]


@pytest.mark.ict
@needs_ict
def test_a_rig_without_gaze_is_rebased_through_the_gazeless_curve(generic_calibrate):
    """A character paired as an upload pairs it (no eye-look examples), re-based with the
    performer's closed eyes and no curve of their own, reads them through the server's
    curve for a rig without gaze."""
    neutral, blinks = generic_calibrate
    examples = arkit_example_set(locate_ict(), identity="person01")
    gazeless = [n for n in examples.names[1:] if not n.startswith("eyeLook")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = fit(examples.subset(gazeless))
    rebased = calibrate(rig, neutral[: rig.num_points], SIGMA, blinks)
    assert rebased.fit_report["closure_contrast"] == list(REBASE_BLINK_CONTRAST_GAZELESS)


@pytest.mark.parametrize(
    "contrast", [(0.8, 0.4), (0.5, 0.5), (-0.1, 0.5), (0.2, 1.5), (np.nan, 0.9), (0.5,), "lo"]
)
def test_an_unusable_own_contrast_is_refused(contrast):
    rig = fit(demo_example_set())
    with pytest.raises(InputError) as caught:
        calibrate(rig, rig.source_neutral, 0.01, None, contrast=contrast)
    assert caught.value.code == "bad_input"

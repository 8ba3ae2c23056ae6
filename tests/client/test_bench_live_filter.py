"""``bench live``'s figure for the live filter's delay, which the glass-to-glass stamps cannot
hold: the server's own filter, run offline on the bench's motion, trails its input."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.bench import live
from facecast.rig import fit
from facecast.rig.demo import demo_example_set
from facecast.rig.evaluation.temporal import lag_frames


@pytest.fixture(scope="module")
def exact_rig(tmp_path_factory):
    """The bench's rig (fitted exactly: the page's auto smoothing runs the one-euro)."""
    folder = tmp_path_factory.mktemp("rigs")
    live._write_rig(folder)
    return folder / f"{live.RIG}.rig"


def test_the_one_euro_filter_trails_the_bench_motion_by_a_fraction_of_a_frame(exact_rig):
    lags = {fps: live._filter_lag(exact_rig, "one-euro", fps) for fps in (10.0, 30.0)}

    for fps, lag in lags.items():
        assert lag is not None and lag["filter"] == "one-euro" and lag["fps"] == fps
        # Behind, never ahead, by less than a frame on a motion this slow (0.5 Hz).
        assert 0.05 < lag["frames"] < 1.0, lag
        assert lag["ms"] == pytest.approx(1000 * lag["frames"] / fps)


def test_a_rig_fitted_with_noise_is_figured_through_the_kalman_filter(tmp_path):
    path = tmp_path / "noisy.rig"
    fit(demo_example_set(), noise=0.05).save(path)

    lags = [live._filter_lag(path, "kalman", fps) for fps in (10.0, 30.0)]

    for lag in lags:
        assert lag is not None and lag["filter"] == "kalman"
        # On a motion this slow the Kalman follows within a fraction of a frame (a whole
        # period later the motion repeats: never read as a lag).
        assert abs(lag["frames"]) < 0.5, lag


def test_no_figure_without_a_filter_or_for_another_than_the_channel_ran(exact_rig):
    assert live._filter_lag(exact_rig, None, 30.0) is None  # ?smoothing=off
    assert live._filter_lag(exact_rig, "kalman", 30.0) is None  # a calibrate started it
    assert live._filter_lag(exact_rig, "one-euro", 0.0) is None  # nothing tracked


def test_the_lag_measure_finds_a_known_delay_of_the_bench_motion():
    # lag_frames on the bench's own motion, delayed by a known 1.5 frames, says 1.5.
    fps = 30.0
    t = np.arange(600) / fps
    truth = live._jaw(t)
    delayed = live._jaw(t - 1.5 / fps)
    assert lag_frames(truth, delayed) == pytest.approx(1.5, abs=0.05)

"""Evaluation measures on known inputs."""

import numpy as np

from articast.core.evaluation.measures import (
    jitter_mm,
    lag_frames,
    rms_3d,
    score_sequence,
    still_pairs,
)
from tests.blobface import blob_model


def test_rms_is_zero_at_truth_and_grows_with_error():
    m = blob_model()
    a = np.random.default_rng(0).normal(size=(5, 7))
    assert np.allclose(rms_3d(m, a, a), 0)
    e1 = rms_3d(m, a + 0.1, a)
    e2 = rms_3d(m, a + 0.2, a)
    np.testing.assert_allclose(e2, 2 * e1)  # the model is linear


def test_lag_detects_a_shift():
    t = np.arange(200)
    truth = np.sin(t / 7.0)
    assert lag_frames(np.roll(truth, 3), truth) == 3
    assert lag_frames(truth, truth) == 0
    assert lag_frames(np.roll(truth, -2), truth) == -2


def test_jitter_counts_only_still_segments():
    m = blob_model()
    pts = np.repeat(m.mean[None], 6, 0)
    pts[3:] += 1.0  # a jump between 2 and 3: not a still pair
    still = still_pairs(pts)
    assert still.tolist() == [True, True, False, True, True]
    alpha = np.zeros((6, 7))
    alpha[1] = 0.05  # tracked geometry wobbles on a still segment
    assert jitter_mm(m, alpha, still) > 0
    assert jitter_mm(m, np.zeros((6, 7)), still) == 0


def test_score_sequence_of_a_perfect_track():
    m = blob_model()
    a = np.random.default_rng(1).normal(size=(10, 7))
    s = score_sequence(m, a, np.ones(10, bool), np.full(10, 4), np.full(10, 2.0), m.shape(a))
    summ = s.summary()
    assert summ["rms_mm_mean"] < 1e-9 and summ["rms_points_mm_mean"] < 1e-9
    assert summ["evals_per_frame"] == 4 and summ["ok_fraction"] == 1.0

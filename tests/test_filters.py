"""The One Euro filter of live tracking: a still noisy signal is smoothed, a fast one passes."""

import numpy as np

from articast.core.tracking.filters import OneEuroFilter, OneEuroPolicy


def test_still_noise_is_smoothed_and_fast_motion_passes_with_little_lag():
    rng = np.random.default_rng(0)
    fps = 30.0
    t = np.arange(300) / fps
    still = 0.05 * rng.standard_normal((300, 7))
    f = OneEuroFilter(OneEuroPolicy(min_cutoff=3.0, beta=1.0))
    out = np.array([f(x, ti) for x, ti in zip(still, t, strict=True)])
    assert out[30:].std() < 0.6 * still[30:].std()
    # a 4 Hz articulation of 2 s.d.: followed with at most a frame of lag
    f.reset()
    wave = 2.0 * np.sin(2 * np.pi * 4.0 * t)[:, None] * np.ones(7)
    out = np.array([f(x, ti) for x, ti in zip(wave, t, strict=True)])
    lags = [float(np.dot(out[30 + s:270 + s, 0], wave[30:270, 0])) for s in range(0, 4)]
    assert int(np.argmax(lags)) <= 1
    assert np.abs(out[30:, 0]).max() > 0.8 * 2.0  # the amplitude survives


def test_first_sample_and_time_going_backwards_restart_the_filter():
    f = OneEuroFilter()
    assert np.allclose(f(np.array([1.0, 2.0]), 0.0), [1.0, 2.0])
    f(np.array([1.0, 2.0]), 0.1)
    assert np.allclose(f(np.array([5.0, 5.0]), 0.05), [5.0, 5.0])  # not after the last: restart

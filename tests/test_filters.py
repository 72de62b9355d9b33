"""The output filters of live tracking: the One Euro filter (a still noisy signal is smoothed, a
fast one passes) and the reading cadence's canceller."""

import numpy as np
import pytest

from articast.core.tracking.filters import CadenceCanceller, OneEuroFilter, OneEuroPolicy


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


def _cadence_run(x: np.ndarray, period: int = 3, rate: float = 0.1,
                 phases: np.ndarray | None = None) -> np.ndarray:
    c = CadenceCanceller(period, rate)
    ph = np.arange(len(x)) % period if phases is None else phases
    return np.array([c(v, int(p)) for v, p in zip(x, ph, strict=True)])


def test_the_cadence_canceller_removes_a_sawtooth_locked_to_the_readings():
    fps, n = 25.0, 250
    t = np.arange(n) / fps
    speech = np.c_[np.sin(2 * np.pi * 1.3 * t), 0.5 * np.cos(2 * np.pi * 0.7 * t)]
    phase = np.arange(n) % 3
    saw = np.array([-1.0, 0.2, 0.8])[phase][:, None] * np.array([0.3, -0.2])
    out = _cadence_run(speech + saw)
    late = slice(125, None)  # after ~40 readings
    before = np.sqrt(np.mean(saw[late] ** 2))
    after = np.sqrt(np.mean((out[late] - speech[late]) ** 2))
    assert after < 0.2 * before
    # causal and without lag: the speech itself is not delayed (its error is not a shift)
    assert np.abs(out[late] - speech[late]).max() < 0.5 * np.abs(saw).max()


def test_the_cadence_canceller_leaves_an_estimate_without_a_cadence_alone():
    rng = np.random.default_rng(0)
    n = 300
    ramp = np.linspace(0.0, 6.0, n)[:, None]  # a steady motion deviates alike at every phase
    out = _cadence_run(ramp)
    assert np.abs(out - ramp).max() < 0.1 * 0.02  # a tenth of one frame's motion at most
    assert np.allclose(out[90:], ramp[90:], atol=1e-4)  # once every phase has settled
    noisy = ramp + rng.normal(0.0, 0.1, (n, 1))
    out = _cadence_run(noisy)
    # no cadence: what it takes off is a small fraction of the noise, and averages to zero
    assert np.sqrt(np.mean((out - noisy) ** 2)) < 0.25 * 0.1
    assert abs(np.mean(out - noisy)) < 0.01


def test_the_cadence_canceller_follows_rereads_and_gaps():
    # phases as the tracker gives them: a reading may come early (a reread: phase 0 twice)
    phases = np.array([0, 1, 2, 0, 0, 1, 2, 0, 1, 2] * 30)
    saw = np.array([-1.0, 0.5, 0.5])[phases] * 0.2
    x = np.zeros(len(phases)) + saw
    out = _cadence_run(x[:, None], phases=phases)[:, 0]
    assert np.sqrt(np.mean(out[150:] ** 2)) < 0.3 * np.sqrt(np.mean(saw[150:] ** 2))
    c = CadenceCanceller(3, 0.1)
    for i in range(30):
        c(np.array([saw[i]]), int(phases[i]))
    c.reset()  # a gap: the recent frames go, the offsets (slow) stay
    assert abs(c(np.array([5.0]), 0)[0] - 5.0) > 0.01
    c.forget()  # a new face: nothing stays
    assert c(np.array([5.0]), 0)[0] == 5.0
    with pytest.raises(ValueError):
        CadenceCanceller(1)
    with pytest.raises(ValueError):
        CadenceCanceller(3, 0.0)


def test_a_jump_is_not_learned_as_the_cadence():
    n = 300
    phase = np.arange(n) % 3
    saw = np.array([-1.0, 0.4, 0.6])[phase] * 0.2
    step = np.where(np.arange(n) >= 150, 10.0, 0.0)  # a lost state found again, unannounced
    out = _cadence_run((saw + step)[:, None])[:, 0]
    err = out - step
    # the sawtooth stays cancelled right after the jump: the jump's deviations (50x the
    # cadence's) are clipped at a few times the phases' own spread
    assert np.sqrt(np.mean(err[153:190] ** 2)) < 0.4 * np.sqrt(np.mean(saw ** 2))
    assert np.abs(err[153:]).max() < 0.1

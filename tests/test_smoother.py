"""The offline smoother (core/tracking/smoother.py): the motion model's fixed-lag RTS smoother
on a simulated constant-velocity filter with a known truth, and the zero-phase One Euro."""

from __future__ import annotations

import numpy as np
import pytest

from articast.core.model.camera import rotation_matrix
from articast.core.tracking.filters import OneEuroFilter, OneEuroPolicy
from articast.core.tracking.kalman import ConstantVelocity, MotionNoise
from articast.core.tracking.smoother import (
    FixedLag,
    offline_articulation,
    rts_window,
    zero_phase_one_euro,
)

K, FPS, SD = 7, 25.0, 0.3


def filtered_run(n: int = 150, seed: int = 0, restart_at: int | None = None,
                 sines: bool = False):
    """An articulation read every frame with noise of SD, the head still, through the filter
    as live tracking runs it: predict, the frame's posterior from the prediction and the
    reading, update. The articulation is the motion model's own process (white acceleration
    of the filter's q: the smoother is then the optimal estimate) or, ``sines``, speech-like
    sines of 2-5 Hz and 1 s.d. Returns the truth (n, K), the filtered states and the steps."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    q = 2000.0 if sines else 300.0
    if sines:
        f, ph = rng.uniform(2.0, 5.0, K), rng.uniform(0, 2 * np.pi, K)
        truth = np.sin(2 * np.pi * f * t[:, None] + ph)
    else:
        acc = rng.normal(0.0, np.sqrt(q * FPS), (n, K))  # density q sampled at FPS
        truth = np.cumsum(np.cumsum(acc, 0) / FPS, 0) / FPS
    noise = MotionNoise(np.concatenate([np.full(K, q), np.full(3, 5.0), np.full(3, 2e5)]),
                        MotionNoise.default(K).initial_velocity_sd)
    cv = ConstantVelocity(K, noise)
    rot, trans = np.zeros(3), np.array([0.0, 0.0, 400.0])
    info_m = np.diag(np.concatenate([np.full(K, 1.0 / SD**2), np.full(6, 1e6)]))
    filt, steps = np.zeros((n, K)), []
    for i in range(n):
        z = truth[i] + rng.normal(0.0, SD, K)
        if i == 0 or i == restart_at:
            cv.start(z, rot, trans)
        prior = cv.predict(1.0 / FPS)
        x_p = np.concatenate([prior.alpha, np.zeros(3), prior.translation])
        x_m = np.concatenate([z, np.zeros(3), trans])
        x = np.linalg.solve(prior.information + info_m,
                            prior.information @ x_p + info_m @ x_m)
        cv.update(x[:K], rot, x[K + 3:], info_m)
        filt[i] = cv.alpha
        steps.append(cv.step)
    return truth, filt, steps


def smooth_all(steps, lag):
    sm = FixedLag(lag)
    out = [s for st in steps for s in sm.push(st)] + sm.flush()
    return np.array([s[0] for s in out]), out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_smoother_uses_the_frames_after_and_is_nearer_the_truth(seed):
    truth, filt, steps = filtered_run(seed=seed)
    assert steps[0].linked is False and all(s.linked for s in steps[1:])
    rms_f = np.sqrt(np.mean((filt - truth) ** 2))
    for lag, bound in ((1, 0.9), (6, 0.8)):
        sm, _ = smooth_all(steps, lag)
        rms_s = np.sqrt(np.mean((sm - truth) ** 2))
        assert rms_s < bound * rms_f, (lag, rms_s, rms_f)
    # a fixed lag of 6 frames gives nearly what the whole clip does
    six, _ = smooth_all(steps, 6)
    full, _ = smooth_all(steps, 10_000)
    rms = [np.sqrt(np.mean((x - truth) ** 2)) for x in (six, full)]
    assert rms[0] < 1.02 * rms[1] and np.max(np.abs(six - full)) < SD
    # the streamed smoother (each pair's gain computed once) is the window's RTS pass
    _, states = smooth_all(steps, 3)
    for i in (0, 70, len(steps) - 2):
        direct = rts_window(steps[i:i + 4])
        assert all(np.allclose(a, b) for a, b in zip(states[i], direct, strict=True))


def test_the_smoother_does_not_lag_where_the_filter_does():
    """On speech-like sines the motion model's prediction holds the filter back (a third of
    a frame late); the smoother is not."""
    truth, filt, steps = filtered_run(sines=True)
    full, _ = smooth_all(steps, 10_000)

    def late(x):  # least-squares shift of x against the truth, in frames (+: late)
        vel = np.gradient(truth, axis=0)
        return -float(np.sum((x - truth) * vel) / np.sum(vel * vel))

    assert late(filt) > 0.15 and abs(late(full)) < 0.25 * late(filt)


def test_a_restart_ends_the_window_and_the_last_frame_is_its_own():
    truth, filt, steps = filtered_run(60, seed=1, restart_at=30)
    assert steps[30].linked is False
    sm, states = smooth_all(steps, 10_000)
    # nothing after the restart reaches frame 29: it is smoothed as if the clip ended there
    alone, _ = smooth_all(steps[:30], 10_000)
    assert np.allclose(sm[:30], alone)
    # the last frame of a window has nothing after it: its filtered state
    assert np.allclose(sm[29], filt[29]) and np.allclose(sm[-1], filt[-1])
    assert np.allclose(states[-1][1], rotation_matrix(np.zeros(3)))
    with pytest.raises(ValueError):
        rts_window([])
    with pytest.raises(ValueError):
        FixedLag(-1)


def test_a_frame_without_a_step_is_passed_through_as_none():
    _, _, steps = filtered_run(20, seed=2)
    sm = FixedLag(3)
    out = [s for st in (*steps[:10], None, *steps[10:]) for s in sm.push(st)] + sm.flush()
    assert len(out) == 21 and out[10] is None and all(s is not None for i, s in
                                                      enumerate(out) if i != 10)


def test_the_zero_phase_one_euro_adds_no_lag():
    t = np.arange(200) / FPS
    x = np.sin(2 * np.pi * 1.5 * t)[:, None]
    fwd = OneEuroFilter()
    one_way = np.array([fwd(v, s) for v, s in zip(x, t, strict=True)])
    both = zero_phase_one_euro(x, t, np.zeros(200, bool))
    mid = slice(20, 180)

    def late(y):
        vel = np.gradient(x[mid, 0])
        return -float(np.sum((y[mid, 0] - x[mid, 0]) * vel) / np.sum(vel * vel))

    assert late(one_way) > 0.3 and abs(late(both)) < 0.1
    # a start cuts the two passes: nothing leaks across it
    starts = np.zeros(200, bool)
    starts[100] = True
    cut = zero_phase_one_euro(x, t, starts)
    assert np.allclose(cut[100:], zero_phase_one_euro(x[100:], t[100:], starts[100:]))
    assert np.allclose(cut[:100], zero_phase_one_euro(x[:100], t[:100], starts[:100]))


def test_frames_not_ok_are_left_as_tracked():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(40, K))
    ok = np.ones(40, bool)
    ok[[5, 6, 20]] = False
    out = offline_articulation(a, np.arange(40) / FPS, ok, np.arange(40) % 3,
                               np.zeros(40, bool), 3)
    assert np.array_equal(out[~ok], a[~ok]) and not np.allclose(out[ok], a[ok])


def test_the_offline_one_euro_runs_only_when_given_its_constants():
    """Without a policy (the offline default since session 9, core/faces/offline.ONE_EURO)
    and without a cadence to cancel, the smoothed fits are written as they are; with one, the
    zero-phase filter smooths them: less frame-to-frame change, the same mean."""
    rng = np.random.default_rng(5)
    t = np.arange(120) / FPS
    a = np.cumsum(rng.normal(size=(120, K)), axis=0) * 0.1 + rng.normal(size=(120, K)) * 0.05
    ok, starts = np.ones(120, bool), np.zeros(120, bool)
    plain = offline_articulation(a, t, ok, np.zeros(120, int), starts, None, policy=None)
    assert np.array_equal(plain, a)
    filtered = offline_articulation(a, t, ok, np.zeros(120, int), starts, None,
                                    policy=OneEuroPolicy())
    assert np.abs(np.diff(filtered, axis=0)).mean() < 0.8 * np.abs(np.diff(a, axis=0)).mean()
    assert np.allclose(filtered.mean(axis=0), a.mean(axis=0), atol=0.05)


def test_two_readers_are_averaged_only_where_both_have_the_frame():
    """core/faces/offline.averaged: the mean articulation where both trackers smoothed the
    frame, the first's head pose; the first's frame where the second has none; none where
    the first has none (its verdict stands)."""
    from articast.core.faces.offline import Smoothed, averaged
    from articast.core.model.camera import Pose

    rng = np.random.default_rng(4)

    def frame(seed_alpha: np.ndarray, turn: float) -> Smoothed:
        return Smoothed(seed_alpha, Pose(np.array([0.0, turn, 0.0]), np.array([0, 0, 600.0])))

    a = [frame(rng.normal(size=K), 0.1) for _ in range(4)]
    b = [frame(rng.normal(size=K), -0.2) for _ in range(4)]
    first = [a[0], a[1], None, a[3]]
    second = [b[0], None, b[2], b[3]]
    out = averaged(first, second)
    assert out[2] is None and out[1] is a[1]
    for i in (0, 3):
        got = out[i]
        assert got is not None
        assert np.allclose(got.alpha, 0.5 * (a[i].alpha + b[i].alpha))
        assert np.allclose(got.pose.rotation, a[i].pose.rotation)
    with pytest.raises(ValueError, match="3 frames against 4"):
        averaged(first[:3], second)

"""A motion model for the tracked state: constant velocity with white-noise acceleration, the
frame's fit as the measurement (an iterated extended Kalman filter).

State: the articulation alpha (K) and the head pose (rotation increment on the left of a
reference rotation, translation mm) -- n = K + 6 -- and their velocities. Each frame:

1. :meth:`ConstantVelocity.predict` moves the state by its velocity over ``dt`` and widens
   its covariance by the process noise ``q`` (per unit, per s^3: how fast each unknown's
   velocity may change; learned from the enrolment clip, :func:`process_noise`);
2. the frame is fitted with the prediction as a Gaussian prior on the whole state
   (:class:`~articast.core.tracking.fitting.StatePrior`: this is the filter's update, solved
   by the same Gauss-Newton that reads the image and the landmarks);
3. :meth:`ConstantVelocity.update` takes the fitted state and the information the frame's
   data carried about it: the velocities follow through their covariance with the state.

No lag is added by the filter itself beyond what the data leave undetermined: where the
frame's evidence is strong its fit is the state; where it is weak (a still mouth between
noisy readings) the prediction holds it.

Each update (or hold) leaves a :class:`MotionStep`, the prediction and the posterior of that
frame, for a smoother that may wait for the frames after
(:func:`~articast.core.tracking.smoother.rts_window`, offline ``articast track``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articast.core.model.camera import axis_angle, rotation_matrix, rotation_of, small_turn
from articast.core.tracking import kernels
from articast.core.tracking.fitting import StatePrior

_NONE = np.zeros((0, 0))  # cv_update: no information


@dataclass(frozen=True)
class MotionNoise:
    """Process noise: spectral density of the acceleration of each unknown (alpha units, rad,
    mm per s^2, squared, per Hz), and the initial velocity uncertainty (per s)."""

    q: np.ndarray
    initial_velocity_sd: np.ndarray

    @classmethod
    def default(cls, k: int) -> MotionNoise:
        # speech: articulation crossing ~2 training s.d. in ~0.1 s; a head turning at ~1 rad/s
        # and moving ~300 mm/s at most, accelerating within ~0.2 s
        q = np.concatenate([np.full(k, 2000.0), np.full(3, 5.0), np.full(3, 2e5)])
        v0 = np.concatenate([np.full(k, 10.0), np.full(3, 0.5), np.full(3, 200.0)])
        return cls(q, v0)


@dataclass(frozen=True)
class MotionStep:
    """One frame of the motion model, as a smoother needs it. ``predicted`` and ``posterior``
    are states (alpha (K,), rotation (3, 3), translation (3,), velocity (K + 6,)), ``p_pred``
    and ``p_post`` their (2n, 2n) covariances (the rotation's block in the left increment's
    axis-angle); ``dt`` the prediction's step (s); ``linked`` False where the model was
    (re)started since the step before, which its prediction does not then continue."""

    predicted: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    p_pred: np.ndarray
    posterior: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    p_post: np.ndarray
    dt: float
    linked: bool


MAX_PERIOD_S = 0.05
"""The motion model holds over short horizons only (speech is bounded: over longer lags its
second differences stop growing like a random walk's), so process noise is learned only from
frames at least this close (20 fps and up); a clip sampled more sparsely keeps the defaults."""


def process_noise(alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                  times: np.ndarray, floor: MotionNoise | None = None) -> MotionNoise:
    """The acceleration noise of each unknown from an enrolment sequence: alpha (F, K),
    rotation (F, 3) axis-angle, translation (F, 3) at ``times`` (F,) s (increasing; gaps
    allowed). A white-noise acceleration of density q gives second differences over h s of
    variance (2/3) q h^3; measurement noise of s.d. s adds 6 s^2: both are solved for, per
    unknown, from second differences over one and two frame periods (equally spaced triples
    only; robust variances, so the landmarks' outliers stay out). The defaults
    (:meth:`MotionNoise.default`) where the frames are further apart than
    :data:`MAX_PERIOD_S` or too few; ``floor`` (default: the defaults / 100) keeps a still
    enrolment clip from freezing the filter, and nothing is learned above the defaults."""
    k = alpha.shape[1]
    base = MotionNoise.default(k)
    lo = (floor or MotionNoise(base.q / 100.0, base.initial_velocity_sd)).q
    t = np.asarray(times, np.float64)
    steps = np.diff(t)
    if len(t) < 10 or not np.any(steps > 0):
        return base
    period = float(np.min(steps[steps > 0]))
    if period > MAX_PERIOD_S:
        return base
    rots = rotation_matrix(np.asarray(rotation))
    ref = rots[0]
    turn = np.array([axis_angle(r @ ref.T) for r in rots])
    x = np.hstack([alpha, turn, translation])
    rows, vals = [], []
    for lag in (1, 2):
        h = lag * period
        tol = 0.25 * period
        i = np.arange(len(t))
        # triples (a, b, c) with t_b - t_a = t_c - t_b = h: searched by time
        b = np.searchsorted(t, t + h - tol)
        c = np.searchsorted(t, t + 2 * h - tol)
        ok = ((b < len(t)) & (c < len(t)))
        ok[ok] &= (np.abs(t[b[ok]] - t[i[ok]] - h) < tol) & (np.abs(t[c[ok]] - t[i[ok]] - 2 * h)
                                                              < tol)
        if ok.sum() < 8:
            break
        d = x[c[ok]] - 2 * x[b[ok]] + x[i[ok]]
        var = (1.4826 * np.median(np.abs(d - np.median(d, 0)), 0)) ** 2
        rows.append([2.0 / 3.0 * h**3, 6.0])
        vals.append(var)
    if len(rows) < 2:
        return base
    sol = np.linalg.lstsq(np.array(rows), np.array(vals), rcond=None)[0]  # q, s^2 per unknown
    return MotionNoise(np.clip(sol[0], lo, base.q), base.initial_velocity_sd)


class ConstantVelocity:
    """The filter; call :meth:`start` on a first state, then per frame :meth:`predict`, fit with
    :meth:`prior`, :meth:`update`."""

    def __init__(self, k: int, noise: MotionNoise | None = None,
                 speaker: float | None = None) -> None:
        """speaker : the weight of the speaker's distribution the fit multiplies each
        prediction by (:meth:`StatePrior.with_speaker`), if any: :meth:`predict` makes that
        prior too, in its own compiled call, and ``with_speaker(speaker)`` returns it."""
        self.k, self.n = k, k + 6
        self.noise = noise or MotionNoise.default(k)
        self.speaker = speaker
        self.started = False
        self.step: MotionStep | None = None  # the last update's or hold's (smoothers)
        self._linked = False

    def start(self, alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
              information: np.ndarray | None = None) -> None:
        """(Re)start at a state with zero velocity. information : (n, n) what is known of the
        state (None: a weak prior, 1 unit / 0.05 rad / 20 mm)."""
        n = self.n
        self.alpha = np.array(alpha, np.float64)
        self.rot = rotation_matrix(np.asarray(rotation, np.float64))
        self.t = np.array(translation, np.float64)
        self.v = np.zeros(n)
        p = np.zeros((2 * n, 2 * n))
        if information is None:
            sd = np.concatenate([np.full(self.k, 1.0), np.full(3, 0.05), np.full(3, 20.0)])
            p[:n, :n] = np.diag(sd**2)
        else:
            p[:n, :n] = np.linalg.pinv(information + 1e-9 * np.eye(n))
        p[n:, n:] = np.diag(self.noise.initial_velocity_sd**2)
        self.p = p
        self.started = True
        self._linked = False  # (the next step does not continue the one before)
        self._pred: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def predict(self, dt: float) -> StatePrior:
        """Move the state by its velocity over ``dt`` s; returns the prediction as a prior."""
        n = self.n
        dt = float(min(max(dt, 1e-3), 1.0))
        # F P F^T + Q by blocks, F = [[I, dt I], [0, I]] (the 2n x 2n products cost more)
        q = self.noise.q
        k = self.k
        speaker = None
        if kernels.AVAILABLE:  # the same sums and inverse in one compiled call, and the
            # speaker's prior on it (StatePrior.with_speaker's numbers) where one is given
            x, y, z = self.v[k:k + 3].tolist()  # (rotation_matrix(dt * v[k:k + 3]), on floats)
            rot = rotation_of(dt * x, dt * y, dt * z) @ self.rot
            w = -1.0 if self.speaker is None else float(self.speaker)
            p, info, alpha, t, *sp = kernels.cv_predict(self.p, q, dt**3, dt**2, dt,
                                                        self.alpha, self.v, self.t, rot, w)
            if w >= 0:
                speaker = (w, StatePrior(*sp))
        else:
            i = np.arange(n)
            pxx, pxv, pvv = self.p[:n, :n], self.p[:n, n:], self.p[n:, n:]
            cross = pxv + dt * pvv
            p = np.empty_like(self.p)
            p[:n, :n] = pxx + dt * (pxv + pxv.T) + dt * dt * pvv
            p[:n, n:] = cross
            p[n:, :n] = cross.T
            p[n:, n:] = pvv
            p[i, i] += q * dt**3 / 3.0
            p[i, n + i] += q * dt**2 / 2.0
            p[n + i, i] += q * dt**2 / 2.0
            p[n + i, n + i] += q * dt
            info = np.linalg.inv(p[:n, :n] + 1e-12 * np.eye(n))
            alpha = self.alpha + dt * self.v[:k]
            rot = rotation_matrix(dt * self.v[k:k + 3]) @ self.rot
            t = self.t + dt * self.v[k + 3:]
        self._pred = (alpha, rot, t, p)
        self._info = info
        self._dt = dt
        return StatePrior.made(alpha, rot, t, info, speaker)

    def update(self, alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
               information: np.ndarray | None) -> None:
        """The frame's fitted state (the fit used :meth:`predict`'s prior) and its data
        information (n, n) (None: the frame told nothing: keep the prediction's covariance)."""
        assert self._pred is not None, "predict() first"
        a_p, r_p, t_p, p = self._pred
        n = self.n
        r_f = rotation_matrix(np.asarray(rotation, np.float64))
        # the new state's own copies: writable (a pose's arrays are read-only, another type
        # to the compiled call, which would compile again on a live frame), never shared
        a_f, t_f = np.array(alpha, np.float64), np.array(translation, np.float64)
        if kernels.AVAILABLE:  # the same algebra in one compiled call (the innovation too,
            # but the rotations' product, numpy's)
            self.p, v = kernels.cv_update(p, self._info, a_f, a_p, r_f @ r_p.T, t_f, t_p,
                                          self.v, _NONE if information is None
                                          else np.asarray(information, np.float64))
        else:
            e = np.concatenate([a_f - a_p, small_turn(r_f @ r_p.T), t_f - t_p])
            pxx = p[:n, :n]
            gain = (self._info @ p[:n, :]).T  # (2n, n): P_{:,x} Pxx^-1 (predict's inverse)
            v = self.v + (gain @ e)[n:]
            if information is None:
                post = pxx
            else:
                post = np.linalg.inv(self._info + information)
            self.p = p - gain @ (pxx - post) @ gain.T
            self.p = 0.5 * (self.p + self.p.T)
        v_pred = self.v
        self.alpha, self.rot, self.t, self.v = a_f, r_f, t_f, v
        self.step = MotionStep((a_p, r_p, t_p, v_pred), p, (self.alpha, r_f, self.t, v),
                               self.p, self._dt, self._linked)
        self._linked = True
        self._pred = None

    def hold(self) -> None:
        """A frame without a fit: keep the prediction as the state (velocity kept)."""
        assert self._pred is not None, "predict() first"
        pred = self._pred
        self.alpha, self.rot, self.t, self.p = pred
        state = (self.alpha, self.rot, self.t, self.v)
        self.step = MotionStep(state, self.p, state, self.p, self._dt, self._linked)
        self._linked = True
        self._pred = None

"""Smoothing a track with the frames after it: recorded video, where nothing is live.

Live, frame t's estimate can only use frames up to t: the motion model's prediction holds a
fit back where the frame's evidence is weak, and the One Euro filter trades the still
mouth's jitter for lag (docs/TRACKING.md). Offline (``articast track``) the frames after
are there, and the same motion model uses them:

1. :func:`rts_window`, a fixed-lag Rauch-Tung-Striebel smoother: frame t's state is
   corrected by how far the later frames' (smoothed) states ended from what the motion model
   predicted for them, through the gain ``G = P(t|t) F^T P(t+1|t)^-1`` of each
   :class:`~articast.core.tracking.kalman.MotionStep`; the head's rotation in the left
   increment's axis-angle, as the filter has it. A constant-velocity model forgets within a
   few frames, so a lag of :data:`LAG` frames gives what the whole clip would (a scratch
   version on the peers' clips: r within 0.0005 of the whole clip's from 3 frames on, 0.0001
   from 6; docs/history/REAL_SPEAKERS_LOG.md, "Where the lag is").
2. :func:`offline_articulation`: the reading cadence's sawtooth taken off
   (:class:`~articast.core.tracking.filters.CadenceCanceller`, as live), then, if asked
   for, the One Euro filter run forward and back, so that its smoothing of a still mouth
   adds no lag either way. Since session 9 only for a clip read by one tracker
   (core/faces/offline.py :data:`~articast.core.faces.offline.ONE_EURO_READERS`): run
   twice, it smooths more than the live filter does, and rounded the mouth's fast openings
   off on faces of both halves of the people (docs/TRACKING.md, "Offline without the One
   Euro filter").

Pure functions over the steps and arrays; the track command streams the frames through
:class:`FixedLag` and rewrites its lines at the end (service/commands/track.py).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np

from articast.core.model.camera import rotation_matrix, small_turn
from articast.core.tracking.filters import CadenceCanceller, OneEuroFilter, OneEuroPolicy
from articast.core.tracking.kalman import MotionStep

State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # alpha, rotation, t, velocity

LAG = 6
"""Frames the smoother waits for (:class:`FixedLag`)."""


def _minus(a: State, b: State) -> np.ndarray:
    """a - b in the filter's coordinates (2n,): alpha, the rotation's left increment, the
    translation, the velocities."""
    return np.concatenate([a[0] - b[0], small_turn(a[1] @ b[1].T), a[2] - b[2], a[3] - b[3]])


def _plus(a: State, d: np.ndarray) -> State:
    k = len(a[0])
    return (a[0] + d[:k], rotation_matrix(d[k:k + 3]) @ a[1], a[2] + d[k + 3:k + 6],
            a[3] + d[k + 6:])


def rts_gain(now: MotionStep, nxt: MotionStep) -> np.ndarray:
    """The smoother's gain from ``now`` to the step after it: G = P(t|t) F^T P(t+1|t)^-1, by
    a solve (P(t+1|t) symmetric)."""
    n = len(now.posterior[3])
    f = np.eye(2 * n)
    f[:n, n:] = nxt.dt * np.eye(n)
    return np.linalg.solve(nxt.p_pred, f @ now.p_post).T


def rts_window(steps: Sequence[MotionStep],
               gains: Sequence[np.ndarray | None] | None = None) -> State:
    """``steps[0]``'s state smoothed with the steps after it: the backward RTS pass from the
    last step that the motion model links to it (a restart ends the window). ``gains[u]``:
    :func:`rts_gain` of steps u and u + 1 if known (None or missing: computed here)."""
    if not steps:
        raise ValueError("no steps to smooth")
    end = 1
    while end < len(steps) and steps[end].linked:
        end += 1
    s = steps[end - 1].posterior
    for u in range(end - 2, -1, -1):
        now, nxt = steps[u], steps[u + 1]
        gain = gains[u] if gains is not None and u < len(gains) else None
        if gain is None:
            gain = rts_gain(now, nxt)
        s = _plus(now.posterior, gain @ _minus(s, nxt.predicted))
    return s


class FixedLag:
    """Streams frames' steps and gives each one's smoothed state :data:`LAG` frames later
    (:meth:`push`), the rest at the end (:meth:`flush`). A frame without a step (not fitted)
    is passed as None and given back as None. Each pair of steps' gain is computed once, when
    the second arrives (a frame is in ``lag`` windows)."""

    def __init__(self, lag: int = LAG) -> None:
        if lag < 0:
            raise ValueError("a smoother's lag is 0 frames or more")
        self.lag = lag
        self._buf: deque[MotionStep | None] = deque()
        self._gains: deque[np.ndarray | None] = deque()  # _buf[u] to _buf[u + 1]

    def _oldest(self) -> State | None:
        first, gain = self._buf.popleft(), self._gains.popleft()
        if first is None:
            return None
        window = [first]
        for st in self._buf:
            if st is None:
                break
            window.append(st)
        return rts_window(window, [gain, *self._gains])

    def push(self, step: MotionStep | None) -> list[State | None]:
        """The frame's step in; out, the state of the frame ``lag`` frames before (a list of
        one), or nothing while the first frames wait."""
        if self._buf:
            last = self._buf[-1]
            self._gains[-1] = (rts_gain(last, step) if last is not None and step is not None
                               and step.linked else None)
        self._buf.append(step)
        self._gains.append(None)
        return [self._oldest()] if len(self._buf) > self.lag else []

    def flush(self) -> list[State | None]:
        """The states of the frames still waiting, in order (smoothed with what is left)."""
        out = []
        while self._buf:
            out.append(self._oldest())
        return out


def zero_phase_one_euro(x: np.ndarray, times: np.ndarray, starts: np.ndarray,
                        policy: OneEuroPolicy | None = None) -> np.ndarray:
    """The One Euro filter run forward, then backward over its output, each pass started
    afresh at every frame where ``starts`` is True (a gap, a restart): x (F, K), times (F,)
    s, increasing."""
    x = np.asarray(x, np.float64)
    out = x.copy()
    bounds = [*np.flatnonzero(starts), len(x)]
    if not len(x):
        return out
    if not starts[0]:
        bounds = [0, *bounds]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        fwd = OneEuroFilter(policy)
        seg = np.array([fwd(x[i], float(times[i])) for i in range(a, b)])
        back = OneEuroFilter(policy)
        # backward in time: the time stamps mirrored so that they still increase
        t_end = float(times[b - 1])
        out[a:b] = np.array([back(seg[j - a], 2.0 * t_end - float(times[j]))
                             for j in range(b - 1, a - 1, -1)])[::-1]
    return out


def offline_articulation(alpha: np.ndarray, times: np.ndarray, ok: np.ndarray,
                         phase: np.ndarray, starts: np.ndarray, period: int | None,
                         cadence_rate: float | None = 0.1,
                         policy: OneEuroPolicy | None = None) -> np.ndarray:
    """The articulation streamed offline from the smoothed fits ``alpha`` (F, K): the reading
    cadence's component taken off (``period``: frames between readings, ``phase``: each
    frame's frames since its reading; None or ``cadence_rate`` None: no canceller), then the
    zero-phase One Euro filter with ``policy`` (None: no such filter). Frames not ``ok`` are
    left as they are and, like ``starts`` (a restart, a gated reading), start the filters
    afresh."""
    alpha = np.asarray(alpha, np.float64)
    ok = np.asarray(ok, bool)
    out = alpha.copy()
    canceller = (CadenceCanceller(period, cadence_rate)
                 if period is not None and period >= 2 and cadence_rate is not None else None)
    fresh = np.asarray(starts, bool).copy()
    prev_ok = False
    for i in range(len(alpha)):
        if not ok[i]:
            prev_ok = False
            continue
        if canceller is not None:
            if not prev_ok or fresh[i]:
                canceller.reset()
            out[i] = canceller(alpha[i], int(phase[i]))
        fresh[i] |= not prev_ok
        prev_ok = True
    idx = np.flatnonzero(ok)
    if len(idx) and policy is not None:
        out[idx] = zero_phase_one_euro(out[idx], np.asarray(times, np.float64)[idx],
                                       fresh[idx], policy)
    return out

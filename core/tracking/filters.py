"""The One Euro filter (Casiez, Roussel & Vogel, CHI 2012): an adaptive low-pass for noisy
real-time signals. Its cutoff rises with the signal's speed, so a still mouth is smoothed
hard (jitter gone) while a fast articulation passes with little lag.

    cutoff = min_cutoff + beta * |dx/dt|        (Hz; dx/dt itself low-passed at d_cutoff)
    x_hat  = x_hat + a (x - x_hat),  a = 1 / (1 + 1 / (2 pi cutoff dt))

Time stamps are passed in (core reads no clock). Works on vectors (one filter per element).

:class:`CadenceCanceller` comes before it in fused live tracking: it takes off the periodic
component that reading landmarks on every n-th frame leaves in the raw fits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OneEuroPolicy:
    """min_cutoff : Hz at rest; beta : how fast the cutoff rises with speed (per unit/s);
    d_cutoff : Hz of the speed estimate."""

    min_cutoff: float = 3.0
    beta: float = 1.0
    d_cutoff: float = 1.0


def _alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray | float:
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """Filters a vector signal sample by sample; :meth:`reset` forgets it (after a gap)."""

    def __init__(self, policy: OneEuroPolicy | None = None) -> None:
        self.policy = policy or OneEuroPolicy()
        self.reset()

    def reset(self) -> None:
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t = 0.0

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        """The filtered value of ``x`` (any shape) sampled at time ``t`` (s)."""
        x = np.asarray(x, np.float64)
        pol = self.policy
        if self._x is None or self._dx is None or not t > self._t:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), float(t)
            return x.copy()
        dt = float(t) - self._t
        dx = (x - self._x) / dt
        self._dx = self._dx + _alpha(pol.d_cutoff, dt) * (dx - self._dx)
        cutoff = pol.min_cutoff + pol.beta * np.abs(self._dx)
        self._x = self._x + _alpha(cutoff, dt) * (x - self._x)
        self._t = float(t)
        return self._x.copy()


class CadenceCanceller:
    """Removes the periodic component a reading cadence imprints on a raw estimate.

    A fused tracker that reads landmarks on every ``period``-th frame and fits the frames
    between on the appearance alone moves its estimate each time a reading comes: the two
    kinds of evidence disagree by a bias that changes slowly (seconds), so the raw estimate
    carries a sawtooth locked to the readings (cap13's still mouth: the aperture 1.2 % of
    the mouth's width low on the read frames, high two frames later). Its period is known
    and its phase too (frames since the last reading), so it is estimated, per phase, as a
    running mean (``rate`` per update) of each frame's deviation from the mean of the last
    ``period`` frames, and subtracted, less the mean over the phases (a steady motion
    deviates alike at every phase and is left alone). Causal: no lag is added. An estimate
    without a cadence averages to zero. Each update is clipped at ``clip`` times the phase's
    running RMS deviation: a jump (a fast turn, the fit recovering from a lost state) is not
    the cadence, and would otherwise be subtracted from the next second of frames.
    """

    def __init__(self, period: int, rate: float = 0.1, clip: float = 3.0) -> None:
        if period < 2 or not 0.0 < rate <= 1.0 or not clip > 0.0:
            raise ValueError("a cadence needs a period >= 2, a rate in (0, 1] and a clip > 0")
        self.period, self.rate, self.clip = int(period), float(rate), float(clip)
        self.forget()

    def reset(self) -> None:
        """Forget the recent frames (after a gap or a jump; the per-phase offsets are kept:
        they change slowly). The next ``2 period - 1`` frames are not learned from (a fit
        settling after a jump is not the cadence)."""
        self._recent: list[np.ndarray] = []
        self._settling = self.period - 1

    def forget(self) -> None:
        """Forget everything (a new face, a restart)."""
        self.reset()
        self._offset: np.ndarray | None = None
        self._spread: np.ndarray | None = None  # per phase, the running mean square update

    def __call__(self, x: np.ndarray, phase: int) -> np.ndarray:
        """``x`` (any shape) with the cadence's component at ``phase`` (frames since the last
        reading, clipped to period - 1) removed."""
        x = np.asarray(x, np.float64)
        if self._offset is None or self._spread is None or self._offset.shape[1:] != x.shape:
            self._offset = np.zeros((self.period, *x.shape))
            self._spread = np.full((self.period, *x.shape), np.nan)
        p = min(max(int(phase), 0), self.period - 1)
        self._recent = [*self._recent, x][-self.period:]
        if len(self._recent) == self.period and self._settling > 0:
            self._settling -= 1
        elif len(self._recent) == self.period:
            e = x - np.mean(self._recent, axis=0) - self._offset[p]
            sp = self._spread[p]
            if np.all(np.isfinite(sp)):
                lim = self.clip * np.sqrt(sp)
                e = np.clip(e, -lim, lim)
                self._spread[p] = sp + self.rate * (e * e - sp)
            else:
                self._spread[p] = e * e
            self._offset[p] += self.rate * e
        return x - self._correction(p)

    def _correction(self, p: int) -> np.ndarray:
        """Phase ``p``'s offset less the mean over the phases, each phase's offset shrunk by
        how well it is known (Wiener: d^2 / (d^2 + v), v the variance of a running mean of
        that phase's deviations): a cadence that is not there is not subtracted."""
        assert self._offset is not None and self._spread is not None
        v = self.rate / (2.0 - self.rate) * np.nan_to_num(self._spread, nan=np.inf)
        d = self._offset
        known = np.where(np.isfinite(v), d * d / np.maximum(d * d + v, 1e-300), 0.0)
        shrunk = d * known
        return shrunk[p] - shrunk.mean(axis=0)

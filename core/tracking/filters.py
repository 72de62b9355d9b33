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
    without a cadence averages to zero.
    """

    def __init__(self, period: int, rate: float = 0.1) -> None:
        if period < 2 or not 0.0 < rate <= 1.0:
            raise ValueError("a cadence needs a period >= 2 and a rate in (0, 1]")
        self.period, self.rate = int(period), float(rate)
        self.forget()

    def reset(self) -> None:
        """Forget the recent frames (after a gap; the per-phase offsets are kept: they change
        slowly)."""
        self._recent: list[np.ndarray] = []

    def forget(self) -> None:
        """Forget everything (a new face, a restart)."""
        self.reset()
        self._offset: np.ndarray | None = None

    def __call__(self, x: np.ndarray, phase: int) -> np.ndarray:
        """``x`` (any shape) with the cadence's component at ``phase`` (frames since the last
        reading, clipped to period - 1) removed."""
        x = np.asarray(x, np.float64)
        if self._offset is None or self._offset.shape[1:] != x.shape:
            self._offset = np.zeros((self.period, *x.shape))
        p = min(max(int(phase), 0), self.period - 1)
        self._recent = [*self._recent, x][-self.period:]
        if len(self._recent) == self.period:
            dev = x - np.mean(self._recent, axis=0)
            self._offset[p] += self.rate * (dev - self._offset[p])
        return x - (self._offset[p] - self._offset.mean(axis=0))

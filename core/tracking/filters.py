"""The One Euro filter (Casiez, Roussel & Vogel, CHI 2012): an adaptive low-pass for noisy
real-time signals. Its cutoff rises with the signal's speed, so a still mouth is smoothed
hard (jitter gone) while a fast articulation passes with little lag.

    cutoff = min_cutoff + beta * |dx/dt|        (Hz; dx/dt itself low-passed at d_cutoff)
    x_hat  = x_hat + a (x - x_hat),  a = 1 / (1 + 1 / (2 pi cutoff dt))

Time stamps are passed in (core reads no clock). Works on vectors (one filter per element).
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

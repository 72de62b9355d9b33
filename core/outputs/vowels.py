"""VRM vowel presets ``A I U E O`` from the tracked articulation.

Ordinary VRM avatars (VRM 0.x presets ``A I U E O``; VRM 1.0 ``aa ih ou ee oh``) have no ARKit
shapes: their mouth is driven by five vowel clips. Our articulation maps onto them naturally:
a vowel is a position of the jaw and the lips.

**Features** (per speaker, from the model's training ranges, as in :mod:`.arkit`), each a
linear measure of feature-point displacements in the head frame (x = the speaker's left,
y up, z forward):

============ =========================================== ======================================
feature      measure (mm)                                scale
============ =========================================== ======================================
jaw          drop of the jaw point 2.1                   0 most closed .. 1 most open
aperture     inner lips apart (2.2 up, 2.3 down)         0 most closed .. 1 most open
spread       lip corners apart (8.3 - 8.4 in x)          -1 most rounded .. 0 mean .. 1 widest
protrusion   outer lip middles forward (8.1, 8.2 in z)   -1 most retracted .. 0 mean .. 1 most
============ =========================================== ======================================

**Mapping**: each vowel (and the closed, neutral mouth) is a prototype point in this feature
space (:data:`PROTOTYPES`); a frame's weight for a vowel is its Gaussian membership
``exp(-|f - p|^2 / (2 sigma^2))`` normalised over the five vowels and the neutral mouth
(``sigma`` 0.15). The five weights are in 0..1, sum to at most 1, the neutral mouth's share
being the rest: a closed mouth sends no vowel, /a/ sends mostly ``A``.

**Where the prototypes come from**: the mean features of the French vowels /a e i o u/ of
the built-in synthetic speakers of seeds 0-9 (their corpus postures), rounded; they agree
with the phonetic description (A open and spread-neutral, I close and spread, U close,
rounded and protruded, E between A and I, O between A and U). On held-out speakers (seeds
10-29) the vowel with the largest weight is the posture's own vowel for 83 of 100 vowels:
/a/ 20 of 20, /u/ 19, the misses are /e/ and /i/ taken for each other and /o/ for /u/ (close
neighbours whose jaw and lips overlap between speakers). ``tests/test_vmc_vowels.py`` checks
it.
"""

from __future__ import annotations

import numpy as np

from articast.core.errors import InputError
from articast.core.model.face import FaceModel
from articast.core.outputs.arkit import Term, full_scale, measure_gradient

VOWELS: tuple[str, ...] = ("A", "I", "U", "E", "O")
"""The VRM 0.x vowel presets, in VRM's order."""

FEATURES: dict[str, tuple[list[Term], bool]] = {
    "jaw": ([("2.1", "y", -1.0)], False),
    "aperture": ([("2.2", "y", 1.0), ("2.3", "y", -1.0)], False),
    "spread": ([("8.3", "x", 1.0), ("8.4", "x", -1.0)], True),
    "protrusion": ([("8.1", "z", 0.5), ("8.2", "z", 0.5)], True),
}
"""name -> (measure terms, signed). Unsigned: 0..1 over the range; signed: -1..0..1."""

PROTOTYPES: dict[str, tuple[float, float, float, float]] = {
    "A": (0.95, 0.80, 0.35, -0.95),
    "I": (0.25, 0.35, 0.80, -0.50),
    "U": (0.35, 0.55, -0.60, 0.65),
    "E": (0.45, 0.50, 0.70, -0.60),
    "O": (0.50, 0.70, -0.40, 0.30),
    "neutral": (0.00, 0.20, 0.50, -0.15),
}
"""Feature values (jaw, aperture, spread, protrusion) of each vowel and of the closed mouth."""


class VowelMapper:
    """Per-speaker map from the tracked state to the VRM vowel weights.

    model : the speaker model; feature points 2.1, 2.2, 2.3, 8.1-8.4 are needed.
    sigma : width of a vowel's membership in feature units.
    """

    names = VOWELS

    def __init__(self, model: FaceModel, *, sigma: float = 0.15) -> None:
        if not (np.isfinite(sigma) and sigma > 0):
            raise InputError(f"sigma must be positive, got {sigma}")
        self.model = model
        self.sigma = float(sigma)
        self._g = np.stack([measure_gradient(model, t) for t, _ in FEATURES.values()])  # (4, K)
        cal = [full_scale(model, g, two_sided=True) for g in self._g]
        self._lo = np.array([c[0] for c in cal])
        self._hi = np.array([c[1] for c in cal])
        self._signed = np.array([signed for _, signed in FEATURES.values()])
        self._proto = np.array([PROTOTYPES[v] for v in (*VOWELS, "neutral")])  # (6, 4)

    def features(self, alpha: np.ndarray) -> np.ndarray:
        """(F, 4) jaw, aperture, spread, protrusion of alpha (F, K); (K,) gives (4,)."""
        a = np.asarray(alpha, dtype=np.float64)
        single = a.ndim == 1
        a = np.atleast_2d(a)
        if a.ndim != 2 or a.shape[1] != self.model.n_params or not np.all(np.isfinite(a)):
            raise InputError(f"alpha must be finite with shape (F, {self.model.n_params}), "
                             f"got {np.shape(alpha)}")
        m = a @ self._g.T  # (F, 4) mm
        lo, hi = self._lo, np.where(np.isfinite(self._hi), self._hi, 1.0)
        unsigned = (m - lo) / (hi - lo)
        signed = np.where(m > 0, m / hi, m / np.where(lo < 0, -lo, 1.0))
        f = np.where(self._signed, signed, unsigned)
        return f[0] if single else f

    def weights(self, alpha: np.ndarray) -> np.ndarray:
        """(F, 5) weights of A I U E O in 0..1 (sum <= 1); (K,) gives (5,)."""
        f = np.atleast_2d(self.features(alpha))
        d2 = ((f[:, None, :] - self._proto[None]) ** 2).sum(-1)  # (F, 6)
        k = np.exp(-(d2 - d2.min(1, keepdims=True)) / (2 * self.sigma**2))
        w = (k / k.sum(1, keepdims=True))[:, : len(VOWELS)]
        return w[0] if np.asarray(alpha).ndim == 1 else w

    def weights_dict(self, alpha: np.ndarray) -> dict[str, float]:
        """``{"A": w, "I": w, "U": w, "E": w, "O": w}`` of one frame, alpha (K,)."""
        w = self.weights(np.asarray(alpha, dtype=np.float64).reshape(-1))
        return {v: float(x) for v, x in zip(VOWELS, w, strict=True)}

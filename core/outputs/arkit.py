"""ARKit face blendshapes (mouth and jaw) from the tracked articulation.

Avatar apps (VSeeFace, VNyan, Warudo, Unity/Unreal rigs with "perfect sync") are driven by
Apple ARKit's 52 blendshape coefficients in 0..1. We populate the mouth and jaw ones (the
cheeks, nose and tongue stay 0: our model does not track them; the eyes and brows come from
the live tracker's upper face, :mod:`articast.core.outputs.upper`).

Each populated shape is a **measure** in mm of feature-point displacements from the neutral
face, in the head frame (x = the speaker's own left, y up, z forward), linear in alpha
because the model is: ``m(alpha) = g . alpha`` (:meth:`ArkitMapper.weights`); the same
measures apply to any geometry in the model's layout
(:meth:`ArkitMapper.weights_from_geometry`). ARKit's "Left" is the user's own left, i.e. our
+x side (8.3, 8.5, 8.7). The measures:

==================== ===========================================================================
jawOpen              drop of the jaw point 2.1
jawForward/Left/Right  2.1 forward, to the left (+x), to the right
mouthClose           jaw drop minus the inner-lip aperture increase (lips kept together)
mouthLeft/Right      sideways shift of the lip corners' midpoint
mouthSmile/Frown L/R corner (8.3 / 8.4) up / down relative to half the jaw's drop (the
                     corners hang half-way between skull and jaw), so opening is no frown
mouthStretch L/R     corner outwards
mouthLowerDown L/R   outer lower lip (8.7 / 8.8) down relative to the jaw (jawOpen carries it)
mouthUpperUp L/R     outer upper lip (8.5 / 8.6) up
mouthRollUpper/Lower visible lip height (8.1 - 2.2 / 2.3 - 8.2) shrinking: the lip rolls in
mouthShrugLower      outer lower lip middle 8.2 up relative to the jaw
mouthShrugUpper      outer upper lip middle 8.1 up
mouthDimple L/R      corner (8.3 / 8.4) pulled back (-z)
mouthPress L/R       outer lips (8.5 / 8.6 down, 8.7 / 8.8 up relative to the jaw) pressed
                     together on that side
mouthFunnel/Pucker   rounding (corners narrowing + lips protruding), split by the lip opening:
                     funnel = rounding x openness, pucker = rounding x (1 - openness)
==================== ===========================================================================

**Calibration per speaker** from the model's training ranges (``model.stats.min/max``):
a measure's positive full scale is the root-sum-square over parameters of the largest
positive value that parameter alone gives the measure within [min_k, max_k]; the value is
``clip(m / full_scale, 0, 1)``: 0 at the neutral (mean) face, 1 at the strongest such
articulation seen in training. ``jawOpen`` and the openness are two-sided: 0 at the most
closed, 1 at the most open posture of the same construction (the mean face is not a closed
mouth). The full scale is at least ``min_full_scale_mm`` (default 2 mm), so a measure that
the model only moves as a sub-millimetre side effect is not blown up to a full activation.
(``stats.std`` is not needed: min/max already bound each parameter.)
"""

from __future__ import annotations

import numpy as np

from articast.core.errors import InputError
from articast.core.model.face import FaceModel

ARKIT_BLENDSHAPES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight",
    "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)  # fmt: skip
"""Apple ARKit's 52 ``ARFaceAnchor.BlendShapeLocation`` names, in Apple's documented order."""

_AXIS = {"x": 0, "y": 1, "z": 2}
Term = tuple[str, str, float]  # (feature point, axis, coefficient)
_HALF_JAW: list[Term] = [("2.1", "y", -0.5)]

MEASURES: dict[str, list[Term]] = {
    "jawOpen": [("2.1", "y", -1.0)],
    "jawForward": [("2.1", "z", 1.0)],
    "jawLeft": [("2.1", "x", 1.0)],
    "jawRight": [("2.1", "x", -1.0)],
    "mouthClose": [("2.1", "y", -1.0), ("2.2", "y", -1.0), ("2.3", "y", 1.0)],
    "mouthLeft": [("8.3", "x", 0.5), ("8.4", "x", 0.5)],
    "mouthRight": [("8.3", "x", -0.5), ("8.4", "x", -0.5)],
    "mouthSmileLeft": [("8.3", "y", 1.0), *_HALF_JAW],
    "mouthSmileRight": [("8.4", "y", 1.0), *_HALF_JAW],
    "mouthFrownLeft": [("8.3", "y", -1.0), ("2.1", "y", 0.5)],
    "mouthFrownRight": [("8.4", "y", -1.0), ("2.1", "y", 0.5)],
    "mouthStretchLeft": [("8.3", "x", 1.0)],
    "mouthStretchRight": [("8.4", "x", -1.0)],
    "mouthLowerDownLeft": [("8.7", "y", -1.0), ("2.1", "y", 1.0)],
    "mouthLowerDownRight": [("8.8", "y", -1.0), ("2.1", "y", 1.0)],
    "mouthUpperUpLeft": [("8.5", "y", 1.0)],
    "mouthUpperUpRight": [("8.6", "y", 1.0)],
    "mouthRollUpper": [("8.1", "y", -1.0), ("2.2", "y", 1.0)],
    "mouthRollLower": [("2.3", "y", -1.0), ("8.2", "y", 1.0)],
    "mouthShrugLower": [("8.2", "y", 1.0), ("2.1", "y", -1.0)],
    "mouthShrugUpper": [("8.1", "y", 1.0)],
    "mouthDimpleLeft": [("8.3", "z", -1.0)],
    "mouthDimpleRight": [("8.4", "z", -1.0)],
    "mouthPressLeft": [("8.5", "y", -1.0), ("8.7", "y", 1.0), ("2.1", "y", -1.0)],
    "mouthPressRight": [("8.6", "y", -1.0), ("8.8", "y", 1.0), ("2.1", "y", -1.0)],
}
"""Linear measures (mm) of the directly measured shapes: sums of coefficient x displacement."""

ROUNDING: list[Term] = [
    ("8.3", "x", -1.0), ("8.4", "x", 1.0), ("8.1", "z", 0.5), ("8.2", "z", 0.5),
]  # fmt: skip
"""Corners narrowing plus lips protruding (mm)."""
OPENNESS: list[Term] = [("2.2", "y", 1.0), ("2.3", "y", -1.0)]
"""Inner lip aperture change (mm)."""
TWO_SIDED = ("jawOpen",)


def measure_gradient(model: FaceModel, terms: list[Term]) -> np.ndarray:
    """(K,) mm per unit of each parameter of a linear measure (sum of coefficient x
    displacement of labelled feature points, head frame)."""
    w = np.zeros(3 * model.n_points)
    for p, ax, c in terms:
        w[3 * model.point(p) + _AXIS[ax]] += c
    return model.basis.reshape(model.n_params, -1) @ w


def full_scale(model: FaceModel, g: np.ndarray, *, two_sided: bool,
               min_full_scale_mm: float = 2.0) -> tuple[float, float]:
    """(lo, hi) mm of a measure with gradient ``g`` (K,): root-sum-square over parameters of
    its largest negative / positive excursions within the training range [min_k, max_k]
    (``lo = 0`` unless ``two_sided``; ``hi = inf`` when nothing moves it up)."""
    s = model.stats
    ends = np.stack([g * s.min, g * s.max])  # (2, K) measure at each parameter's extremes
    hi = float(np.sqrt(np.sum(np.clip(ends.max(0), 0, None) ** 2)))
    lo = -float(np.sqrt(np.sum(np.clip(-ends.min(0), 0, None) ** 2))) if two_sided else 0.0
    if hi < 1e-9:  # nothing moves the measure this way: stays at 0
        return lo, np.inf
    return lo, max(hi, lo + min_full_scale_mm)


class ArkitMapper:
    """Per-speaker map from the tracked state to ARKit blendshape weights.

    model : the speaker model; feature points 2.1, 2.2, 2.3 and 8.1-8.8 are used. A shape
    whose points the model does not label is left at 0 (see :attr:`populated`).
    min_full_scale_mm : lower bound of every measure's full scale (module docstring).

    Attributes
    ----------
    names : the 52 ARKit names (:data:`ARKIT_BLENDSHAPES`).
    populated : names of the shapes this model drives.
    """

    names = ARKIT_BLENDSHAPES

    def __init__(self, model: FaceModel, *, min_full_scale_mm: float = 2.0) -> None:
        if not (np.isfinite(min_full_scale_mm) and min_full_scale_mm > 0):
            raise InputError(f"min_full_scale_mm must be positive, got {min_full_scale_mm}")
        self.model = model
        self.min_full_scale_mm = float(min_full_scale_mm)
        self._index = {n: i for i, n in enumerate(ARKIT_BLENDSHAPES)}
        # one row per measure over the flattened displacement (3N,): m = W . (x - mean)
        specs = [(name, terms) for name, terms in MEASURES.items() if self._labelled(terms)]
        self._has_rounding = self._labelled(ROUNDING) and self._labelled(OPENNESS)
        if self._has_rounding:
            specs += [("_rounding", ROUNDING), ("_openness", OPENNESS)]
        self._w = np.zeros((len(specs), 3 * model.n_points))
        for row, (_, terms) in enumerate(specs):
            for p, ax, c in terms:
                self._w[row, 3 * model.point(p) + _AXIS[ax]] += c
        self._g = self._w @ model.basis.reshape(model.n_params, -1).T  # (B, K) mm per alpha
        cal = [self._calibration(g, two_sided=name in TWO_SIDED + ("_openness",))
               for (name, _), g in zip(specs, self._g, strict=True)]
        self._lo = np.array([c[0] for c in cal])
        self._hi = np.array([c[1] for c in cal])
        self._cols = np.array([self._index[n] for n, _ in specs if not n.startswith("_")],
                              dtype=np.int64)
        driven = {n for n, _ in specs if not n.startswith("_")}
        if self._has_rounding:
            driven |= {"mouthFunnel", "mouthPucker"}
        self.populated: tuple[str, ...] = tuple(n for n in ARKIT_BLENDSHAPES if n in driven)

    def _labelled(self, terms: list[Term]) -> bool:
        return all(p in self.model.feature_points for p, _, _ in terms)

    def _calibration(self, g: np.ndarray, *, two_sided: bool) -> tuple[float, float]:
        return full_scale(self.model, g, two_sided=two_sided,
                          min_full_scale_mm=self.min_full_scale_mm)

    def _from_measures(self, m: np.ndarray) -> np.ndarray:
        """Measures (F, B) mm -> weights (F, 52)."""
        scaled = np.clip((m - self._lo) / (self._hi - self._lo), 0.0, 1.0)
        out = np.zeros((m.shape[0], len(ARKIT_BLENDSHAPES)))
        n = len(self._cols)
        out[:, self._cols] = scaled[:, :n]
        if self._has_rounding:
            rounding, openness = scaled[:, n], scaled[:, n + 1]
            out[:, self._index["mouthFunnel"]] = rounding * openness
            out[:, self._index["mouthPucker"]] = rounding * (1.0 - openness)
        return out

    def weights(self, alpha: np.ndarray) -> np.ndarray:
        """Blendshape weights (F, 52) in 0..1, columns in :attr:`names` order.

        alpha : (F, K) articulatory parameters (or (K,) for one frame -> (52,)).
        """
        a = np.asarray(alpha, dtype=np.float64)
        single = a.ndim == 1
        a = np.atleast_2d(a)
        if a.ndim != 2 or a.shape[1] != self.model.n_params or not np.all(np.isfinite(a)):
            raise InputError(f"alpha must be finite with shape (F, {self.model.n_params}), "
                             f"got {np.shape(alpha)}")
        out = self._from_measures(a @ self._g.T)
        return out[0] if single else out

    def weights_from_geometry(self, points: np.ndarray) -> np.ndarray:
        """Blendshape weights (F, 52) from the model's points (F, N, 3) mm, head frame.

        For geometry that does not come from ``model.shape(alpha)`` (e.g. another tracker's
        points in this model's layout); equals :meth:`weights` when it does.
        (N, 3) gives (52,).
        """
        x = np.asarray(points, dtype=np.float64)
        single = x.ndim == 2
        x = x[None] if single else x
        if x.ndim != 3 or x.shape[1:] != self.model.mean.shape or not np.all(np.isfinite(x)):
            raise InputError(f"points must be finite with shape (F, {self.model.n_points}, 3), "
                             f"got {np.shape(points)}")
        out = self._from_measures((x - self.model.mean).reshape(len(x), -1) @ self._w.T)
        return out[0] if single else out

    def weights_dict(self, alpha: np.ndarray, *, populated_only: bool = True) -> dict[str, float]:
        """``{name: weight}`` for one frame, alpha (K,)."""
        w = self.weights(np.asarray(alpha, dtype=np.float64).reshape(-1))
        names = self.populated if populated_only else ARKIT_BLENDSHAPES
        return {n: float(w[self._index[n]]) for n in names}

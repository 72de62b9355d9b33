"""The synthetic speaker's posture corpus: 68 visemes like the paper's (METHOD.md §1).

14 vowels (French oral and nasal), central frames of 52 VCV sequences (13 consonants x the
vowels a, i, u, y, with bilabial closure for p b m and lower lip against the upper teeth for
f v), and the silent postures ``rest`` and ``preph``. Each posture's controls are a phonetic
target plus seeded token-to-token variability (coarticulation, the speaker is not a robot).
The controls are then decorrelated across the corpus (guided PCA credits shared variance to
the earlier parameter, so correlated controls could not be recovered) and every bilabial is
closed by the least extra lip raising/lowering that closes the middle of the mouth.
"""

from __future__ import annotations

import numpy as np

from articast.core.errors import InputError
from articast.core.model.build import Corpus
from articast.core.model.face import PARAM_NAMES
from articast.core.synthetic.geometry import SpeakerGeometry, make_geometry

#: jaw1, lips1, lips2, lips3, lips4, jaw2, lar1 targets of the vowels. lips2/lips3 are the
#: lips relative to the jaw (open vowels keep the lower lip up, close ones lower it);
#: lips4, jaw2 and lar1 are weakly phonetic (prosody and mood move them), mostly variability.
VOWELS: dict[str, tuple[float, ...]] = {
    "a": (2.0, 0.3, 0.6, -0.2, 0.2, -0.3, -0.2),
    "E": (1.4, 0.6, 0.4, -0.3, -0.1, 0.2, 0.3),
    "e": (0.8, 0.9, -0.2, 0.1, 0.3, -0.2, 0.4),
    "i": (0.4, 1.2, -0.6, 0.2, -0.2, 0.3, 0.5),
    "y": (0.4, -1.5, -0.3, 0.2, 0.3, -0.3, 0.2),
    "u": (0.5, -1.8, -0.5, 0.0, -0.3, 0.2, -0.5),
    "o": (0.9, -1.3, -0.2, -0.3, 0.2, 0.0, -0.4),
    "O": (1.5, -0.8, 0.3, -0.4, 0.0, -0.2, 0.0),
    "2": (0.8, -1.2, 0.0, 0.3, -0.2, 0.3, 0.1),
    "9": (1.3, -0.7, 0.4, 0.0, 0.3, 0.0, -0.3),
    "@": (1.0, -0.5, 0.0, 0.0, -0.3, -0.2, 0.2),
    "a~": (1.7, -0.3, 0.5, 0.2, -0.2, 0.2, -0.3),
    "o~": (1.0, -1.4, 0.0, 0.1, 0.1, -0.1, 0.3),
    "e~": (1.3, 0.5, 0.2, -0.3, 0.4, 0.0, -0.1),
}
CONTEXT_VOWELS = ("a", "i", "u", "y")
NAN = float("nan")
#: consonant targets; NaN keeps the context vowel's value, else blend weight CONSONANT_WEIGHT
CONSONANTS: dict[str, tuple[float, ...]] = {
    "p": (0.5, NAN, 1.4, 0.2, NAN, NAN, NAN),
    "b": (0.5, NAN, 0.8, 0.8, NAN, NAN, NAN),
    "m": (0.6, NAN, 0.2, 1.4, NAN, NAN, NAN),
    "f": (0.4, 0.3, 1.8, -1.4, NAN, NAN, NAN),
    "v": (0.5, 0.2, 1.6, -1.3, NAN, NAN, NAN),
    "t": (0.4, NAN, -0.5, -0.3, NAN, 0.3, NAN),
    "d": (0.5, NAN, -0.4, -0.4, NAN, 0.2, NAN),
    "s": (0.3, 0.6, -0.8, -0.5, NAN, 0.5, NAN),
    "z": (0.3, 0.5, -0.7, -0.5, NAN, 0.4, NAN),
    "S": (0.4, -1.7, 0.2, -0.9, NAN, 0.3, NAN),
    "Z": (0.4, -1.6, 0.1, -0.8, NAN, 0.2, NAN),
    "k": (0.9, NAN, NAN, NAN, NAN, -0.4, NAN),
    "l": (0.9, NAN, NAN, NAN, NAN, -0.2, NAN),
}
CONSONANT_WEIGHT = 0.8
BILABIALS = ("p", "b", "m")
SILENT = {
    "rest": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "preph": (0.6, 0.0, -0.3, -0.2, 0.0, 0.0, -0.8),
}
#: seeded token variability (s.d., control units) added to every posture except rest
JITTER_SD = np.array([0.25, 0.3, 0.4, 0.45, 0.7, 0.7, 0.7])


def posture_targets() -> tuple[tuple[str, ...], np.ndarray]:
    """Names and phonetic targets (V, 7) of the 68 postures, before token variability."""
    names, rows = [], []
    for v, target in VOWELS.items():
        names.append(v)
        rows.append(target)
    for cons, ctarget in CONSONANTS.items():
        for v in CONTEXT_VOWELS:
            vt, ct = np.array(VOWELS[v]), np.array(ctarget)
            row = np.where(np.isnan(ct), vt, (1 - CONSONANT_WEIGHT) * vt + CONSONANT_WEIGHT * ct)
            names.append(f"{v}{cons}{v}")
            rows.append(row)
    for name, target in SILENT.items():
        names.append(name)
        rows.append(target)
    return tuple(names), np.array(rows, dtype=np.float64)


def corpus_controls(seed: int = 0, geometry: SpeakerGeometry | None = None,
                    ) -> tuple[tuple[str, ...], np.ndarray]:
    """Posture names and generating controls (68, 7) of the corpus of ``seed``.

    geometry : the speaker whose lips must close for the bilabials (default
    ``make_geometry(seed)``).
    """
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    names, targets = posture_targets()
    rng = np.random.default_rng([int(seed), 0xC0DE])
    jitter = rng.normal(size=targets.shape) * JITTER_SD
    jitter[names.index("rest")] = 0.0
    controls = targets + jitter
    bilabial = np.array([len(n) == 3 and n[1] in BILABIALS for n in names])
    geom = geometry if geometry is not None else make_geometry(seed)
    controls[bilabial] = close_lips(geom, controls[bilabial])
    # Phonetics correlates the controls (bilabials: lips up, jaw closed...). Guided PCA
    # attributes shared variance to the earlier parameter, so the corpus is decorrelated with
    # the transform nearest to identity (ZCA on correlations), about the rest posture; then
    # the bilabials, which it moved a little, are closed again (small corrections).
    centred = controls - controls.mean(0)
    sd = centred.std(0)
    corr = np.corrcoef(centred.T)
    evals, evecs = np.linalg.eigh(corr)
    zca = evecs @ np.diag(evals**-0.5) @ evecs.T
    controls = controls @ (np.diag(1 / sd) @ zca @ np.diag(sd))
    controls[:, 0] = np.clip(controls[:, 0], -0.3, None)  # the jaw does not close past the teeth
    controls[bilabial] = close_lips(geom, controls[bilabial])
    return names, controls


def close_lips(geom: SpeakerGeometry, controls: np.ndarray, max_gap_mm: float = 0.3,
               ) -> np.ndarray:
    """Raise the lower lip and/or lower the upper lip (and raise the jaw a little) by the least
    amount that closes the middle of the mouth (inner gap <= ``max_gap_mm``).

    controls : (B, 7) -> (B, 7). Each posture closes with its own mix of lips2 and lips3
    (the direction of its positive parts), as a speaker closes the lips for a bilabial
    whatever the jaw and the rounding do; the lips press together (contact model of
    ``articulate``).
    """
    up, lo = geom.pairs[:, 0], geom.pairs[:, 1]
    central = np.abs(np.sin(geom.angle[up])) > 0.5
    up, lo = up[central & (geom.ring[up] == 0)], lo[central & (geom.ring[up] == 0)]
    mix = np.clip(controls[:, 2:4], 0.1, None)
    step = np.zeros((len(controls), 7))
    step[:, 2:4] = mix / mix.max(1, keepdims=True)
    step[:, 0] = -0.25  # and the jaw helps a little

    def gap(d: np.ndarray) -> np.ndarray:
        pts = geom.articulate(controls + d[:, None] * step)
        return (pts[:, up, 1] - pts[:, lo, 1]).max(1)

    lo_d, hi_d = np.zeros(len(controls)), np.full(len(controls), 3.0)
    for _ in range(30):  # bisection on d, vectorised over postures
        mid = 0.5 * (lo_d + hi_d)
        closed = gap(mid) <= max_gap_mm
        hi_d, lo_d = np.where(closed, mid, hi_d), np.where(closed, lo_d, mid)
    done = gap(np.zeros(len(controls))) <= max_gap_mm
    return controls + np.where(done, 0.0, hi_d)[:, None] * step


def make_corpus(seed: int = 0, noise_mm: float = 0.3,
                geometry: SpeakerGeometry | None = None) -> Corpus:
    """The 68-posture corpus of the synthetic speaker.

    seed : speaker and token variability. noise_mm : RMS 3D measurement error per point (mm),
    drawn iid, isotropic (each coordinate has s.d. ``noise_mm / sqrt(3)``).
    geometry : the speaker (default ``make_geometry(seed)``).
    Returns a :class:`articast.core.model.build.Corpus` with ``controls`` (68, 7) and
    ``control_names``.
    """
    if not np.isfinite(noise_mm) or noise_mm < 0:
        raise InputError(f"noise_mm must be finite and >= 0, got {noise_mm!r}")
    geom = geometry if geometry is not None else make_geometry(seed)
    names, controls = corpus_controls(seed, geom)
    points = geom.articulate(controls)
    rng = np.random.default_rng([int(seed), 0x0B5E])
    points = points + rng.normal(size=points.shape) * (noise_mm / np.sqrt(3.0))
    return Corpus(
        postures=points,
        posture_names=names,
        point_names=geom.point_names,
        groups=dict(geom.groups),
        triangles=geom.triangles,
        feature_points=dict(geom.feature_points),
        fapu_overrides=dict(geom.fapu_overrides),
        controls=controls,
        control_names=PARAM_NAMES,
        name=f"synthetic-{geom.seed}",
    )

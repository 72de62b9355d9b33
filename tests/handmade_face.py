"""A small hand-made speaker model with a plausible mouth, for FAP, ARKit and transfer tests.

Head frame, mm: x = the speaker's own left, y up, z forward; origin at the upper incisors.
Modes (per unit alpha): jaw1 rotates the jaw about a hinge behind the mouth (chin down and
back), lips1 spreads the lips (corners out, lips back), lips2 raises the lower lip, lips3 lowers
the upper lip, lips4 raises the corners (smile), jaw2 advances the jaw, lar1 moves the throat.
The geometry is symmetric about x = 0, so symmetric modes give symmetric FAPs.
"""

from __future__ import annotations

import numpy as np

from articast.core.model.face import FaceModel, ParamStats

HINGE = np.array([0.0, 0.0, -80.0])
"""Jaw rotation centre (mm, head frame), behind the teeth near the ears' height."""

JAW_RAD_PER_ALPHA = 0.06
"""Jaw rotation per unit of jaw1 (rad)."""

# label or name -> (x, y, z) mm; pairs of left (+x) / right points are mirrored.
_POINTS = {
    "2.1": (0, -48, 8), "2.10": (0, -32, 14), "2.2": (0, 2, 10), "2.3": (0, -4, 10),
    "2.4": (22, -1, 2), "2.5": (-22, -1, 2), "2.6": (11, 1.5, 8), "2.7": (-11, 1.5, 8),
    "2.8": (11, -3.5, 8), "2.9": (-11, -3.5, 8), "8.1": (0, 10, 13), "8.2": (0, -13, 12),
    "8.3": (25, -1, 0), "8.4": (-25, -1, 0), "8.5": (12, 8, 11), "8.6": (-12, 8, 11),
    "8.7": (12, -11, 10), "8.8": (-12, -11, 10), "9.15": (0, 22, 16), "3.5": (32, 60, -10),
    "3.6": (-32, 60, -10), "7.1": (0, 30, -90),
    "jaw_l": (45, -30, -35), "jaw_r": (-45, -30, -35), "teeth_lo": (0, -6, 4),
    "cheek_l": (45, 15, -15), "cheek_r": (-45, 15, -15), "throat": (0, -70, -25),
}  # fmt: skip

JAW = ("2.1", "2.10", "jaw_l", "jaw_r", "teeth_lo")
LOWER_LIP = ("2.3", "2.8", "2.9", "8.2", "8.7", "8.8")
UPPER_LIP = ("2.2", "2.6", "2.7", "8.1", "8.5", "8.6")
CORNERS = ("2.4", "2.5", "8.3", "8.4")


def make_face_model() -> FaceModel:
    """The hand-made model (28 points, 7 modes, feature points all labelled)."""
    names = tuple(_POINTS)
    idx = {n: i for i, n in enumerate(names)}
    mean = np.array([_POINTS[n] for n in names], dtype=np.float64)
    basis = np.zeros((7, len(names), 3))
    # jaw1: rotation about +x through HINGE (chin goes down and back); corners follow half-way
    omega = np.array([JAW_RAD_PER_ALPHA, 0.0, 0.0])
    weight = {**{n: 1.0 for n in JAW + LOWER_LIP}, **{n: 0.5 for n in CORNERS}}
    for n, w in weight.items():
        basis[0, idx[n]] = w * np.cross(omega, mean[idx[n]] - HINGE)
    # lips1: spreading: corners outwards (left corner +x), all lip points back
    for n in CORNERS:
        basis[1, idx[n]] = (np.sign(mean[idx[n], 0]) * 3.0, 0.0, -1.0)
    for n in UPPER_LIP + LOWER_LIP:
        basis[1, idx[n]] = (np.sign(mean[idx[n], 0]) * 1.0, 0.0, -1.5)
    for n in LOWER_LIP:  # lips2: lower lip up
        basis[2, idx[n], 1] = 1.5
    for n in UPPER_LIP:  # lips3: upper lip down
        basis[3, idx[n], 1] = -1.2
    for n in CORNERS:  # lips4: corners up (smile) and slightly out
        basis[4, idx[n]] = (np.sign(mean[idx[n], 0]) * 0.8, 1.5, 0.0)
    for n in JAW + LOWER_LIP:  # jaw2: jaw advance
        basis[5, idx[n], 2] = 1.0
    basis[6, idx["throat"], 1] = 2.0  # lar1
    labels = {n: idx[n] for n in names if n[0].isdigit()}
    tris = [[idx[a], idx[b], idx[c]] for a, b, c in (
        ("8.1", "8.5", "2.6"), ("8.1", "2.6", "2.2"), ("8.1", "2.2", "2.7"), ("8.1", "2.7", "8.6"),
        ("8.2", "2.3", "2.8"), ("8.2", "2.8", "8.7"), ("8.2", "8.8", "2.9"), ("8.2", "2.9", "2.3"),
    )]  # fmt: skip
    k = 7
    return FaceModel(
        mean=mean,
        basis=basis,
        stats=ParamStats(np.zeros(k), np.ones(k), np.full(k, -2.5), np.full(k, 3.0)),
        point_names=names,
        groups={"jaw_line": [idx[n] for n in JAW], "lower_lip": [idx[n] for n in LOWER_LIP],
                "upper_lip": [idx[n] for n in UPPER_LIP]},
        triangles=tris,
        feature_points=labels,
        name="handmade",
    )



"""The MediaPipe 478-point face topology as a speaker model: which landmarks, which groups.

Model points are the landmarks of the lower face (below the cheekbones on MediaPipe's
canonical face, which also gives the triangles) plus the nose, whose bridge and tip speech
does not move (the *stable* points that remove the head pose). On a desk webcam the eye
corners and the forehead join the stable points; a head-mounted camera sees the face from
the nose down, so the landmarker's guesses for the eyes are not used there.

Groups follow METHOD.md §1: ``jaw_line`` (the jaw contour and the chin), ``lip_outer`` and
``lip_inner`` contours, ``upper_lip`` / ``lower_lip`` (both contours of each lip, corners
excluded), ``rest``; there are no lip beads, and the lower teeth are not landmarks. Feature
points map MPEG-4 labels to landmarks (left = the speaker's own, +x).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from articast.core.faces.enrol import LandmarkScheme
from articast.core.faces.finder import models_dir

N_LANDMARKS = 478
LIP_OUTER_UPPER = (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291)
LIP_OUTER_LOWER = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291)
LIP_INNER_UPPER = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
LIP_INNER_LOWER = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)
CORNERS = (61, 291, 78, 308)
JAW_LINE = (58, 172, 136, 150, 149, 176, 148, 152, 377, 400, 378, 379, 365, 397, 288,
            175, 199, 200)
NOSE = (1, 2, 4, 5, 6, 19, 94, 168, 195, 197)
UPPER_FACE = (33, 133, 362, 263, 10, 151, 9, 8, 234, 454, 127, 356)
FEATURE_LANDMARKS = {
    "2.1": 152, "2.2": 13, "2.3": 14, "2.4": 308, "2.5": 78, "2.6": 311, "2.7": 81,
    "2.8": 402, "2.9": 178, "8.1": 0, "8.2": 17, "8.3": 291, "8.4": 61, "8.5": 269,
    "8.6": 39, "8.7": 405, "8.8": 181, "9.15": 2,
}  # fmt: skip
LOWER_FACE_Y_CM = 1.0
"""Landmarks below this height on the canonical face (cm; the eyes are at 2.6) are modelled."""
ENS_OVER_ES = 0.75
"""Eye-nose separation over eye separation on MediaPipe's canonical face (4.7 / 6.3 cm): the
ENS0 unit of a model without eyes, from its assumed eye separation."""


@lru_cache(maxsize=2)
def canonical_face() -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe's canonical face: vertices (468, 3) in mm (x the face's left, y up, z out of
    the face) and triangles (T, 3)."""
    with np.load(models_dir() / "canonical_face.npz") as d:
        return np.asarray(d["vertices_cm"], np.float64) * 10.0, np.asarray(d["triangles"])


@lru_cache(maxsize=4)
def mediapipe_scheme(rig: str = "desk", ipd_mm: float = 63.0) -> LandmarkScheme:
    """The landmark scheme of the 478-point MediaPipe topology for ``rig`` ("desk"/"head")."""
    if rig not in ("desk", "head"):
        raise ValueError(f"rig must be 'desk' or 'head', got {rig!r}")
    verts, tris = canonical_face()
    lower = np.flatnonzero(verts[:, 1] < LOWER_FACE_Y_CM * 10.0)
    extra = NOSE + (UPPER_FACE if rig == "desk" else ())
    points = np.unique(np.concatenate([lower, extra])).astype(np.int64)
    where = {int(p): i for i, p in enumerate(points)}

    def idx(landmarks: tuple[int, ...]) -> np.ndarray:
        return np.array(sorted({where[p] for p in landmarks}), np.int64)

    upper = tuple(p for p in LIP_OUTER_UPPER + LIP_INNER_UPPER if p not in CORNERS)
    lower_lip = tuple(p for p in LIP_OUTER_LOWER + LIP_INNER_LOWER if p not in CORNERS)
    lips = set(LIP_OUTER_UPPER + LIP_OUTER_LOWER + LIP_INNER_UPPER + LIP_INNER_LOWER)
    groups = {
        "jaw_line": idx(JAW_LINE),
        "lip_outer": idx(LIP_OUTER_UPPER + LIP_OUTER_LOWER),
        "lip_inner": idx(LIP_INNER_UPPER + LIP_INNER_LOWER),
        "upper_lip": idx(upper),
        "lower_lip": idx(lower_lip),
        "rest": np.array([i for i, p in enumerate(points)
                          if int(p) not in lips and int(p) not in JAW_LINE], np.int64),
    }
    inside = np.isin(tris, points).all(1)
    triangles = np.vectorize(where.get)(tris[inside]).astype(np.int32)
    a, b, c = (verts[points[triangles[:, i]]] for i in range(3))
    if np.cross(b - a, c - a)[:, 2].sum() < 0:  # counter-clockwise seen from the front
        triangles = triangles[:, ::-1].copy()
    stable = idx(NOSE + (UPPER_FACE if rig == "desk" else ()))
    return LandmarkScheme(
        name=f"mediapipe-478-{rig}", n_landmarks=N_LANDMARKS, points=points, groups=groups,
        stable=stable, feature_points={k: where[v] for k, v in FEATURE_LANDMARKS.items()},
        mouth_corners=(where[291], where[61]), lip_inner_corners=(where[308], where[78]),
        triangles=triangles, eyes=(473, 468) if rig == "desk" else None,
        point_names=tuple(f"mp{int(p)}" for p in points),
        fapu_overrides={"ES0": ipd_mm, "ENS0": ENS_OVER_ES * ipd_mm},
    )

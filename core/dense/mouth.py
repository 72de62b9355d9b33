"""The mouth of a dense face: which dense points are lips, and the teeth and mouth cavity that a
face surface with a hole between the lips lacks — so an avatar shades lips, teeth and the
inner mouth distinctly, and an opening mouth shows dark inside and teeth, not the background.

Everything stays linear in alpha (``x = mean + sum_k alpha_k modes_k``), so a client animates
the added parts exactly as the rest of the dense face:

* **lips**: dense points bound to a facet of the sparse mesh whose three corners are in the
  model's ``upper_lip`` / ``lower_lip`` groups (label 1);
* **lower teeth**: a band under the ``lower_teeth`` points (their upper edge), 9 mm high,
  moving vertically with the jaw point 2.1 (the mandible carries them; only its vertical
  motion, so they never pass in front of the upper teeth) (label 2);
* **upper teeth**: the same arc 1.5 mm further forward, from the bite plane (y = 0, the
  head frame's origin) 10 mm up, fixed to the skull: no modes (label 2);
* **mouth cavity**: a funnel from the inner lip contour (``lip_inner``, moving with the lips)
  back 10 mm and in by 40 %, closed 22 mm behind the lips (label 3).

A model without these groups gets only what it has (no lips group: no lip labels; no
``lip_inner``: no cavity; no ``lower_teeth``: no teeth).
"""

from __future__ import annotations

import numpy as np

from articast.core.model.face import FaceModel

LABELS: tuple[str, ...] = ("skin", "lips", "teeth", "mouth")
"""Label values 0..3 of :func:`lip_labels` and :func:`mouth_parts`."""

LOWER_TEETH_MM = 9.0
UPPER_TEETH_MM = 10.0
UPPER_AHEAD_MM = 1.5
CAVITY_DEPTH_MM = (10.0, 22.0)
CAVITY_INSET = 0.4


def lip_labels(model: FaceModel, facet: np.ndarray) -> np.ndarray:
    """(M,) uint8: 1 where a dense point's facet (index into ``model.triangles``) is a lip
    facet, else 0. facet : (M,) int."""
    lips = np.zeros(model.n_points, bool)
    for g in ("upper_lip", "lower_lip"):
        lips[model.group(g)] = True
    lip_facet = lips[model.triangles].all(1)
    return lip_facet[np.asarray(facet)].astype(np.uint8)


def _band(top: np.ndarray, top_modes: np.ndarray, drop: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A strip under a polyline: top (n, 3), its modes (K, n, 3), drop (3,) from top to the
    bottom edge. Returns vertices (2n, 3), modes (K, 2n, 3), triangles (2(n-1), 3)."""
    n = len(top)
    verts = np.concatenate([top, top + drop])
    modes = np.concatenate([top_modes, top_modes], axis=1)
    tris = []
    for i in range(n - 1):
        a, b, c, d = i, i + 1, n + i, n + i + 1
        tris += [(a, c, b), (b, c, d)]
    return verts, modes, np.array(tris, np.int64).reshape(-1, 3)


def mouth_parts(model: FaceModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Teeth and mouth cavity of ``model``: vertices (P, 3) mm head frame at the mean, modes
    (K, P, 3) mm per unit alpha, triangles (Q, 3) indexing these P vertices, labels (P,)
    uint8 (:data:`LABELS`). Empty arrays when the model lacks the groups."""
    k = model.n_params
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
    teeth = model.group("lower_teeth")
    if len(teeth) >= 2:
        order = teeth[np.argsort(model.mean[teeth, 0])]
        top = model.mean[order]
        top_modes = np.zeros((k, len(order), 3))
        if "2.1" in model.feature_points:  # the mandible: vertically with the jaw point
            top_modes[:, :, 1] = model.basis[:, model.point("2.1"), 1][:, None]
        parts.append((*_band(top, top_modes, np.array([0.0, -LOWER_TEETH_MM, 0.0])), 2))
        upper = top.copy()
        upper[:, 1] = 0.0
        upper[:, 2] += UPPER_AHEAD_MM
        v, _, t = _band(upper + [0.0, UPPER_TEETH_MM, 0.0], np.zeros((k, len(upper), 3)),
                        np.array([0.0, -UPPER_TEETH_MM, 0.0]))
        parts.append((v, np.zeros((k, len(v), 3)), t, 2))
    inner = model.group("lip_inner")
    if len(inner) >= 3:
        c = model.mean[inner].mean(0)
        ang = np.arctan2(model.mean[inner, 1] - c[1], model.mean[inner, 0] - c[0])
        ring = inner[np.argsort(ang)]
        n = len(ring)
        r0, m0 = model.mean[ring], model.basis[:, ring]
        mc = model.basis[:, inner].mean(1, keepdims=True)  # (K, 1, 3) the centroid's modes
        r1 = (1 - CAVITY_INSET) * r0 + CAVITY_INSET * c - [0.0, 0.0, CAVITY_DEPTH_MM[0]]
        m1 = (1 - CAVITY_INSET) * m0 + CAVITY_INSET * mc
        back = c - [0.0, 0.0, CAVITY_DEPTH_MM[1]]
        verts = np.concatenate([r0, r1, back[None]])
        modes = np.concatenate([m0, m1, mc], axis=1)
        tris = []
        for i in range(n):
            j = (i + 1) % n
            tris += [(i, j, n + i), (j, n + j, n + i), (n + i, n + j, 2 * n)]
        parts.append((verts, modes, np.array(tris, np.int64), 3))
    if not parts:
        return (np.zeros((0, 3)), np.zeros((k, 0, 3)), np.zeros((0, 3), np.int64),
                np.zeros(0, np.uint8))
    all_verts: list[np.ndarray] = []
    all_modes: list[np.ndarray] = []
    all_tris: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    offset = 0
    for v, m, t, lab in parts:
        all_verts.append(v)
        all_modes.append(m)
        all_tris.append(t + offset)
        labels.append(np.full(len(v), lab, np.uint8))
        offset += len(v)
    return (np.concatenate(all_verts), np.concatenate(all_modes, axis=1), np.concatenate(all_tris),
            np.concatenate(labels))

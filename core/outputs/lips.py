"""Lip measures in millimetres on the fitted model geometry: what speech scientists read.

``aperture_mm``: inner upper-lip midpoint to inner lower-lip midpoint (MPEG-4 points 2.2 and
2.3); ``width_mm``: inner lip corner to inner lip corner (2.4 and 2.5). Both on the model
shape x(alpha) (head frame), so head motion does not change them, and they are available on
every frame the tracker fits — the direct check of a tracker on real video (the paper plots
these two curves).
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from articast.core.model.face import FaceModel
from articast.core.tracking.kernels import AVAILABLE, njit

LIP_POINTS = ("2.2", "2.3", "2.4", "2.5")
"""MPEG-4 feature points the measures need: inner upper/lower midpoints, inner corners."""


def has_lip_points(model: FaceModel) -> bool:
    """True when ``model`` labels the four inner-lip feature points."""
    return all(label in model.feature_points for label in LIP_POINTS)


_LIP_POINTS: weakref.WeakKeyDictionary[
    FaceModel, tuple[np.ndarray, np.ndarray, list, np.ndarray]] = weakref.WeakKeyDictionary()


def _lip_points(model: FaceModel) -> tuple[np.ndarray, np.ndarray]:
    """The four points' mean (4, 3) and basis (K, 4, 3) of a model, taken once per model (a
    live tracker measures the lips two or three times a frame)."""
    got = _lip_rows(model)
    return got[0], got[1]


def _lip_rows(model: FaceModel) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """:func:`_lip_points`, and both as Python floats: per point and axis, its mean and its K
    basis values ((4 x 3) rows of 1 + K floats), for :func:`lip_measures` of one frame; and
    those rows as a (12, 1 + K) float64 array (:func:`lip_lengths`)."""
    got = _LIP_POINTS.get(model)
    if got is None:
        idx = [model.point(label) for label in LIP_POINTS]
        mean, basis = model.mean[idx], model.basis[:, idx, :]
        rows = [[float(mean[p, c]), *basis[:, p, c].tolist()] for p in range(4) for c in range(3)]
        got = (mean, basis, rows, np.array(rows, np.float64).reshape(12, -1))
        _LIP_POINTS[model] = got
    return got


def lip_measures(model: FaceModel, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(aperture_mm, width_mm), each of shape alpha.shape[:-1].

    alpha : (..., K) articulatory parameters. Raises KeyError if a point is not labelled.
    """
    mean, basis = _lip_points(model)
    a = np.asarray(alpha, np.float64)
    # only the four points are needed: x_i(alpha) = mean_i + alpha @ basis[:, i]
    pts = mean + np.einsum("...k,kpc->...pc", a, basis)
    aperture = np.linalg.norm(pts[..., 0, :] - pts[..., 1, :], axis=-1)
    width = np.linalg.norm(pts[..., 2, :] - pts[..., 3, :], axis=-1)
    return aperture, width


def _lip_measures_one(model: FaceModel, alpha: list[float]) -> tuple[float, float]:
    """:func:`lip_measures` of one frame's alpha (K Python floats), in Python floats: the
    same operations in the same order (einsum's sum over K from 0.0, then the mean added;
    the norm's squares summed from 0.0), so the same numbers, without ~15 numpy calls (most
    of ``lips_dict``'s ~70 us a frame in the live loop)."""
    pts = []
    for row in _lip_rows(model)[2]:
        acc = 0.0
        for a, b in zip(alpha, row[1:], strict=True):
            acc += a * b
        pts.append(row[0] + acc)
    out = []
    for a, b in ((0, 3), (6, 9)):  # (2.2 - 2.3, 2.4 - 2.5: each axis's difference squared)
        d = [pts[a + c] - pts[b + c] for c in range(3)]
        out.append(math.sqrt(0.0 + d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
    return out[0], out[1]


@njit(cache=True, nogil=True)
def lip_lengths(rows, alpha):  # pragma: no cover - compiled
    """:func:`_lip_measures_one` compiled: ``rows`` the (12, 1 + K) float64 array of
    :func:`_lip_rows`, ``alpha`` (K,) float64 -> (finite, aperture_mm, width_mm); finite
    False (the lengths 0) where an alpha is not finite. The same float64 operations in the
    same order (each sum over K from 0.0, then the mean added; the squares summed from 0.0),
    so the same numbers: one call in place of ~100 cold Python float operations (~30 us a
    frame in the live loop)."""
    k = alpha.shape[0]
    for j in range(k):
        if not np.isfinite(alpha[j]):
            return False, 0.0, 0.0
    pts = np.empty(12)
    for r in range(12):
        acc = 0.0
        for j in range(k):
            acc += alpha[j] * rows[r, j + 1]
        pts[r] = rows[r, 0] + acc
    out = np.empty(2)
    for m, (a, b) in enumerate(((0, 3), (6, 9))):
        d0, d1, d2 = pts[a] - pts[b], pts[a + 1] - pts[b + 1], pts[a + 2] - pts[b + 2]
        out[m] = np.sqrt(0.0 + d0 * d0 + d1 * d1 + d2 * d2)
    return True, out[0], out[1]


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) :func:`lip_lengths` for the live
    tracker's types (:func:`articast.core.faces.kernels.warm_up` calls it)."""
    if AVAILABLE:
        lip_lengths(np.zeros((12, 2)), np.zeros(1))


def lips_dict(model: FaceModel, alpha: np.ndarray) -> dict[str, float] | None:
    """``{"aperture_mm", "width_mm"}`` of one frame (rounded to 1 µm), or None when the model
    does not label the inner-lip points or alpha is not finite."""
    got = _LIP_POINTS.get(model)  # (held only for a model that labels the points: one look-up
    # a frame instead of the labels' four)
    if got is None:
        if not has_lip_points(model):
            return None
        got = _lip_rows(model)
    a = np.asarray(alpha, np.float64)
    if a.ndim == 1 and AVAILABLE:
        rows = got[3]
        if rows.shape[1] == a.shape[0] + 1:
            ok, ap, wd = lip_lengths(rows, a if a.flags.c_contiguous and a.flags.writeable
                                      else a.copy())  # (the warmed type)
            return ({"aperture_mm": round(float(ap), 3), "width_mm": round(float(wd), 3)}
                    if ok else None)
    if a.ndim == 1:
        values = a.tolist()
        if not all(map(math.isfinite, values)):
            return None
        ap, wd = _lip_measures_one(model, values)
    else:
        if not np.all(np.isfinite(a)):
            return None
        ap, wd = (float(x) for x in lip_measures(model, a))
    return {"aperture_mm": round(ap, 3), "width_mm": round(wd, 3)}

"""Lip measures in millimetres on the fitted model geometry: what speech scientists read.

``aperture_mm``: inner upper-lip midpoint to inner lower-lip midpoint (MPEG-4 points 2.2 and
2.3); ``width_mm``: inner lip corner to inner lip corner (2.4 and 2.5). Both on the model
shape x(alpha) (head frame), so head motion does not change them, and they are available on
every frame the tracker fits — the direct check of a tracker on real video (the paper plots
these two curves).
"""

from __future__ import annotations

import weakref

import numpy as np

from articast.core.model.face import FaceModel

LIP_POINTS = ("2.2", "2.3", "2.4", "2.5")
"""MPEG-4 feature points the measures need: inner upper/lower midpoints, inner corners."""


def has_lip_points(model: FaceModel) -> bool:
    """True when ``model`` labels the four inner-lip feature points."""
    return all(label in model.feature_points for label in LIP_POINTS)


_LIP_POINTS: weakref.WeakKeyDictionary[FaceModel, tuple[np.ndarray, np.ndarray]] = (
    weakref.WeakKeyDictionary())


def _lip_points(model: FaceModel) -> tuple[np.ndarray, np.ndarray]:
    """The four points' mean (4, 3) and basis (K, 4, 3) of a model, taken once per model (a
    live tracker measures the lips two or three times a frame)."""
    got = _LIP_POINTS.get(model)
    if got is None:
        idx = [model.point(label) for label in LIP_POINTS]
        got = (model.mean[idx], model.basis[:, idx, :])
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


def lips_dict(model: FaceModel, alpha: np.ndarray) -> dict[str, float] | None:
    """``{"aperture_mm", "width_mm"}`` of one frame (rounded to 1 µm), or None when the model
    does not label the inner-lip points or alpha is not finite."""
    if not has_lip_points(model) or not np.all(np.isfinite(alpha)):
        return None
    ap, wd = lip_measures(model, alpha)
    return {"aperture_mm": round(float(ap), 3), "width_mm": round(float(wd), 3)}

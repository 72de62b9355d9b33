"""The delegate's surface: MediaPipe's full-face mesh (468 vertices, its UV layout) fitted to a
speaker model enrolled from face landmarks, and moved by that model.

A landmark-enrolled model's point ``i`` is landmark ``points[i]`` of the same topology (its
point names are ``mp<landmark>``), so the fitted mesh takes those vertices from the model
itself, exactly: the model's mean and basis. The others (eyes, brows, forehead, temples,
cheekbones: what the model does not cover) are placed by

1. a similarity (Umeyama) from the canonical face onto the model's mean on the shared
   vertices, then a thin-plate-spline of the shared vertices' residuals (the speaker's own
   proportions carried smoothly onto the rest of the face);
2. their motion: bound to the model's own mesh and moved by the dense-mesh paper's
   deformation transfer (:mod:`articast.core.dense.transfer`, METHOD.md §5); the per-parameter
   modes are its central differences (:func:`~articast.core.dense.transfer.dense_modes`).

The result is linear in alpha: ``vertices + sum_k alpha_k modes[k]``, exact at the model's
points (the glTF morph targets reproduce the model there).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RBFInterpolator

from articast.core.dense.transfer import bind, dense_modes
from articast.core.errors import InputError
from articast.core.faces.canonical import canonical_face
from articast.core.model.face import FaceModel

_MP_NAME = re.compile(r"^mp(\d+)$")
SUPPORT_MM = (20.0, 35.0)
"""A vertex within the first distance of the nearest model point has a known position
(support 1); beyond the second, only an extrapolated one (support 0), linear between: the
texture is not sampled there (:func:`~articast.core.delegate.texture.build_texture`)."""
MAX_MODE_MM = 3.0
"""Largest motion (mm per s.d.) a vertex outside the model may get from the transfer: the
upper face hardly moves in speech, and a vertex far beyond the model's mesh extrapolates its
nearest facet's map (DENSE_TRANSFER.md, limits)."""


@dataclass(frozen=True, eq=False)
class DelegateMesh:
    """vertices : (V, 3) mm, head frame, at alpha = 0; modes : (K, V, 3) mm per unit alpha;
    uv : (V, 2) texture coordinates in [0, 1] (v down, image convention, as glTF);
    triangles : (T, 3) int32, counter-clockwise seen from the front;
    model_index : (V,) model point of each vertex, -1 where the model has none."""

    vertices: np.ndarray
    modes: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    model_index: np.ndarray

    def support(self) -> np.ndarray:
        """(V,) in [0, 1]: how well each vertex's position is known (:data:`SUPPORT_MM`)."""
        from scipy.spatial import cKDTree

        own = self.model_index >= 0
        if not own.any():
            return np.ones(len(self.vertices))
        dist, _ = cKDTree(self.vertices[own]).query(self.vertices)
        near, far = SUPPORT_MM
        return np.clip((far - dist) / (far - near), 0.0, 1.0)

    def shape(self, alpha: np.ndarray) -> np.ndarray:
        """(V, 3) mm at ``alpha`` (K,)."""
        a = np.asarray(alpha, np.float64).reshape(-1)
        if a.shape != (self.modes.shape[0],):
            raise InputError(f"alpha must have {self.modes.shape[0]} values, got {a.shape}")
        return self.vertices + np.tensordot(a, self.modes, 1)


def landmark_ids(model: FaceModel) -> np.ndarray:
    """(N,) the landmark of each model point, from its ``mp<i>`` name; one clear error for a
    model that was not enrolled from face landmarks."""
    ids = [_MP_NAME.match(n) for n in model.point_names]
    if not all(ids):
        raise InputError("a delegate needs a speaker enrolled from face landmarks ('articast "
                         "enroll'): this model's points are not MediaPipe landmarks")
    out = np.array([int(m.group(1)) for m in ids if m], np.int64)
    if out.max() >= 468 or len(np.unique(out)) != len(out):
        raise InputError("this model's point names are not distinct landmarks of the 468-point "
                         "face mesh")
    return out


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimising |s R src + t - dst| (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    corr = np.diag([1.0, 1.0, d])
    rot = u @ corr @ vt
    s = float(np.trace(np.diag(sig) @ corr) / np.sum(a * a))
    return s, rot, md - s * rot @ ms


def fit_mesh(model: FaceModel) -> DelegateMesh:
    """The full-face mesh fitted to ``model`` and moved by it (module docstring)."""
    ids = landmark_ids(model)
    face = canonical_face()
    canon = face.vertices_mm
    s, rot, t = similarity(canon[ids], model.mean)
    placed = s * canon @ rot.T + t
    resid = model.mean - placed[ids]
    others = np.setdiff1d(np.arange(len(canon)), ids)
    verts = placed.copy()
    if len(others):
        rbf = RBFInterpolator(placed[ids], resid, kernel="thin_plate_spline", smoothing=1.0)
        verts[others] += rbf(placed[others])
    verts[ids] = model.mean
    modes = np.zeros((model.n_params, len(canon), 3))
    modes[:, ids] = model.basis
    if len(others) and len(model.triangles):
        binding = bind(model.mean, model.triangles, verts[others])
        _, m = dense_modes(binding, model)
        norm = np.linalg.norm(m, axis=2, keepdims=True)
        modes[:, others] = m * np.minimum(1.0, MAX_MODE_MM / np.maximum(norm, 1e-12))
    index = np.full(len(canon), -1, np.int64)
    index[ids] = np.arange(len(ids))
    return DelegateMesh(verts, modes, face.uv.copy(), face.triangles.copy(), index)

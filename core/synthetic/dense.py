"""A dense face mesh for the built-in speaker and its dense modes (METHOD.md §5).

The dense mesh is the model's mean surface refined by Loop subdivision (three steps: 64
triangles per model triangle, ~23k vertices) and given fine skin relief along its normals, so
that it is a genuinely different, denser surface; it is bound to the sparse model mesh by the
per-facet affine transfer, and the model's modes transferred to it give dense modes, so a
client animates the dense face linearly from the streamed alpha.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articast.core.dense.subdivide import loop_subdivide
from articast.core.model.face import FaceModel


@dataclass(frozen=True, eq=False)
class DenseFace:
    """mean (M, 3) mm, modes (K, M, 3) mm per unit alpha, triangles (T, 3), the largest
    gap (mm) between the linear dense modes and per-frame transfer over training postures,
    and labels (M,) uint8 per point (:data:`~articast.core.dense.mouth.LABELS`: skin, lips,
    teeth, mouth; the teeth and mouth cavity are added points, :mod:`articast.core.dense.mouth`).
    """

    mean: np.ndarray
    modes: np.ndarray
    triangles: np.ndarray
    linearity_error_mm: float
    labels: np.ndarray | None = None

    def to_dict(self) -> dict:
        from articast.core.dense.mouth import LABELS

        labels = self.labels if self.labels is not None else np.zeros(len(self.mean), np.uint8)
        return {"n_points": int(len(self.mean)),
                "mean": self.mean.astype(np.float32).ravel().tolist(),
                "basis": self.modes.astype(np.float32).ravel().tolist(),
                "triangles": self.triangles.ravel().tolist(),
                "labels": labels.tolist(), "label_names": list(LABELS),
                "linearity_error_mm": self.linearity_error_mm}


def relief(points: np.ndarray, normals: np.ndarray, seed: int = 0,
           depth_mm: float = 0.15) -> np.ndarray:
    """Fine skin relief: a few random plane waves of ~3-8 mm along the normals."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(12, 3))
    k *= (2 * np.pi / rng.uniform(3.0, 8.0, 12) / np.linalg.norm(k, axis=1))[:, None]
    phase = rng.uniform(0, 2 * np.pi, 12)
    h = np.sin(points @ k.T + phase).mean(1) * depth_mm * 2
    return points + h[:, None] * normals


def dense_face(model: FaceModel, steps: int = 2, seed: int = 0,
               outlier_mm: float = 1.5) -> DenseFace:
    """Build the dense mesh of ``model`` and its dense modes.

    A few dense points near the mesh border are bound to a facet they lie far outside of;
    there the affine map extrapolates (measured: up to 10 mm off the barycentric transfer at
    jaw1 = 2 s.d., while the median point differs by 0.006 mm). Points whose affine and
    barycentric transfers differ by more than ``outlier_mm`` at +-2 s.d. of any parameter
    follow the barycentric transfer instead.
    """
    from articast.core.appearance.models import vertex_normals
    from articast.core.dense.transfer import barycentric_apply, bind, dense_modes

    used = np.unique(model.triangles)
    remap = -np.ones(model.n_points, np.int64)
    remap[used] = np.arange(used.size)
    verts, tris = loop_subdivide(model.mean[used], remap[model.triangles], steps)
    verts = relief(verts, vertex_normals(verts, tris), seed)
    binding = bind(model.mean, model.triangles, verts, dense_triangles=tris)
    mean, modes = dense_modes(binding, model)
    b_mean = barycentric_apply(binding, model.mean)
    b_modes = np.stack([(barycentric_apply(binding, model.mean + b)
                         - barycentric_apply(binding, model.mean - b)) / 2 for b in model.basis])
    probes = np.concatenate([2 * np.eye(model.n_params), -2 * np.eye(model.n_params)])
    gap = np.zeros(len(verts))
    from articast.core.dense.transfer import apply

    for a in probes:
        full = apply(binding, model.shape(a))
        gap = np.maximum(gap, np.linalg.norm(full - barycentric_apply(binding, model.shape(a)),
                                             axis=1))
    out = gap > outlier_mm
    mean[out] += verts[out] - b_mean[out]  # keep the dense rest shape, move barycentrically
    modes[:, out] = b_modes[:, out]
    lin = mean + np.tensordot(probes, modes, 1)
    exact = np.stack([apply(binding, model.shape(a)) for a in probes])
    exact[:, out] = np.stack([barycentric_apply(binding, model.shape(a)) + verts - b_mean
                              for a in probes])[:, out]
    err = float(np.linalg.norm(lin - exact, axis=-1).max())
    from articast.core.dense.mouth import lip_labels, mouth_parts

    labels = lip_labels(model, binding.facet)
    verts_m, modes_m, tris_m, labels_m = mouth_parts(model)
    return DenseFace(np.concatenate([mean, verts_m]), np.concatenate([modes, modes_m], axis=1),
                     np.concatenate([tris, tris_m + len(mean)]), err,
                     np.concatenate([labels, labels_m]))

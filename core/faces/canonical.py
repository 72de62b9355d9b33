"""MediaPipe's metric canonical face and its landmark groups (``models/canonical_face.npz``).

The canonical face is the mean face MediaPipe fits its head pose to. Its frame is the head
frame of :mod:`articast.core.model.camera`: x towards the person's left, y up, z forward (out
of the face); its triangles are counter-clockwise seen from +z. Vertex ``i`` is landmark
``i`` of the 478-point landmarks (the first 468; 468..477 are the irises).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from articast.core.errors import ModelFileError
from articast.core.faces.finder import models_dir

LIP_CONTOURS = ("lips_outer_upper", "lips_outer_lower", "lips_inner_upper", "lips_inner_lower")


@dataclass(frozen=True, eq=False)
class CanonicalFace:
    """The canonical face.

    vertices_mm : (468, 3) float64, mm, canonical head frame (see the module docstring).
    uv : (468, 2) float64 texture coordinates in [0, 1].
    triangles : (898, 3) int32 vertex indices.
    procrustes_ids, procrustes_weights : (33,) landmarks and weights of MediaPipe's pose fit.
    edges : group name (``lips``, ``face_oval``, ``left_eye``, ``nose``...) -> (E, 2) int32
        landmark pairs.
    contours : lip contour name (:data:`LIP_CONTOURS`) -> (11,) int32 landmarks from the
        person's right corner to the left one (outer: 61 -> 291, inner: 78 -> 308).
    """

    vertices_mm: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    procrustes_ids: np.ndarray
    procrustes_weights: np.ndarray
    edges: Mapping[str, np.ndarray]
    contours: Mapping[str, np.ndarray]


def canonical_face() -> CanonicalFace:
    """Load the bundled canonical face (vertices converted from cm to mm)."""
    path = models_dir() / "canonical_face.npz"
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"cannot read {path}: {exc}") from None
    missing = {"vertices_cm", "triangles", *LIP_CONTOURS} - data.keys()
    if missing:
        raise ModelFileError(f"{path} lacks {sorted(missing)}")
    edges = {k.removeprefix("edges_"): v for k, v in data.items() if k.startswith("edges_")}
    return CanonicalFace(
        vertices_mm=data["vertices_cm"].astype(np.float64) * 10.0,
        uv=data["uv"].astype(np.float64),
        triangles=data["triangles"].astype(np.int32),
        procrustes_ids=data["procrustes_ids"].astype(np.int32),
        procrustes_weights=data["procrustes_weights"].astype(np.float64),
        edges=MappingProxyType(edges),
        contours=MappingProxyType({k: data[k].astype(np.int32) for k in LIP_CONTOURS}),
    )

"""Dense-mesh animation by deformation transfer (METHOD.md §5, dense-mesh-transfer.txt §3).

A dense static mesh (a scan, thousands of points) is moved by the tracked sparse mesh:

1. :func:`~articast.core.dense.mesh.register_icp` brings the dense mesh into the sparse mesh's
frame.
2. :func:`bind` attaches every dense point M to one sparse facet ABC: with vertex normals
   N_A, N_B, N_C, find (a, b, c = 1 - a - b) and an offset t with
   ``M = H + t (a N_A + b N_B + c N_C)``, ``H = a A + b B + c C`` (the paper's affine projection;
   a cubic in t, solved by Newton from the orthogonal distance, for the few nearest facets at
   once). The facet with a, b, c in [0, 1] and the smallest |t| is kept, else the nearest facet.
3. Per facet, the affine map f(x) = A' + L (x - A) (12 DOF) satisfies f(A) = A', f(B) = B',
   f(C) = C' exactly and the curvature constraints L(K_X N_X) = K'_X N'_X (K the angle
   deficit, X in {A, B, C}) in the least-squares sense, regularised towards the
   Sumner-Popovic map L n = n' (a 4th vertex at unit distance along the facet normal n).
   The 9 equalities fix L on the facet plane (L e1 = e1', L e2 = e2') and the translation, so
   the equality-constrained problem reduces exactly (null-space form of the KKT system) to the
   3 unknowns v = L n. With N_X = alpha_X e1 + beta_X e2 + gamma_X n:

       minimise  sum_X || c_X v - r_X ||^2 + lambda^2 || v - n' ||^2,
       c_X = K_X gamma_X,   r_X = K'_X N'_X - K_X (alpha_X e1' + beta_X e2'),
       v = (sum_X c_X r_X + lambda^2 n') / (sum_X c_X^2 + lambda^2)

   in closed form, batched over facets. Where the curvature vanishes, v = n'.
   lambda^2 = ``regularisation`` x mean(c_X^2) of the reference mesh; the default 3 was
   chosen on synthetic curved surfaces (tests/test_transfer.py): with lambda -> 0 (the
   curvature constraints alone) the transfer is worse than barycentric interpolation where the
   deformation changes the sign of the curvature (K'/K blows up or flips the normal offset);
   with lambda -> infinity (Sumner-Popovic alone) it is worse than barycentric on every
   surface tried; at 3 it beats barycentric on all of them (RMS ratios 0.59-0.87).
4. Each dense point moves as M' = f(M) with its facet's f: :func:`apply`.
5. :func:`dense_modes` transfers the model's modes, so a client animates the dense mesh
   linearly from the streamed alpha. f is not linear in alpha (normals and angle deficits
   are not), so the modes are central differences at alpha = 0 (+-``step`` s.d.);
   :func:`linearity_error` measures the gap to per-frame transfer for a given model.

Frames: every array is in the sparse mesh's frame (the head frame for a model), mm.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.dense.mesh import (
    MeshTopology,
    Registration,
    angle_deficits,
    facet_cross,
    point_triangle_distance,
    register_icp,
    vertex_normals,
)  # fmt: skip
from articast.core.errors import InputError
from articast.core.model.face import FaceModel

BINDING_KIND = "dense-binding"
BINDING_VERSION = 1
_INSIDE_EPS = 1e-9
_NEWTON_STEPS = 12

__all__ = ["Binding", "Registration", "apply", "barycentric_apply", "bind", "dense_modes",
           "facet_maps", "linearity_error", "register_and_bind", "register_icp"]


@dataclass(frozen=True, eq=False)
class Binding:
    """Dense points bound to the facets of a sparse reference mesh.

    Attributes
    ----------
    sparse_vertices : (N, 3) mm, the sparse reference mesh (e.g. ``model.mean``).
    triangles : (T, 3) int, its facets.
    dense_vertices : (M, 3) mm, the dense points in the sparse frame.
    facet : (M,) int, the facet each dense point is bound to.
    local : (M, 3), coordinates of ``M - A`` in the facet basis (B - A, C - A, n): f(M) is
        ``A' + local_0 e1' + local_1 e2' + local_2 v``.
    weights : (M, 3), the affine coordinates (a, b, c) of the binding (for
        :func:`barycentric_apply`). offset : (M,) mm, t along the interpolated normal.
    inside : (M,) bool, a facet with a, b, c in [0, 1] was found (else: the nearest facet).
    corner_normals : (T, 3, 3), each corner's vertex normal N_X in the facet basis.
    curvature : (N,) rad, angle deficits of the reference (0 on the boundary).
    lambda2 : regularisation weight lambda^2 of the Sumner-Popovic term.
    dense_triangles : (Q, 3) int, the dense mesh's facets, kept for rendering (may be empty).
    follow : (M,) in [0, 1] or None (all 1): how much of its facet's motion a point takes,
        ``M' = M + follow (f(M) - M)``; 0 holds it to the head (a scan's cranium, far from
        the sparse mesh), in between a smooth falloff across the border
        (:mod:`articast.core.dense.scan`).
    turn : (M,) in [0, 1] or None (all 1): share of the normal offset ``local_2`` that turns
        with the facet (``v``).

    With ``follow`` or ``turn`` given, whatever part of ``M - A`` the terms
    ``local_0 e1 + local_1 e2 + turn local_2 n`` do not account for is carried unrotated
    (it is linear in the sparse vertices, as barycentric transfer): the rest of a normal
    offset that does not turn, or, for a point bound by its nearest surface point
    (``local`` = that point's (b, c, 0)), the whole offset from it
    (:mod:`articast.core.dense.scan`).
    """

    sparse_vertices: np.ndarray
    triangles: np.ndarray
    dense_vertices: np.ndarray
    facet: np.ndarray
    local: np.ndarray
    weights: np.ndarray
    offset: np.ndarray
    inside: np.ndarray
    corner_normals: np.ndarray
    curvature: np.ndarray
    lambda2: float
    dense_triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    follow: np.ndarray | None = None
    turn: np.ndarray | None = None
    # derived once, for the per-frame maps
    topology: MeshTopology = field(init=False, repr=False)
    curvature_weights: np.ndarray = field(init=False, repr=False)  # c_X (T, 3)
    denominators: np.ndarray = field(init=False, repr=False)  # sum_X c_X^2 + lambda^2 (T,)
    gather: sp.csr_matrix = field(init=False, repr=False)  # (M, 4T), see :func:`apply`
    held: np.ndarray = field(init=False, repr=False)  # (M, 3) carried part, see :func:`apply`

    def __post_init__(self) -> None:
        object.__setattr__(self, "topology",
                           MeshTopology(self.triangles, len(self.sparse_vertices)))
        c = self.curvature[self.triangles] * self.corner_normals[..., 2]
        object.__setattr__(self, "curvature_weights", c)
        object.__setattr__(self, "denominators", (c * c).sum(1) + self.lambda2)
        # f(M) = [1, local] . [A', e1', e2', v][facet]: one sparse product per frame
        m, t = len(self.facet), len(self.triangles)
        coef = np.c_[np.ones(m), self.local]
        held = np.zeros((m, 3))
        if self.follow is not None or self.turn is not None:
            # M' = M + w (f(M) - M), f(M) = A' + l0 e1' + l1 e2' + s l2 v + (M - A - l0 e1
            # - l1 e2 - s l2 n): at the reference (v = n) M' = M; the bracket is carried
            w = _weights_in_unit("follow", np.ones(m) if self.follow is None else self.follow, m)
            s = _weights_in_unit("turn", np.ones(m) if self.turn is None else self.turn, m)
            object.__setattr__(self, "follow", w)
            object.__setattr__(self, "turn", s)
            coef[:, 3] *= s
            coef = coef * w[:, None]
            ref = np.concatenate(facet_basis_rest(self.sparse_vertices, self.triangles))
            held = self.dense_vertices - np.asarray(gather_rows(coef, self.facet, len(
                self.triangles)) @ ref)
        object.__setattr__(self, "held", held)
        object.__setattr__(self, "gather", gather_rows(coef, self.facet, t))

    @property
    def n_dense(self) -> int:
        return int(self.dense_vertices.shape[0])

    def save(self, path: str | os.PathLike[str],
             extra: dict[str, np.ndarray] | None = None) -> None:
        """Write as a versioned bundle (kind ``dense-binding``); ``extra`` arrays ride along
        (e.g. a scan's texture, :mod:`articast.core.dense.texture`)."""
        arrays = {**(extra or {}), **{name: getattr(self, name) for name in _ARRAYS}}
        for name in ("follow", "turn"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        save_bundle(path, BINDING_KIND, BINDING_VERSION, arrays, {"lambda2": self.lambda2})

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Binding:
        """Read a binding; :class:`~articast.core.errors.ModelFileError` for any defect."""
        arrays, meta = load_bundle(path, BINDING_KIND, (BINDING_VERSION,))
        with reading(path, "dense binding"):
            for name in _ARRAYS:
                require(name in arrays, path, f"missing array {name!r}")
            n, t, m = len(arrays["sparse_vertices"]), len(arrays["triangles"]), len(arrays["facet"])
            shapes = {"sparse_vertices": (n, 3), "triangles": (t, 3), "dense_vertices": (m, 3),
                      "local": (m, 3), "weights": (m, 3), "offset": (m,), "inside": (m,),
                      "corner_normals": (t, 3, 3), "curvature": (n,)}
            for name, shape in shapes.items():
                require(arrays[name].shape == shape, path,
                        f"array {name!r} has shape {arrays[name].shape}, expected {shape}")
            tri, fac = arrays["triangles"], arrays["facet"]
            require(t > 0 and tri.min() >= 0 and tri.max() < n, path, "triangles index no vertex")
            require(m == 0 or (fac.min() >= 0 and fac.max() < t), path, "facet indexes no triangle")
            dtri = arrays["dense_triangles"]
            require(dtri.ndim == 2 and dtri.shape[1] == 3, path,
                    f"dense_triangles have shape {dtri.shape}, expected (Q, 3)")
            require(dtri.size == 0 or (dtri.min() >= 0 and dtri.max() < m), path,
                    "dense_triangles index no dense point")
            lam = meta.get("lambda2")
            require(isinstance(lam, int | float) and lam > 0, path, "lambda2 must be positive")
            extra = {k: arrays.get(k) for k in ("follow", "turn")}  # whole-head scans only
            for name, w in extra.items():
                require(w is None or (w.shape == (m,) and bool(np.all((w >= 0) & (w <= 1)))),
                        path, f"array {name!r} must be ({m},) weights in [0, 1]")
            return cls(**{k: arrays[k] for k in _ARRAYS}, lambda2=float(lam), **extra)


_ARRAYS = ("sparse_vertices", "triangles", "dense_vertices", "facet", "local", "weights",
           "offset", "inside", "corner_normals", "curvature", "dense_triangles")


def gather_rows(coef: np.ndarray, facet: np.ndarray, t: int) -> sp.csr_matrix:
    """(M, 4T) sparse: row i puts ``coef[i]`` on facet ``facet[i]`` of ``[A; e1; e2; v]``."""
    m = len(facet)
    cols = np.arange(4)[None, :] * t + facet[:, None]
    return sp.csr_matrix((coef.ravel(), (np.repeat(np.arange(m), 4), cols.ravel())),
                         shape=(m, 4 * t))


def facet_basis_rest(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, ...]:
    """A, e1, e2 and the unit normal n (each (T, 3)) of a mesh: ``[A; e1; e2; v]`` at rest."""
    a = vertices[triangles[:, 0]]
    e1, e2 = vertices[triangles[:, 1]] - a, vertices[triangles[:, 2]] - a
    n = np.cross(e1, e2)
    return a, e1, e2, n / np.linalg.norm(n, axis=1, keepdims=True)


def _weights_in_unit(name: str, w: Any, m: int) -> np.ndarray:
    w = np.asarray(w, np.float64)
    if w.shape != (m,) or not np.all((w >= 0) & (w <= 1)):
        raise InputError(f"{name} must be ({m},) weights in [0, 1]")
    return w


def _check_points(name: str, arr: Any, n: int | None = None) -> np.ndarray:
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and arr.shape[0] != n):
        want = f"({n}, 3)" if n is not None else "(n, 3)"
        raise InputError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains NaN or infinite values")
    return arr


def _facet_basis(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, ...]:
    """A (T,3), e1 (T,3), e2 (T,3), unit n (T,3) and E^-1 (T,3,3), E = [e1 e2 n] by columns."""
    a = vertices[triangles[:, 0]]
    e1, e2 = vertices[triangles[:, 1]] - a, vertices[triangles[:, 2]] - a
    cross = np.cross(e1, e2)
    area2 = np.linalg.norm(cross, axis=1)
    if np.any(area2 <= 1e-12 * (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) + 1)):
        raise InputError("the sparse mesh has degenerate (zero-area) triangles")
    n = cross / area2[:, None]
    basis = np.stack([e1, e2, n], axis=-1)
    return a, e1, e2, n, np.linalg.inv(basis)


def _det(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.einsum("...d,...d->...", x, np.cross(y, z))


def _project_on_facets(
    m: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
    na: np.ndarray, nb: np.ndarray, nc: np.ndarray, t0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve M = H + t N(a, b) on each (point, facet) pair (all arrays (..., 3)).

    M - C - t N_C = a (A - C + t (N_A - N_C)) + b (B - C + t (N_B - N_C)): the three vectors
    are coplanar, a cubic in t, solved by Newton from ``t0``. Returns a, b, t (...,).
    """
    u0, u1, w0, w1, m0, m1 = a - c, na - nc, b - c, nb - nc, m - c, -nc
    k0 = _det(u0, w0, m0)
    k1 = _det(u1, w0, m0) + _det(u0, w1, m0) + _det(u0, w0, m1)
    k2 = _det(u1, w1, m0) + _det(u1, w0, m1) + _det(u0, w1, m1)
    k3 = _det(u1, w1, m1)
    t = t0.copy()
    for _ in range(_NEWTON_STEPS):
        g = ((k3 * t + k2) * t + k1) * t + k0
        dg = (3 * k3 * t + 2 * k2) * t + k1
        t = t - np.where(np.abs(dg) > 1e-30, g / np.where(dg == 0, 1.0, dg), 0.0)
    u, w, r = u0 + t[..., None] * u1, w0 + t[..., None] * w1, m0 + t[..., None] * m1
    uu, uw, ww = (np.einsum("...d,...d->...", x, y) for x, y in ((u, u), (u, w), (w, w)))
    ur, wr = np.einsum("...d,...d->...", u, r), np.einsum("...d,...d->...", w, r)
    det = uu * ww - uw * uw
    det = np.where(np.abs(det) > 1e-30, det, 1e-30)
    return (ww * ur - uw * wr) / det, (uu * wr - uw * ur) / det, t


def bind(
    sparse_vertices: np.ndarray,
    triangles: np.ndarray,
    dense_vertices: np.ndarray,
    *,
    dense_triangles: np.ndarray | None = None,
    candidates: int = 8,
    regularisation: float = 3.0,
) -> Binding:
    """Bind dense points to the facets of the sparse reference mesh (paper §3.1).

    sparse_vertices : (N, 3) mm; triangles : (T, 3) int, outward (counter-clockwise);
    dense_vertices : (M, 3) mm, already in the sparse frame (see :func:`register_icp`).
    candidates : facets (nearest by centroid) tried per dense point.
    regularisation : lambda^2 relative to the mean squared curvature weight c_X^2 of the
        reference mesh; small values follow the curvature constraints, large ones the
        Sumner-Popovic normal-preserving map.
    """
    sparse = _check_points("sparse_vertices", sparse_vertices)
    dense = _check_points("dense_vertices", dense_vertices)
    topo = MeshTopology(triangles, len(sparse))
    tri = topo.triangles
    if not (regularisation > 0 and np.isfinite(regularisation)):
        raise InputError(f"regularisation must be positive, got {regularisation}")
    normals, curv = vertex_normals(sparse, topo), angle_deficits(sparse, topo)
    a_pt, e1, e2, n, inv = _facet_basis(sparse, tri)
    k = int(min(max(candidates, 1), len(tri)))
    centroids = sparse[tri].mean(1)
    _, cand = cKDTree(centroids).query(dense, k=k)
    cand = cand.reshape(len(dense), k)
    corners = [sparse[tri[cand, i]] for i in range(3)]
    cnorm = [normals[tri[cand, i]] for i in range(3)]
    m = np.broadcast_to(dense[:, None, :], corners[0].shape)
    t0 = np.einsum("mkd,mkd->mk", m - corners[0], n[cand])
    wa, wb, t = _project_on_facets(m, *corners, *cnorm, t0)
    wc = 1.0 - wa - wb
    inside = (np.minimum(np.minimum(wa, wb), wc) >= -_INSIDE_EPS) & np.isfinite(t)
    score = np.where(inside, np.abs(t), np.inf)
    best = np.argmin(score, axis=1)
    found = np.isfinite(score[np.arange(len(dense)), best])
    if not found.all():
        lost = ~found
        flat = [x[lost].reshape(-1, 3) for x in (m, *corners)]
        dist = point_triangle_distance(*flat).reshape(-1, k)
        best[lost] = np.argmin(dist, axis=1)
    rows = np.arange(len(dense))
    facet = cand[rows, best]
    weights = np.stack([wa[rows, best], wb[rows, best], wc[rows, best]], axis=1)
    offset = t[rows, best]
    local = np.einsum("mij,mj->mi", inv[facet], dense - a_pt[facet])
    bad = ~(np.isfinite(weights).all(1) & np.isfinite(offset))
    if bad.any():  # projection diverged (far outside): orthogonal projection on the facet
        lb = local[bad]
        weights[bad] = np.c_[1.0 - lb[:, 0] - lb[:, 1], lb[:, 0], lb[:, 1]]
        offset[bad] = lb[:, 2]
    corner_normals = np.einsum("tij,tcj->tci", inv, normals[tri])
    c = curv[tri] * corner_normals[..., 2]
    mean_c2 = float(np.mean(c * c))
    lambda2 = regularisation * (mean_c2 if mean_c2 > 0 else 1.0)
    dtri = np.zeros((0, 3), np.int64) if dense_triangles is None else dense_triangles
    dtri = np.asarray(dtri, dtype=np.int64).reshape(-1, 3)
    if dtri.size and (dtri.min() < 0 or dtri.max() >= len(dense)):
        raise InputError(f"dense_triangles index points outside 0..{len(dense) - 1}")
    return Binding(sparse, tri, dense, facet.astype(np.int64), local, weights,
                   offset, found, corner_normals, curv, lambda2, dtri)


def register_and_bind(
    sparse_vertices: np.ndarray,
    triangles: np.ndarray,
    dense_vertices: np.ndarray,
    dense_triangles: np.ndarray | None = None,
    **bind_options: Any,
) -> tuple[Binding, Registration]:
    """Steps 1 and 2: ICP of the sparse mesh onto the dense scan, then :func:`bind`.

    dense_vertices : (M, 3) mm in the scan's own frame, roughly aligned with the sparse mesh.
    dense_triangles : (Q, 3), enables point-to-plane ICP (recommended). Returns the binding
    (dense points moved into the sparse frame: ``registration.invert(dense_vertices)``) and
    the registration (``dense ~ R sparse + T``; check its ``rms`` and ``converged``).
    """
    dense = _check_points("dense_vertices", dense_vertices)
    reg = register_icp(_check_points("sparse_vertices", sparse_vertices), dense,
                       fixed_triangles=dense_triangles)
    return bind(sparse_vertices, triangles, reg.invert(dense), dense_triangles=dense_triangles,
                **bind_options), reg


def facet_maps(binding: Binding, vertices: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-facet affine maps for a deformed sparse mesh (paper §3.2, closed form above).

    vertices : (N, 3) mm, the sparse mesh now. Returns A' (T, 3), e1' (T, 3), e2' (T, 3) and
    v = L n (T, 3): f(x) = A' + L (x - A) with L [e1 e2 n] = [e1' e2' v].
    """
    tri, topo = binding.triangles, binding.topology
    a = vertices[tri[:, 0]]
    e1, e2 = vertices[tri[:, 1]] - a, vertices[tri[:, 2]] - a
    cross = facet_cross(vertices, tri)
    n_new = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    normals = vertex_normals(vertices, topo)
    k_new = angle_deficits(vertices, topo)
    cn = binding.corner_normals
    k_ref = binding.curvature[tri]
    r = k_new[tri][..., None] * normals[tri] - k_ref[..., None] * (
        cn[..., 0:1] * e1[:, None, :] + cn[..., 1:2] * e2[:, None, :]
    )
    num = np.einsum("tc,tcd->td", binding.curvature_weights, r) + binding.lambda2 * n_new
    return a, e1, e2, num / binding.denominators[:, None]


def apply(binding: Binding, sparse_vertices_new: np.ndarray) -> np.ndarray:
    """Dense mesh (M, 3) mm for the sparse mesh at ``sparse_vertices_new`` (N, 3) mm."""
    v = _check_points("sparse_vertices_new", sparse_vertices_new, len(binding.sparse_vertices))
    return binding.gather @ np.concatenate(facet_maps(binding, v)) + binding.held


def barycentric_apply(binding: Binding, sparse_vertices_new: np.ndarray) -> np.ndarray:
    """Baseline: each dense point moved by the binding-weighted mean of its facet's vertex
    displacements (no rotation of the offset). (N, 3) -> (M, 3) mm."""
    v = _check_points("sparse_vertices_new", sparse_vertices_new, len(binding.sparse_vertices))
    disp = (v - binding.sparse_vertices)[binding.triangles[binding.facet]]  # (M, 3, 3)
    moved = np.einsum("mc,mcd->md", binding.weights, disp)
    if binding.follow is not None:
        moved *= binding.follow[:, None]
    return binding.dense_vertices + moved


def _check_model(binding: Binding, model: FaceModel) -> None:
    if model.n_points != len(binding.sparse_vertices):
        raise InputError(f"the model has {model.n_points} points, the binding's sparse mesh "
                         f"{len(binding.sparse_vertices)}")


def dense_modes(
    binding: Binding, model: FaceModel, *, step: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Dense mean (M, 3) and modes (K, M, 3) mm per unit alpha, so that
    ``dense(alpha) ~ mean + sum_k alpha_k modes[k]``.

    mean = transfer of ``model.mean``; modes[k] = (transfer(mean + step b_k) -
    transfer(mean - step b_k)) / (2 step), a central difference that cancels the even-order
    error. The gap to :func:`apply` per frame grows with the motion: on the test paraboloid
    (modes of 1.3-2.4 mm per s.d., sparse motion up to 9 mm over the box [-2.5, 2.5]^3) it is
    at most 0.21-0.27 mm, median 0.06 mm; the tests hold it to 0.3 mm. Measure a model's own
    with :func:`linearity_error` on postures of its training range.
    """
    _check_model(binding, model)
    if not (step > 0 and np.isfinite(step)):
        raise InputError(f"step must be positive, got {step}")
    mean = apply(binding, model.mean)
    modes = np.stack([
        (apply(binding, model.mean + step * b) - apply(binding, model.mean - step * b)) / (2 * step)
        for b in model.basis
    ])  # fmt: skip
    return mean, modes


def linearity_error(
    binding: Binding, model: FaceModel, alphas: np.ndarray, *, step: float = 1.0,
    points: np.ndarray | None = None,
) -> np.ndarray:
    """Max distance (F,) mm between the linear dense modes and per-frame transfer at each alpha.

    alphas : (F, K). Use postures from the training range to state a model's tolerance.
    points : (M,) bool or indices, the dense points to measure (default all), e.g. only those
        that move with the articulation.
    """
    alphas = np.asarray(alphas, dtype=np.float64)
    if alphas.ndim != 2 or alphas.shape[1] != model.n_params:
        raise InputError(f"alphas must have shape (F, {model.n_params}), got {alphas.shape}")
    mean, modes = dense_modes(binding, model, step=step)
    linear = mean + np.einsum("fk,kmd->fmd", alphas, modes)
    exact = np.stack([apply(binding, s) for s in model.shape(alphas)])
    gap = np.linalg.norm(linear - exact, axis=-1)
    if points is not None:
        gap = gap[:, np.asarray(points)]
        if gap.shape[1] == 0:
            raise InputError("linearity_error: no points to measure")
    return gap.max(axis=1)

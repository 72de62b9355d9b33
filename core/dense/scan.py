"""A whole head scan, in its own frame and units, bound to a speaker model (METHOD.md §5).

A real scan (an artist's head, a photogrammetry or structured-light capture) covers far more
than the lower-face model: cranium, ears, neck. Binding it takes three steps:

1. **Landmarks** (:func:`~articast.core.dense.landmarks.parse_landmarks`): 68 points of the
   iBUG scheme in 3-D, given by the user with the scan (``.ljson``, ``.pts`` or a JSON list).
   The points that have a clear counterpart among the model's MPEG-4 feature points
   (:data:`IBUG_TO_MPEG4`: lip corners, lip mid points, nose base, eye centres) give a
   similarity transform, scale included (weighted Umeyama), from the scan's frame and unit to
   the head frame in mm.
2. **ICP on the overlap** (:func:`align_scan`): the rigid point-to-plane ICP of
   :func:`~articast.core.dense.mesh.register_icp` refines it, between the model's surface
   points and the scan points near them only (the rest of the head has no counterpart).
   An alignment that fails is refused with its reason (landmarks that do not fit the model
   after the similarity, ICP that does not converge or walks away from the landmarks, a scan
   that does not cover the model's face).
3. **Support and falloff** (:func:`bind_scan`): points within ``support_mm`` of the model's
   surface are bound per facet (:func:`~articast.core.dense.transfer.bind`) and move with the
   articulation; points further away or beyond the model's border follow their nearest
   surface point by a share ``follow`` that falls from 1 to 0 over ``falloff_mm`` (a raised
   cosine), so the neck under the jaw follows the jaw partly, the cranium stays with the head,
   and nothing tears at the border. :class:`ScanReport` says how many points are bound which
   way. A real scan's surface lies millimetres off the model's, and some of the model's facets
   fold as it articulates (the lip opening, under the jaw): an offset turning with such a facet
   swings non-linearly, so the share of the offset that turns is limited where the linear
   dense modes would stray (``turn`` of :class:`~articast.core.dense.transfer.Binding`).

Frames: the scan's own frame and unit in, the head frame in mm out (x speaker's left, y up,
z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from articast.core.dense.mesh import point_triangle_distance, register_icp
from articast.core.dense.transfer import Binding, apply, bind, dense_modes
from articast.core.errors import InputError
from articast.core.model.face import FaceModel

IBUG_TO_MPEG4: tuple[tuple[str, tuple[int, ...], float], ...] = (
    ("8.3", (54,), 1.0),  # outer lip corner, speaker's left (iBUG: image right)
    ("8.4", (48,), 1.0),  # outer lip corner, speaker's right
    ("8.1", (51,), 1.0),  # upper outer lip, middle
    ("8.2", (57,), 0.5),  # lower outer lip, middle: moves with the jaw, half weight
    ("9.15", (33,), 1.0),  # nose base, middle (subnasale)
    ("3.5", (42, 43, 44, 45, 46, 47), 0.5),  # eye centre, speaker's left: mean of its contour
    ("3.6", (36, 37, 38, 39, 40, 41), 0.5),  # eye centre, speaker's right
)
"""MPEG-4 feature point of the model, the iBUG-68 points (0-based) whose mean is its
counterpart, and its weight in the similarity. Left out: the chin (iBUG 8 is the menton under
the chin, the model's 2.1 the front of the chin: ~20 mm apart in depth), the inner lip
points (the model's mean posture has the mouth open, a scan's is usually closed), the jaw
contour, brows and nose bridge (no counterpart in the model)."""

# ---------------------------------------------------------------- alignment
@dataclass(frozen=True)
class Similarity:
    """``X_head = scale * rotation @ X_scan + translation`` (head frame, mm)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Scan-frame points (..., 3) -> head frame, mm."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation


def similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> Similarity:
    """Weighted least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991), no reflection.

    src, dst : (P, 3); weights : (P,) >= 0. :class:`InputError` when the points span no
    plane (the rotation is not determined).
    """
    w = np.asarray(weights, np.float64) / np.sum(weights)
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    u, sv, vt = np.linalg.svd(cov)
    var_s = float(w @ np.einsum("pd,pd->p", xs, xs))
    if var_s <= 0 or sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise InputError("the shared landmarks lie on a line: the scan's orientation is not "
                         "determined")
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(d) @ vt
    scale = float((sv * d).sum() / var_s)
    return Similarity(scale, rot, mu_d - scale * rot @ mu_s)


@dataclass(frozen=True)
class Alignment:
    """The scan's map to the head frame and how it was found.

    transform : scan frame -> head frame (similarity, then the ICP refinement), mm.
    landmark_rms_mm : weighted RMS of the shared landmarks after the similarity, and
    icp_landmark_rms_mm after the ICP. pairs : feature-point labels used.
    icp_rms_mm, icp_iterations, icp_converged : of the ICP on the overlap;
    overlap_fraction : share of the model's surface points with a scan point within
    ``overlap_mm``.
    """

    transform: Similarity
    pairs: tuple[str, ...]
    landmark_rms_mm: float
    icp_landmark_rms_mm: float
    icp_rms_mm: float
    icp_iterations: int
    icp_converged: bool
    overlap_fraction: float


def shared_landmarks(model: FaceModel, landmarks: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Scan points (P, 3), model points (P, 3) mm, weights (P,) and the MPEG-4 labels of the
    pairs both sides have (a pair is dropped when the model lacks the label or a landmark is
    missing)."""
    src, dst, w, names = [], [], [], []
    for label, idx, weight in IBUG_TO_MPEG4:
        if label not in model.feature_points:
            continue
        p = landmarks[list(idx)].mean(0)
        if not np.all(np.isfinite(p)):
            continue
        src.append(p)
        dst.append(model.mean[model.point(label)])
        w.append(weight)
        names.append(label)
    return np.array(src).reshape(-1, 3), np.array(dst).reshape(-1, 3), np.array(w), tuple(names)


def coverage(model: FaceModel, head_points: np.ndarray, within_mm: float) -> np.ndarray:
    """(S,) bool over the model's surface points (``np.unique(model.triangles)``): a point of
    ``head_points`` (P, 3) mm head frame lies within ``within_mm``."""
    sparse = model.mean[np.unique(model.triangles)]
    near, _ = cKDTree(head_points).query(sparse, distance_upper_bound=within_mm)
    return np.isfinite(near)


def _rms(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    return float(np.sqrt(np.sum(w * np.sum((a - b) ** 2, axis=1)) / np.sum(w)))


def align_scan(
    model: FaceModel,
    vertices: np.ndarray,
    triangles: np.ndarray,
    landmarks: np.ndarray,
    *,
    max_landmark_rms_mm: float = 10.0,
    overlap_mm: float = 12.0,
    min_overlap: float = 0.5,
    max_drift_mm: float = 5.0,
) -> Alignment:
    """Similarity from the shared landmarks, then rigid ICP on the overlap (module docstring).

    vertices : (M, 3), triangles : (Q, 3) of the scan, its frame and unit; landmarks :
    (68, 3) iBUG, same frame. Refuses (:class:`InputError`, the reason in one line) when
    fewer than 4 pairs are shared, the landmarks do not fit the model's feature points within
    ``max_landmark_rms_mm`` after the similarity (another scheme, another order, mirrored),
    less than ``min_overlap`` of the model's surface has a scan point within ``overlap_mm``,
    the ICP does not converge, or it moves the landmarks' RMS up by more than
    ``max_drift_mm`` (it slid to another fit of the surfaces).
    """
    src, dst, w, names = shared_landmarks(model, landmarks)
    if len(names) < 4:
        raise InputError(f"only {len(names)} landmarks have a counterpart among the model's "
                         "feature points (lip corners and mid points, nose base, eye centres); "
                         "need at least 4")
    sim = similarity(src, dst, w)
    lm_rms = _rms(sim.apply(src), dst, w)
    if not lm_rms <= max_landmark_rms_mm:
        raise InputError(f"the landmarks do not fit the model's feature points: RMS "
                         f"{lm_rms:.1f} mm after the best similarity (limit "
                         f"{max_landmark_rms_mm:g} mm); are they the iBUG 68 points, in order?")
    head = sim.apply(vertices)
    sparse = model.mean[np.unique(model.triangles)]
    covered = coverage(model, head, overlap_mm)
    moving = sparse[covered]
    overlap = float(covered.mean())
    if overlap < min_overlap:
        raise InputError(f"after the landmark alignment the scan covers {overlap:.0%} of the "
                         f"model's face (need {min_overlap:.0%} within {overlap_mm:g} mm): does "
                         "the scan show the face, and are the landmarks on it?")
    near_model, _ = cKDTree(sparse).query(head, distance_upper_bound=3 * overlap_mm)
    keep = np.isfinite(near_model)
    remap = -np.ones(len(head), np.int64)
    remap[keep] = np.arange(keep.sum())
    tri = remap[triangles] if len(triangles) else np.zeros((0, 3), np.int64)
    tri = tri[(tri >= 0).all(1)] if len(tri) else tri
    reg = register_icp(moving, head[keep], fixed_triangles=tri if len(tri) else None,
                       max_iterations=200, tolerance=1e-7)
    if not reg.converged:
        raise InputError(f"the ICP on the overlap did not converge in {reg.iterations} "
                         f"iterations (RMS {reg.rms:.2f} mm): check the landmarks")
    # dense ~ R sparse + T  =>  head-frame scan = R^T (s Q X + t - T)
    rot = reg.rotation.T @ sim.rotation
    final = Similarity(sim.scale, rot, reg.rotation.T @ (sim.translation - reg.translation))
    icp_lm = _rms(final.apply(src), dst, w)
    if icp_lm > lm_rms + max_drift_mm:
        raise InputError(f"the ICP slid away from the landmarks (their RMS went from "
                         f"{lm_rms:.1f} to {icp_lm:.1f} mm): the scan's face and the model's "
                         "differ too much to refine")
    return Alignment(final, names, lm_rms, icp_lm, reg.rms, reg.iterations, reg.converged,
                     overlap)


# ---------------------------------------------------------------- binding with falloff
@dataclass(frozen=True)
class ScanReport:
    """How the points were bound.

    articulated : (M,) bool, in the model's support: within ``support_mm`` of the model's
    surface, the nearest surface point not on its border (outer outline or lip opening);
    bound per facet, they move fully with the articulation. distance_mm : (M,) to the
    model's surface. n_articulated; n_border : beyond the border or further than
    ``support_mm``, following their nearest facet by a share in (0, 1]; n_held : following
    the head only (share 0). inside_support_fraction : of the articulated points, the share
    whose binding found a facet containing them (the rest: the nearest facet).
    n_unturned : articulated points whose normal offset does not turn fully with the facet
    (``turn`` < 1: offsets near ``support_mm``, and :func:`limit_turning`).
    """

    articulated: np.ndarray
    distance_mm: np.ndarray
    n_articulated: int
    n_border: int
    n_held: int
    inside_support_fraction: float
    n_unturned: int = 0


def falloff(distance: np.ndarray, support_mm: float, falloff_mm: float) -> np.ndarray:
    """(M,) share of the facet motion: 1 up to ``support_mm`` from the model surface, a raised
    cosine down to 0 at ``support_mm + falloff_mm`` (C1: no crease at either end)."""
    u = np.clip((np.asarray(distance) - support_mm) / falloff_mm, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def bind_scan(
    model: FaceModel,
    vertices: np.ndarray,
    triangles: np.ndarray | None = None,
    *,
    support_mm: float = 10.0,
    falloff_mm: float = 40.0,
    candidates: int = 16,
    regularisation: float = 3.0,
    turn_tolerance_mm: float = 0.2,
) -> tuple[Binding, ScanReport]:
    """Bind a whole-head scan already in the head frame (mm) to ``model``'s mesh.

    vertices : (M, 3) mm head frame (e.g. ``align_scan(...).transform.apply(scan)``);
    triangles : (Q, 3) the scan's facets, kept for rendering.

    * In the support (within ``support_mm`` of the model's surface, nearest surface point
      not on its border): the per-facet binding of :func:`~articast.core.dense.transfer.bind`;
      the normal offset turns with the facet fully up to ``support_mm / 3``, not at all at
      ``support_mm`` (a raised cosine), and less where it would make the dense modes stray
      by more than ``turn_tolerance_mm`` (:func:`limit_turning`).
    * Elsewhere: bound to the nearest surface point Q, which moves with its facet
      (barycentrically), the offset M - Q carried unrotated, scaled by the share
      :func:`falloff` of the distance. Q and the falloff vary continuously over the scan,
      and at the support's edge both rules give the same motion: no tear.
    """
    if not (support_mm > 0 and falloff_mm > 0):
        raise InputError(f"support_mm and falloff_mm must be positive, got {support_mm}, "
                         f"{falloff_mm}")
    b = bind(model.mean, model.triangles, vertices, dense_triangles=triangles,
             candidates=8, regularisation=regularisation)
    tri = b.triangles
    sparse = b.sparse_vertices
    k = int(min(candidates, len(tri)))
    _, cand = cKDTree(sparse[tri].mean(1)).query(b.dense_vertices, k=k)
    cand = cand.reshape(len(b.dense_vertices), k)
    corners = [sparse[tri[cand, i]].reshape(-1, 3) for i in range(3)]
    pts = np.repeat(b.dense_vertices, k, axis=0)
    dist = point_triangle_distance(pts, *corners).reshape(-1, k)
    nearest = cand[np.arange(len(cand)), np.argmin(dist, axis=1)]
    distance = dist.min(axis=1)
    articulated = (distance <= support_mm) & ~_beyond_border(
        b.dense_vertices, sparse, tri, nearest, distance)
    facet, local = b.facet.copy(), b.local.copy()
    weights, offset = b.weights.copy(), b.offset.copy()
    out = ~articulated
    if out.any():  # by the nearest surface point Q: Q moves with the facet, M - Q is carried
        bc = closest_point_coordinates(b.dense_vertices[out], *(
            sparse[tri[nearest[out], i]] for i in range(3)))
        facet[out], local[out] = nearest[out], np.c_[bc[:, 1:], np.zeros(len(bc))]
        weights[out], offset[out] = bc, distance[out]
    follow = falloff(distance, support_mm, falloff_mm)
    # the offset turns fully near the surface, not at all at the support's edge: there the
    # articulated points move as their border neighbours do (no tear)
    taper = falloff(np.abs(local[:, 2]), support_mm / 3, support_mm * 2 / 3)
    turn = np.where(articulated, taper, 0.0)
    binding = Binding(b.sparse_vertices, tri, b.dense_vertices, facet, local, weights, offset,
                      b.inside & articulated, b.corner_normals, b.curvature, b.lambda2,
                      b.dense_triangles, follow=follow, turn=turn)
    binding = limit_turning(binding, model, tolerance_mm=turn_tolerance_mm)
    n_art = int(articulated.sum())
    held = follow == 0
    report = ScanReport(
        articulated=articulated, distance_mm=distance, n_articulated=n_art,
        n_border=int((~articulated & ~held).sum()), n_held=int(held.sum()),
        inside_support_fraction=float(b.inside[articulated].mean()) if n_art else 0.0,
        n_unturned=int((binding.turn[articulated] < 1).sum()) if binding.turn is not None
        else 0)
    return binding, report


def _beyond_border(points: np.ndarray, sparse: np.ndarray, tri: np.ndarray,
                   nearest: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """(M,) bool: the surface point nearest each point lies on a border edge of the mesh
    (an edge of one facet only) of its nearest facet ``nearest`` at ``distance``."""
    edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, inv, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    border_edge = (counts == 1)[inv.ravel()].reshape(-1, 3)  # (T, 3) edges 01, 12, 20
    out = np.zeros(len(points), bool)
    for j, (u, w) in enumerate(((0, 1), (1, 2), (2, 0))):
        on = border_edge[nearest, j]
        if not on.any():
            continue
        p, q = sparse[tri[nearest[on], u]], sparse[tri[nearest[on], w]]
        x = points[on]
        d = q - p
        s = np.clip(np.einsum("pd,pd->p", x - p, d) / np.einsum("pd,pd->p", d, d), 0.0, 1.0)
        edge_dist = np.linalg.norm(x - p - s[:, None] * d, axis=1)
        out[np.flatnonzero(on)] |= edge_dist <= distance[on] + 1e-9
    return out


def closest_point_coordinates(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                              c: np.ndarray) -> np.ndarray:
    """(P, 3) barycentric coordinates of the point of triangle ABC nearest p (all (P, 3))."""
    e1, e2 = b - a, c - a
    gram = np.stack([np.einsum("pd,pd->p", e1, e1), np.einsum("pd,pd->p", e1, e2),
                     np.einsum("pd,pd->p", e2, e2)], 1)
    r1, r2 = np.einsum("pd,pd->p", p - a, e1), np.einsum("pd,pd->p", p - a, e2)
    det = gram[:, 0] * gram[:, 2] - gram[:, 1] ** 2
    u = (gram[:, 2] * r1 - gram[:, 1] * r2) / det
    v = (gram[:, 0] * r2 - gram[:, 1] * r1) / det
    best = np.c_[1.0 - u - v, u, v]
    inside = best.min(1) >= 0
    if inside.all():
        return best
    cand, dist = [], []
    for i, j in ((0, 1), (1, 2), (2, 0)):  # the nearest point of each edge
        x, y = (a, b, c)[i], (a, b, c)[j]
        d = y - x
        s = np.clip(np.einsum("pd,pd->p", p - x, d) / np.einsum("pd,pd->p", d, d), 0.0, 1.0)
        w = np.zeros((len(p), 3))
        w[:, i], w[:, j] = 1.0 - s, s
        cand.append(w)
        dist.append(np.linalg.norm(p - x - s[:, None] * d, axis=1))
    pick = np.argmin(np.stack(dist), axis=0)
    edge = np.stack(cand)[pick, np.arange(len(p))]
    return np.where(inside[:, None], best, edge)


def limit_turning(binding: Binding, model: FaceModel, *, tolerance_mm: float = 0.2,
                  probes: int = 24, seed: int = 1) -> Binding:
    """The binding with ``turn`` lowered where the turning normal offset makes the dense
    modes stray from per-frame transfer by more than ``tolerance_mm``.

    The gap g of each point between :func:`~articast.core.dense.transfer.dense_modes` and
    per-frame transfer is measured over calibration postures of the training range (each
    parameter at its min and max, and ``probes`` random postures of the box); the carried,
    unrotated share of the offset is exactly linear in alpha, so ``turn = min(1, tol / g)``
    brings the gap to at most ``tol`` at those postures, continuously in g. Points bound to
    facets that fold with the articulation (the model's lip opening, under the jaw) keep a
    thick scan's offset from swinging non-linearly.
    """
    s = model.stats
    k = model.n_params
    box = np.concatenate([np.diag(s.min), np.diag(s.max),
                          np.random.default_rng(seed).uniform(s.min, s.max, size=(probes, k))])
    mean, modes = dense_modes(binding, model)
    gap = np.zeros(binding.n_dense)
    for a in box:
        lin = mean + np.tensordot(a, modes, 1)
        gap = np.maximum(gap, np.linalg.norm(lin - apply(binding, model.shape(a)), axis=1))
    turn = binding.turn if binding.turn is not None else np.ones(binding.n_dense)
    turn = turn * np.minimum(1.0, tolerance_mm / np.maximum(gap, 1e-12))
    return Binding(binding.sparse_vertices, binding.triangles, binding.dense_vertices,
                   binding.facet, binding.local, binding.weights, binding.offset,
                   binding.inside, binding.corner_normals, binding.curvature, binding.lambda2,
                   binding.dense_triangles, follow=binding.follow, turn=turn)


def mouth_facets(binding: Binding, model: FaceModel) -> np.ndarray:
    """(Q,) bool over ``binding.dense_triangles``: the scan's facets across its lips, to leave
    out of the drawing so that the mouth opens instead of stretching its skin.

    A scan usually has its mouth closed, its lips joined by thin facets; the model's lips part
    as the jaw opens. A scan point follows the upper lip when its facet of the model has a
    point of the ``upper_lip`` group and none of ``lower_lip`` (and the other way round); a
    facet across the lips has points following each, and two of its three over the model's
    mouth opening (bound to no facet containing them: ``binding.inside`` false), which leaves
    the skin at the corners of an open mouth alone. On menpo3d's james: 23 facets along the
    line where the lips meet. None without the two groups.
    """
    tri = binding.dense_triangles
    upper, lower = np.zeros(model.n_points, bool), np.zeros(model.n_points, bool)
    upper[model.group("upper_lip")], lower[model.group("lower_lip")] = True, True
    if len(tri) == 0 or not upper.any() or not lower.any():
        return np.zeros(len(tri), bool)
    corners = binding.triangles[binding.facet]
    up, low = upper[corners].any(axis=1), lower[corners].any(axis=1)
    across = (up & ~low)[tri].any(axis=1) & (low & ~up)[tri].any(axis=1)
    return across & ((~binding.inside)[tri].sum(axis=1) >= 2)

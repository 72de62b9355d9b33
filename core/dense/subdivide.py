"""Loop subdivision of a triangle mesh (vectorised): each step splits every triangle in four
and smooths, converging to a C2 surface away from the boundary (Loop, 1987). Used to make a
dense face mesh from a sparse model mesh that the dense-mesh transfer then animates."""

from __future__ import annotations

import numpy as np

from articast.core.errors import InputError


def loop_subdivide(vertices: np.ndarray, triangles: np.ndarray,
                   steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Subdivide ``steps`` times.

    vertices : (N, 3) float; triangles : (T, 3) int (only the vertices they use are moved,
    unreferenced vertices are kept as they are). Returns (N', 3) vertices, (T * 4**steps, 3)
    triangles; the first N vertices are the (smoothed) original ones, in order.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3:
        raise InputError("loop_subdivide needs vertices (N, 3) and triangles (T, 3)")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise InputError("triangles index vertices that do not exist")
    for _ in range(int(steps)):
        v, t = _step(v, t)
    return v, t.astype(np.int32)


def _step(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = len(v)
    half = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])  # (3T, 2) directed
    opposite = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    key = np.sort(half, axis=1)
    edges, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    e = len(edges)
    boundary = counts == 1
    # edge points: 3/8 (a + b) + 1/8 (c + d) inside, midpoints on the boundary
    opp_sum = np.zeros((e, 3))
    np.add.at(opp_sum, inverse, v[opposite])
    ends = v[edges[:, 0]] + v[edges[:, 1]]
    edge_pts = np.where(boundary[:, None], 0.5 * ends, 0.375 * ends + 0.125 * opp_sum)
    # vertex points
    nb_sum = np.zeros((n, 3))
    valence = np.zeros(n)
    for a, b in ((0, 1), (1, 0)):
        np.add.at(nb_sum, edges[:, a], v[edges[:, b]])
        np.add.at(valence, edges[:, a], 1)
    safe = np.maximum(valence, 1)
    beta = np.where(valence > 3, 3.0 / (8.0 * safe), 3.0 / 16.0)
    new_v = np.where(valence[:, None] > 0,
                     (1 - valence * beta)[:, None] * v + beta[:, None] * nb_sum, v)
    bnd_sum = np.zeros((n, 3))
    bnd_count = np.zeros(n)
    for a, b in ((0, 1), (1, 0)):
        np.add.at(bnd_sum, edges[boundary, a], v[edges[boundary, b]])
        np.add.at(bnd_count, edges[boundary, a], 1)
    on_bnd = bnd_count == 2
    new_v[on_bnd] = 0.75 * v[on_bnd] + 0.125 * bnd_sum[on_bnd]
    # four triangles per triangle
    m = (n + inverse).reshape(3, -1).T  # edge-point ids of edges (01, 12, 20) per triangle
    tris = np.concatenate([
        np.stack([t[:, 0], m[:, 0], m[:, 2]], 1),
        np.stack([t[:, 1], m[:, 1], m[:, 0]], 1),
        np.stack([t[:, 2], m[:, 2], m[:, 1]], 1),
        m,
    ])
    return np.concatenate([new_v, edge_pts]), tris

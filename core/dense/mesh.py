"""Triangle-mesh geometry for dense-mesh transfer: normals, angle deficits, distances, ICP.

All functions are vectorised over facets or points. Vertices are ``(N, 3)`` float arrays in
mm in one frame (normally the head frame); triangles ``(T, 3)`` int vertex indices, counter-
clockwise seen from outside (for a face: from the front, +z), so normals point outwards.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from articast.core.errors import InputError


class MeshTopology:
    """Connectivity of a triangle mesh, precomputed once for fast per-frame geometry.

    triangles : (T, 3) int. n_vertices : N.
    Holds sparse incidence matrices (vertex x facet, vertex x facet corner) and the boundary
    vertices (on an edge used by one facet only).
    """

    def __init__(self, triangles: np.ndarray, n_vertices: int) -> None:
        tri = np.asarray(triangles, dtype=np.int64)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
            raise InputError(f"triangles must have shape (T >= 1, 3), got {tri.shape}")
        if tri.min() < 0 or tri.max() >= n_vertices:
            raise InputError(f"triangles index vertices outside 0..{n_vertices - 1}")
        if np.any((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])):
            raise InputError("a triangle repeats a vertex")
        self.triangles = tri
        self.n_vertices = int(n_vertices)
        t = tri.shape[0]
        ones = np.ones(3 * t)
        self.corners = sp.csr_matrix(
            (ones, (tri.ravel(), np.arange(3 * t))), shape=(n_vertices, 3 * t)
        )
        self.incidence = sp.csr_matrix(
            (ones, (tri.ravel(), np.repeat(np.arange(t), 3))), shape=(n_vertices, t)
        )
        edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        uniq, counts = np.unique(edges, axis=0, return_counts=True)
        self.boundary = np.zeros(n_vertices, dtype=bool)
        self.boundary[uniq[counts == 1].ravel()] = True
        self.used = np.zeros(n_vertices, dtype=bool)
        self.used[tri.ravel()] = True


def facet_cross(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) ``(B - A) x (C - A)``: normal times twice the area (mm^2)."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return np.cross(b - a, c - a)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def vertex_normals(vertices: np.ndarray, topo: MeshTopology) -> np.ndarray:
    """(N, 3) unit area-weighted vertex normals (zero for vertices in no facet)."""
    return _unit(topo.incidence @ facet_cross(vertices, topo.triangles))


def corner_angles(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) interior angle (rad) at each corner of each facet."""
    p = vertices[triangles]  # (T, 3, 3)
    u = np.roll(p, -1, axis=1) - p  # to the next corner
    w = np.roll(p, 1, axis=1) - p  # to the previous corner
    return np.arctan2(np.linalg.norm(np.cross(u, w), axis=-1), np.einsum("tcd,tcd->tc", u, w))


def angle_deficits(vertices: np.ndarray, topo: MeshTopology) -> np.ndarray:
    """(N,) discrete Gaussian curvature K = 2 pi - sum of corner angles (rad).

    Boundary vertices and vertices in no facet get 0: there the deficit measures the outline's
    turning, not bending, so the curvature constraint of the transfer must not use it.
    """
    k = 2.0 * np.pi - topo.corners @ corner_angles(vertices, topo.triangles).ravel()
    return np.where(topo.boundary | ~topo.used, 0.0, k)


def point_triangle_distance(
    points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """(P,) Euclidean distance of each point to its triangle; all inputs (P, 3) mm."""
    n = np.cross(b - a, c - a)
    nn = np.einsum("pd,pd->p", n, n)
    inside = np.ones(len(points), dtype=bool)
    for p, q in ((a, b), (b, c), (c, a)):  # inside iff on the inner side of every edge
        inside &= np.einsum("pd,pd->p", np.cross(q - p, points - p), n) >= 0
    plane = np.abs(np.einsum("pd,pd->p", points - a, n)) / np.sqrt(np.where(nn > 0, nn, 1.0))
    seg = np.min([_segment_distance(points, p, q) for p, q in ((a, b), (b, c), (c, a))], axis=0)
    return np.where(inside & (nn > 0), plane, seg)


def _segment_distance(x: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    d = q - p
    dd = np.einsum("pd,pd->p", d, d)
    s = np.clip(np.einsum("pd,pd->p", x - p, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.linalg.norm(x - p - s[:, None] * d, axis=-1)


@dataclass(frozen=True)
class Registration:
    """Rigid map ``X_fixed = rotation @ X_moving + translation`` found by :func:`register_icp`.

    rotation : (3, 3). translation : (3,) mm. rms : final RMS distance (mm) of the kept pairs.
    iterations : ICP iterations run. converged : the RMS change fell below the tolerance.
    """

    rotation: np.ndarray
    translation: np.ndarray
    rms: float
    iterations: int
    converged: bool

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Moving-frame points (..., 3) -> fixed frame."""
        return np.asarray(points) @ self.rotation.T + self.translation

    def invert(self, points: np.ndarray) -> np.ndarray:
        """Fixed-frame points (..., 3) -> moving frame."""
        return (np.asarray(points) - self.translation) @ self.rotation


def register_icp(
    moving: np.ndarray,
    fixed: np.ndarray,
    *,
    fixed_triangles: np.ndarray | None = None,
    max_iterations: int = 60,
    tolerance: float = 1e-9,
    keep: float = 0.9,
) -> Registration:
    """Rigid ICP: the ``R, T`` minimising the distance of ``moving`` points to ``fixed``.

    moving : (N, 3) mm (the sparse mesh's vertices). fixed : (M, 3) mm (the dense mesh).
    fixed_triangles : (Q, 3) int facets of ``fixed``; when given, the point-to-plane distance
        (the distance to the dense *surface*, as in the paper) is minimised, else
        point-to-point, which stalls at the sampling step of ``fixed`` (a point snaps to the
        nearest sample). keep : fraction of closest pairs used per iteration (robust to parts of
        the sparse mesh the dense one does not cover); when the kept set flips between two sets
        at every step (a two-step cycle of the residual), that is convergence too. Starts from
        the identity: bring the two meshes roughly together first (e.g. both in the head
        frame).
    """
    if not (0.0 < keep <= 1.0) or max_iterations < 1:
        raise InputError(f"need 0 < keep <= 1 and max_iterations >= 1, got {keep}, "
                         f"{max_iterations}")
    moving, fixed = np.asarray(moving, float), np.asarray(fixed, float)
    for name, arr in (("moving", moving), ("fixed", fixed)):
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 3 or not np.isfinite(arr).all():
            raise InputError(f"{name} points must be finite with shape (>= 3, 3), got {arr.shape}")
    fixed_normals = None
    if fixed_triangles is not None:
        fixed_normals = vertex_normals(fixed, MeshTopology(fixed_triangles, len(fixed)))
    tree = cKDTree(fixed)
    rot, trans = np.eye(3), np.zeros(3)
    n_keep = max(3, int(round(keep * len(moving))))
    prev, prev2, rms, it = np.inf, np.inf, np.inf, 0
    last = (rot, trans)  # the pose before the current one
    for it in range(1, max_iterations + 1):
        cur = moving @ rot.T + trans
        dist, idx = tree.query(cur)
        sel = np.argsort(dist)[:n_keep]
        p, q = cur[sel], fixed[idx[sel]]
        if fixed_normals is None:
            d_rot, d_trans = _kabsch(p, q)
            rms = float(np.sqrt(np.mean(dist[sel] ** 2)))
        else:
            nrm = fixed_normals[idx[sel]]
            d_rot, d_trans = _point_to_plane_step(p, q, nrm)
            rms = float(np.sqrt(np.mean(np.einsum("pd,pd->p", p - q, nrm) ** 2)))
        if abs(prev2 - rms) < tolerance <= abs(prev - rms):
            # the trimmed pairs flip between two sets and the poses with them: a fixed point
            # of two steps; keep the better of the two poses
            return (Registration(*last, prev, it, True) if prev < rms
                    else Registration(rot, trans, rms, it, True))
        last = (rot, trans)
        rot, trans = d_rot @ rot, d_rot @ trans + d_trans
        if abs(prev - rms) < tolerance:
            return Registration(rot, trans, rms, it, True)
        prev2, prev = prev, rms
    return Registration(rot, trans, rms, it, False)


def _kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation with ``q ~ R p + t``."""
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, qc - rot @ pc


def _point_to_plane_step(
    p: np.ndarray, q: np.ndarray, n: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One linearised point-to-plane step, returned as an exact rotation and a translation."""
    centre = p.mean(0)  # solve about the centroid: better conditioned
    pc = p - centre
    jac = np.hstack([np.cross(pc, n), n])  # d residual / d (omega, t)
    res = np.einsum("pd,pd->p", q - p, n)
    sol, *_ = np.linalg.lstsq(jac, res, rcond=None)
    omega, t = sol[:3], sol[3:]
    theta = np.linalg.norm(omega)
    k = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    rot = np.eye(3) + k if theta < 1e-12 else (
        np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * (k @ k)
    )
    return rot, centre + t - rot @ centre


def load_obj(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`parse_obj` of a file; :class:`InputError` naming the file for any defect."""
    from articast.core.safe_io import read_regular_bytes

    text = read_regular_bytes(path).decode("utf-8", errors="replace")
    verts, tris = parse_obj(text, source=str(path))
    check_scan(verts, tris, source=str(path))
    check_scan_faces(verts, tris, source=str(path))
    return verts, tris


MAX_COORDINATE_MM = 1e6
"""A scan's coordinates, mm (1 km): beyond, a file is not a face."""


def check_scan(verts: np.ndarray, tris: np.ndarray, source: str = "<obj>") -> None:
    """A scan a face can be bound to: finite coordinates of plausible size, at least three
    distinct vertices that span an area (500 copies of one point bound with a 45 mm error
    before, and exited 0)."""
    if len(verts) and not np.all(np.abs(verts) <= MAX_COORDINATE_MM):
        raise InputError(f"{source}: vertex coordinates must be finite and within "
                         f"{MAX_COORDINATE_MM:g} mm")
    if len(verts) < 3:
        raise InputError(f"{source}: a scan needs at least 3 vertices, found {len(verts)}")
    spread = verts - verts.mean(axis=0)
    extent = np.linalg.svd(spread, compute_uv=False) if len(verts) else np.zeros(3)
    if extent[1] <= 1e-9 * max(1.0, float(extent[0])):
        raise InputError(f"{source}: the vertices do not span a surface (all the same point, "
                         "or on one line)")


MAX_SCAN_VERTICES = 2_000_000
"""Vertices of a scan bind-dense takes: a fine face scan has ~0.1-1 M (binding 1 M took
20-28 s); beyond, it is a point cloud to decimate first."""
MAX_SCAN_FACES = 4_000_000
"""Triangles of a scan (after splitting polygons into fans): twice the vertex limit."""
MAX_BAD_FACE_FRACTION = 0.1
"""Duplicate or degenerate (zero-area) triangles a real scan may carry: a few from its
mesher; a file of mostly such facets (3 M copies of one triangle bound with a 90-101 mm
error, exit 0) is not a face's surface."""


def check_scan_faces(verts: np.ndarray, tris: np.ndarray, source: str = "<obj>",
                     max_bad_fraction: float = MAX_BAD_FACE_FRACTION) -> None:
    """A scan is a surface: it has facets, each naming three vertices it defines, and few of
    them are copies of another or of zero area. One :class:`InputError` line otherwise,
    before any binding (1 M vertices without a facet bound, exit 0, with a 90-101 mm error)."""
    if len(tris) == 0:
        raise InputError(f"{source}: no faces (f lines): a scan is a surface, not a point "
                         f"cloud ({len(verts)} vertices and no facet)")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise InputError(f"{source}: faces refer to vertices the file does not define "
                         f"(indices {int(tris.min()) + 1}..{int(tris.max()) + 1} of "
                         f"{len(verts)})")
    corners = np.sort(tris, axis=1)
    repeated = (corners[:, 0] == corners[:, 1]) | (corners[:, 1] == corners[:, 2])
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    scale = float(np.ptp(verts, axis=0).max()) or 1.0
    flat = repeated | (area2 <= 1e-12 * scale * scale)
    copies = len(corners) - len(np.unique(corners, axis=0))
    bad = int(flat.sum()) + copies
    if bad > max_bad_fraction * len(tris):
        raise InputError(f"{source}: {bad} of {len(tris)} faces are duplicates ({copies}) or "
                         f"degenerate ({int(flat.sum())}: a repeated vertex or no area), over "
                         f"the {max_bad_fraction:.0%} a scan may have: not a surface to bind")


def parse_obj(text: str, source: str = "<obj>", max_vertices: int = MAX_SCAN_VERTICES,
              max_faces: int = MAX_SCAN_FACES) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (M, 3) and triangles (Q, 3) of a Wavefront OBJ text (e.g. a face scan).

    Reads ``v x y z`` and ``f`` lines (``i``, ``i/t``, ``i//n``, ``i/t/n``, 1-based or
    negative indices); polygons are split into triangle fans; other statements are ignored.
    Raises :class:`InputError` ``"<source>: line <n>: <reason>"``, also as soon as the file
    holds more than ``max_vertices`` vertices or ``max_faces`` triangles (no work on a scan
    that is refused anyway).
    """
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0] not in ("v", "f"):
            continue
        try:
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError("a vertex needs 3 coordinates")
                verts.append([float(p) for p in parts[1:4]])
                if len(verts) > max_vertices:
                    raise InputError(f"{source}: line {n}: more than {max_vertices} vertices, "
                                     "the limit for a face scan (decimate it first)")
                continue
            idx = [int(p.split("/")[0]) for p in parts[1:]]
        except ValueError as exc:
            raise InputError(f"{source}: line {n}: {exc}") from None
        if len(idx) < 3:
            raise InputError(f"{source}: line {n}: a face needs at least 3 vertices")
        idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
        if any(not 0 <= i < len(verts) for i in idx):
            raise InputError(f"{source}: line {n}: face refers to a vertex not defined before")
        faces.extend([idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1))
        if len(faces) > max_faces:
            raise InputError(f"{source}: line {n}: more than {max_faces} triangles, the limit "
                             "for a face scan (decimate it first)")
    vertices = np.array(verts, dtype=np.float64).reshape(-1, 3)
    if len(vertices) == 0:
        raise InputError(f"{source}: no vertices")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{source}: vertices must be finite")
    return vertices, np.array(faces, dtype=np.int64).reshape(-1, 3)

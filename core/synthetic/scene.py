"""The triangle soup the renderer draws: articulated face plus non-model render parts.

Parts (head frame, mm): ``skin`` (the model mesh itself, at the true articulated points),
``cavity`` (the mouth interior hanging from the inner lip contour, dark, with a tongue on its
floor), ``upper_teeth`` (fixed to the head), ``lower_teeth`` (rigid with the jaw, the same
motion as the model's lower-teeth points), ``head`` (an ellipsoid with hair behind the face),
``ears``, ``neck`` (an elliptic cylinder down to a shirt collar) and ``shoulders``.
Only ``skin`` is part of the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from articast.core.synthetic.geometry import N_ANGLES, SpeakerGeometry, jaw_transform
from articast.core.synthetic.surface import ARCH_RADIUS, arch_z
from articast.core.synthetic.texture import Atlas


@dataclass(frozen=True, eq=False)
class Scene:
    """vertices, normals : (V, 3) head frame; uv : (V, 2) atlas px; triangles : (T, 3) int64;
    cull : (T,) bool (one-sided triangles); two_sided_vertex : (V,) bool;
    occlusion : (V,) light multiplier (< 1 inside the mouth, which the lips shadow);
    mouth_anchor : (3, 3) mouth centre, left and right inner corners (head frame)."""

    vertices: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    cull: np.ndarray
    two_sided_vertex: np.ndarray
    occlusion: np.ndarray
    mouth_anchor: np.ndarray


@dataclass(frozen=True, eq=False)
class _Part:
    vertices: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    two_sided: bool


def _grid_triangles(rows: int, cols: int, wrap: bool = False) -> np.ndarray:
    """Two triangles per cell of a rows x cols vertex grid (row-major)."""
    c_max = cols if wrap else cols - 1
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(c_max), indexing="ij")
    a = (r * cols + c).ravel()
    b = (r * cols + (c + 1) % cols).ravel()
    return np.concatenate([np.stack([a, b, b + cols], 1), np.stack([a, b + cols, a + cols], 1)])


def _orient(vertices: np.ndarray, tri: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """Flip triangles whose normal points against ``outward`` (T, 3) directions."""
    p = vertices[tri]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    bad = np.einsum("ij,ij->i", fn, outward) < 0
    tri = tri.copy()
    tri[bad] = tri[bad][:, ::-1]
    return tri


def _normals(vertices: np.ndarray, tri: np.ndarray) -> np.ndarray:
    from articast.core.synthetic.render import vertex_normals

    return vertex_normals(vertices, tri)


def _teeth(lower: bool) -> _Part:
    phi = np.linspace(-1.15, 1.15, 23)
    x = ARCH_RADIUS * 0.95 * np.sin(phi)
    rows_y = np.array([-0.6, -4.0, -8.5, -13.0]) if lower else np.array([-0.3, 3.0, 7.5, 12.0])
    rows_t = np.array([0.0, 0.3, 0.72, 1.0])
    z = arch_z(x) - (1.8 if lower else 0.0)
    v = np.stack(np.broadcast_arrays(x[None, :], rows_y[:, None], z[None, :]), -1).reshape(-1, 3)
    st = np.stack(np.broadcast_arrays((phi[None, :] + 1.15) / 2.3, rows_t[:, None]), -1)
    tri = _grid_triangles(rows_y.size, phi.size)
    out = np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], -1)
    tri = _orient(v, tri, out[tri[:, 0] % phi.size])
    return _Part(v, _normals(v, tri), Atlas.material_uv("teeth", st.reshape(-1, 2)), tri, True)


def _ellipsoid(centre: tuple[float, ...], radii: tuple[float, ...], material: str,
               n_az: int = 32, n_pol: int = 16) -> _Part:
    """A closed ellipsoid (head, ears, shoulders) with outward triangles and (s, t) texture
    coordinates: s = azimuth around y (0.5 = facing forward), t = polar angle from the top."""
    centre_a, radii_a = np.asarray(centre), np.asarray(radii)
    az = np.linspace(-np.pi, np.pi, n_az + 1)[:-1]
    pol = np.linspace(0.05, np.pi - 0.05, n_pol)
    unit = np.stack([np.sin(pol)[:, None] * np.sin(az)[None, :],
                     np.cos(pol)[:, None] * np.ones_like(az)[None, :],
                     np.sin(pol)[:, None] * np.cos(az)[None, :]], -1).reshape(-1, 3)
    v = centre_a + unit * radii_a
    tri = _grid_triangles(pol.size, az.size, wrap=True)
    tri = _orient(v, tri, unit[tri[:, 0]])
    st = np.stack(np.broadcast_arrays((az[None, :] + np.pi) / (2 * np.pi),
                                      pol[:, None] / np.pi), -1).reshape(-1, 2)
    return _Part(v, _normals(v, tri), Atlas.material_uv(material, st), tri, False)


def _neck() -> _Part:
    az = np.linspace(-np.pi, np.pi, 25)[:-1]
    ys = np.linspace(-40.0, -250.0, 8)
    unit = np.stack([np.sin(az), np.zeros_like(az), np.cos(az)], -1)
    v = (np.array([0.0, 0.0, -100.0]) + unit * np.array([47.0, 0.0, 40.0]))[None, :, :].repeat(
        ys.size, 0)
    v[..., 1] = ys[:, None]
    v = v.reshape(-1, 3)
    tri = _grid_triangles(ys.size, az.size, wrap=True)
    tri = _orient(v, tri, np.tile(unit, (ys.size, 1))[tri[:, 0]])
    st = np.stack(np.broadcast_arrays((az[None, :] + np.pi) / (2 * np.pi),
                                      (ys[:, None] + 40.0) / -210.0), -1).reshape(-1, 2)
    return _Part(v, _normals(v, tri), Atlas.material_uv("neck", st), tri, False)


@lru_cache(maxsize=1)
def _static_parts() -> tuple[_Part, ...]:
    """Upper teeth, lower teeth (at rest), then the parts behind the face: head, ears, neck,
    shoulders."""
    return (
        _teeth(lower=False),
        _teeth(lower=True),
        _ellipsoid((0.0, 30.0, -118.0), (80.0, 114.0, 80.0), "head"),
        _ellipsoid((74.0, 18.0, -100.0), (9.0, 28.0, 16.0), "ear", 12, 8),
        _ellipsoid((-74.0, 18.0, -100.0), (9.0, 28.0, 16.0), "ear", 12, 8),
        _neck(),
        _ellipsoid((0.0, -215.0, -95.0), (190.0, 70.0, 90.0), "shirt", 24, 10),
    )


TEETH_LIGHT = 0.62
"""Light reaching the teeth relative to the face (the lips and cheeks shadow them)."""
CAVITY_T = np.array([0.0, 0.05, 0.3, 0.8, 1.0])
"""Texture depth coordinate of the lip rim, cavity rings and back point."""


def _cavity(points: np.ndarray, inner: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cavity rings below/behind the inner contour (M,3) -> vertices (3M+1, 3), uv, triangles.

    Triangle indices refer to ``[inner contour (M) | new vertices]``.
    """
    p0 = points[inner]
    m = p0.shape[0]
    centre = p0.mean(0)
    up = np.sign(np.sin(2 * np.pi * np.arange(m) / m))[:, None]
    r1 = p0 + np.array([0.0, 0.0, -3.0])
    r2 = np.column_stack([centre[0] + (p0[:, 0] - centre[0]) * 1.1,
                          p0[:, 1] + 12.0 * up[:, 0] * np.abs(np.sin(2 * np.pi * np.arange(m) / m)),
                          np.full(m, -8.0)])
    r3 = np.column_stack([centre[0] + (r2[:, 0] - centre[0]) * 0.8,
                          centre[1] + (r2[:, 1] - centre[1]) * 0.8, np.full(m, -32.0)])
    back = np.array([[centre[0], centre[1], -38.0]])
    v = np.concatenate([r1, r2, r3, back])
    s = np.arange(m) / m
    st = np.concatenate([np.column_stack([s, np.full(m, CAVITY_T[k])]) for k in (1, 2, 3)]
                        + [np.array([[0.75, 1.0]])])
    tri = _grid_triangles(4, m, wrap=True)  # rings 0..3 (ring 0 = inner contour)
    b = 4 * m
    fan = np.stack([3 * m + np.arange(m), 3 * m + (np.arange(m) + 1) % m, np.full(m, b)], 1)
    return v, Atlas.material_uv("cavity", st), np.concatenate([tri, fan])


def build_scene(geom: SpeakerGeometry, points: np.ndarray, controls: np.ndarray,
                skin_uv: np.ndarray) -> Scene:
    """Scene of one frame.

    points : (N, 3) articulated model points (head frame, mm); controls : (7,) that produced
    them (for the jaw's rigid motion of the lower teeth); skin_uv : (N, 2) atlas px.
    """
    upper, lower, *behind = _static_parts()
    rot, t = jaw_transform(geom, controls)
    lower_v = lower.vertices @ rot.T + t
    lower_n = lower.normals @ rot.T
    skin_tri = geom.triangles.astype(np.int64)
    skin_n = _normals(points, skin_tri)
    inner = np.arange(N_ANGLES)  # ring 0
    cav_v, cav_uv, cav_tri = _cavity(points, inner)
    n = points.shape[0]
    # cavity triangles: index < M -> inner contour point, else new vertex (offset by n - M)
    cav_tri = np.where(cav_tri < N_ANGLES, cav_tri, cav_tri - N_ANGLES + n)
    cav_n = np.zeros_like(cav_v)
    cav_n[:, 2] = 1.0
    parts = [(cav_v, cav_n, cav_uv, None, True, 0.8),
             (upper.vertices, upper.normals, upper.uv, upper.triangles, True, TEETH_LIGHT),
             (lower_v, lower_n, lower.uv, lower.triangles, True, TEETH_LIGHT),
             *((p.vertices, p.normals, p.uv, p.triangles, False, 1.0) for p in behind)]
    verts, norms, uvs, tris, culls, two = [points], [skin_n], [skin_uv], [skin_tri], [], []
    occ = [np.ones(n)]
    culls.append(np.ones(skin_tri.shape[0], bool))
    two.append(np.zeros(n, bool))
    offset = n
    for v, nn, uv, tri, two_sided, light in parts:
        occ.append(np.full(v.shape[0], light))
        tri = cav_tri if tri is None else tri + offset
        verts.append(v)
        norms.append(nn)
        uvs.append(uv)
        tris.append(tri)
        culls.append(np.full(tri.shape[0], not two_sided))
        two.append(np.full(v.shape[0], two_sided))
        offset += v.shape[0]
    anchor = np.stack([points[inner].mean(0), points[0], points[N_ANGLES // 2]])
    return Scene(np.concatenate(verts), np.concatenate(norms), np.concatenate(uvs),
                 np.concatenate(tris), np.concatenate(culls), np.concatenate(two),
                 np.concatenate(occ), anchor)

"""Procedural geometry of the built-in synthetic speaker and its non-linear articulation.

The face is a polar grid around the mouth: ring 0 is the inner lip contour, ring 1 the
lip-contouring beads (mid-vermilion), ring 2 the outer lip contour, rings 3.. are skin, out to
an outline running over the eyes, the cheeks and under the jaw to the throat. The neutral
surface is a smooth height field (:mod:`articast.core.synthetic.surface`: lips, nose, chin,
nasolabial
folds, jaw border with the under-jaw drop). Extra points: lower incisor edges
(``lower_teeth``), eye centres and the head rotation centre (in ``rest``, not triangulated).

Frame: head frame of :mod:`articast.core.model.face` (mm, x speaker's left, y up, z forward,
origin at the
upper incisor edge on the bite plane).

Controls (dimensionless, 0 = rest, order of :data:`articast.core.model.face.PARAM_NAMES`):

=====  ==================================================================================
jaw1   jaw rotation about a hinge 80 mm behind and 20 mm above the incisors; 1 = 7 deg open
lips1  +1 spreads the corners ~2 mm each, lips back ~2 mm; -1 rounds: corners ~6 mm in, 5 mm out
lips2  +1 raises the lower lip 4 mm at its middle (relative to the jaw)
lips3  +1 lowers the upper lip 3.5 mm at its middle
lips4  +1 raises the corners 4.5 mm and pulls them out 1.5 mm (smile), cheeks bulge
jaw2   +1 advances the jaw 2.5 mm
lar1   +1 raises the throat 5 mm
=====  ==================================================================================

:func:`articulate` is deliberately non-linear (rotation, sliding along the curved face,
asymmetric rounding/spreading, lip contact, speaker asymmetries), so a linear model built from
a corpus of it is an approximation, as for a real speaker.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from types import MappingProxyType

import numpy as np

from articast.core.errors import InputError
from articast.core.model.face import PARAM_NAMES
from articast.core.synthetic.surface import (
    arch_z,
    jaw_border_y,
    nasolabial_distance,
    neutral_height,
    smooth_step,
    softplus,
)

N_ANGLES = 32
"""Samples around the mouth (index 0 = speaker's left corner, counter-clockwise from +z)."""
LIP_RINGS = 3
"""Rings 0 (inner contour), 1 (beads), 2 (outer contour)."""
SKIN_T = np.array([0.035, 0.08, 0.14, 0.22, 0.32, 0.45, 0.6, 0.78, 1.0])
"""Fractions of the way from the outer lip contour to the face outline of the skin rings."""
N_RINGS = LIP_RINGS + SKIN_T.size
HINGE_YZ = (20.0, -80.0)
"""Jaw hinge axis (parallel to x), mm in the head frame."""
JAW_DEG_PER_UNIT = 7.0
LOWER_TEETH_X = np.array([-17.0, -10.0, -3.5, 3.5, 10.0, 17.0])
LIPS2_MM, LIPS3_MM, LIPS4_MM = 4.0, 3.5, 4.5


# ---------------------------------------------------------------- the speaker
@dataclass(frozen=True, eq=False)
class SpeakerGeometry:
    """The synthetic speaker's points, mesh, labels and articulation weights.

    neutral : (N, 3) float64 mm head frame (rest posture, controls = 0).
    uv : (N, 2) float64, the neutral (x, y) in mm, used as skin texture coordinates.
    triangles : (T, 3) int32, skin mesh, counter-clockwise seen from +z.
    ring, angle : (N,) grid ring index (-1 off the grid) and polar angle (rad) of each point.
    weights : name -> (N,) float64 articulation weights (see :func:`articulate`).
    pairs : (P, 2) int64 (upper, lower) point pairs facing each other across the mouth.
    quirks : (6,) speaker idiosyncrasies drawn from the seed (see :func:`make_geometry`).
    """

    neutral: np.ndarray
    uv: np.ndarray
    point_names: tuple[str, ...]
    groups: Mapping[str, np.ndarray]
    triangles: np.ndarray
    feature_points: Mapping[str, int]
    ring: np.ndarray
    angle: np.ndarray
    weights: Mapping[str, np.ndarray]
    pairs: np.ndarray
    quirks: np.ndarray
    fapu_overrides: Mapping[str, float] = field(default_factory=dict)
    seed: int = 0

    @property
    def n_points(self) -> int:
        return int(self.neutral.shape[0])

    def grid_index(self, ring: int, i: int) -> int:
        """Point index of grid ring ``ring`` at angle sample ``i`` (mod N_ANGLES)."""
        return ring * N_ANGLES + i % N_ANGLES

    def articulate(self, controls: np.ndarray) -> np.ndarray:
        """See :func:`articulate`."""
        return articulate(self, controls)


def _outline(theta: np.ndarray) -> np.ndarray:
    """Face outline (x, y) mm at polar angle theta: over the eyes, under the jaw to the throat."""
    s, c = np.sin(theta), np.cos(theta)
    x = c * (68.0 + 7.0 * s)
    y = np.where(s >= 0, 72.0 * s, -105.0 * np.abs(s) ** 1.1)
    return np.stack([x, y], -1)


def _lip_rings(theta: np.ndarray) -> np.ndarray:
    """(3, M, 2) neutral (x, y) of the inner contour, beads and outer contour."""
    s, c = np.sin(theta), np.cos(theta)
    cx = np.sign(c) * np.abs(c) ** 0.8
    up = s > 0
    inner = np.stack([24.0 * cx, 0.2 * s], -1)
    xo = 26.5 * cx
    bow = 1.2 * np.exp(-((xo / 3.0) ** 2)) - 0.8 * np.exp(-(((np.abs(xo) - 6.0) / 3.0) ** 2))
    yo_up = (8.5 - bow) * np.abs(s) ** 0.75
    yo_low = -10.5 * np.abs(s) ** 0.85
    outer = np.stack([xo, np.where(up, yo_up, yo_low)], -1)
    beads = np.stack([25.2 * cx, 0.5 * (inner[:, 1] + outer[:, 1])], -1)
    return np.stack([inner, beads, outer])


def make_geometry(seed: int = 0) -> SpeakerGeometry:
    """Build the speaker (deterministic in ``seed``; cached)."""
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    return _make_geometry(int(seed))


@lru_cache(maxsize=8)
def _make_geometry(seed: int) -> SpeakerGeometry:
    rng = np.random.default_rng([seed, 0x5EED])
    m = N_ANGLES
    theta = 2 * np.pi * np.arange(m) / m
    lips = _lip_rings(theta)
    outer, outline = lips[2], _outline(theta)
    skin = outer[None] + SKIN_T[:, None, None] * (outline - outer)[None]
    xy = np.concatenate([lips, skin]).reshape(-1, 2)  # (N_RINGS*M, 2)
    ring = np.repeat(np.arange(N_RINGS), m)
    ang = np.tile(theta, N_RINGS)
    # smooth seeded idiosyncrasy of the neutral face: a little asymmetry of the lips and cheeks
    asym = rng.normal(0.0, 1.0, 4)
    xy[:, 1] += 0.6 * asym[0] * np.tanh(xy[:, 0] / 25.0) * np.exp(-((xy[:, 1] / 30.0) ** 2))
    xy[:, 0] += 0.5 * asym[1] * np.exp(-((xy[:, 0] / 40.0) ** 2 + (xy[:, 1] / 40.0) ** 2))
    z = neutral_height(xy[:, 0], xy[:, 1])
    z += 0.8 * asym[2] * np.tanh(xy[:, 0] / 40.0) * np.exp(-((xy[:, 1] / 50.0) ** 2))
    z[ring == 0] -= 2.5  # the inner contour rolls in behind the vermilion
    z[ring == 1] += 0.6
    grid = np.column_stack([xy, z])

    teeth = np.column_stack([LOWER_TEETH_X, np.full(6, -0.6), arch_z(LOWER_TEETH_X) - 1.8])
    eyes = np.array([[32.0, 52.0, 0.0], [-32.0, 52.0, 0.0]])
    eyes[:, 2] = neutral_height(eyes[:, 0], eyes[:, 1]) + 2.0
    centre = np.array([[0.0, 12.0, -95.0]])
    neutral = np.concatenate([grid, teeth, eyes, centre])
    n = neutral.shape[0]
    uv = neutral[:, :2].copy()

    ring_all = np.concatenate([ring, np.full(n - ring.size, -1)])
    ang_all = np.concatenate([ang, np.zeros(n - ang.size)])

    names = [f"{('inner', 'bead', 'outer')[r] if r < LIP_RINGS else f'skin{r - LIP_RINGS}'}"
             f"_{i:02d}" for r, i in zip(ring, np.tile(np.arange(m), N_RINGS), strict=True)]
    names += [f"lower_tooth_{k}" for k in range(6)] + ["eye_left", "eye_right", "head_centre"]

    # ---- groups
    idx = np.arange(ring.size)
    lip = idx[ring < LIP_RINGS]
    s = np.sin(ang)
    jaw_line = []
    for i in range(m):
        if np.sin(theta[i]) < -0.05 or abs(np.cos(theta[i])) > 0.99:
            cand = idx[(ang == theta[i]) & (ring >= LIP_RINGS + 2)]
            above = grid[cand, 1] - jaw_border_y(grid[cand, 0])  # on the mandible, not under it
            err = np.where(above >= 0.0, above, 1e3 - above)
            jaw_line.append(int(cand[np.argmin(err)]))
    jaw_line_arr = np.array(sorted(set(jaw_line)))
    teeth_idx = np.arange(ring.size, ring.size + 6)
    groups = {
        "jaw_line": jaw_line_arr,
        "lower_teeth": teeth_idx,
        "lip_inner": idx[ring == 0],
        "lip_outer": idx[ring == 2],
        "lip_beads": idx[ring == 1],
        "upper_lip": lip[s[lip] > 1e-9],
        "lower_lip": lip[s[lip] < -1e-9],
    }
    used = np.concatenate([jaw_line_arr, teeth_idx, lip])
    groups["rest"] = np.setdiff1d(np.arange(n), used)

    # ---- triangles: quads between consecutive rings, oriented counter-clockwise from +z
    r_, i_ = np.meshgrid(np.arange(N_RINGS - 1), np.arange(m), indexing="ij")
    a = (r_ * m + i_).ravel()
    b = (r_ * m + (i_ + 1) % m).ravel()
    c, d = b + m, a + m
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    p = neutral[:, :2]
    e1, e2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tri[area < 0] = tri[area < 0][:, ::-1]

    fp = {
        "2.2": 8, "2.3": 24, "2.4": 0, "2.5": 16, "2.6": 4, "2.7": 12, "2.8": 28, "2.9": 20,
        "8.1": 2 * m + 8, "8.2": 2 * m + 24, "8.3": 2 * m, "8.4": 2 * m + 16,
        "8.5": 2 * m + 4, "8.6": 2 * m + 12, "8.7": 2 * m + 28, "8.8": 2 * m + 20,
        "3.5": n - 3, "3.6": n - 2, "7.1": n - 1,
    }  # fmt: skip
    skin_idx = idx[ring >= LIP_RINGS]
    mid = skin_idx[np.abs(grid[skin_idx, 0]) < 8.0]
    fp["2.1"] = int(jaw_line_arr[np.argmin(np.abs(grid[jaw_line_arr, 0]))])
    fp["2.10"] = int(mid[np.argmin(np.hypot(grid[mid, 0], grid[mid, 1] + 40.0))])
    fp["9.15"] = int(mid[np.argmin(np.hypot(grid[mid, 0], grid[mid, 1] - 22.0))])

    weights = _weights(neutral, ring_all, ang_all, teeth_idx)
    upper = np.arange(1, m // 2)
    pairs = np.concatenate([np.stack([r * m + upper, r * m + (m - upper)], 1) for r in (0, 1)])
    quirks = np.array([
        rng.normal(0.0, 4.0),        # jaw lateral deviation, mm per rad of opening
        1.0 + rng.normal(0.0, 0.08),  # left smile gain
        1.0 + rng.normal(0.0, 0.08),  # right smile gain
        rng.normal(0.0, 0.04),        # spread asymmetry (left minus right, fraction)
        rng.normal(0.0, 0.3),         # lower-lip raise leaning to one side, mm per unit
        rng.normal(0.0, 0.02),        # jaw roll, rad per rad of opening
    ])
    frozen = {k: _ro(v) for k, v in weights.items()}
    return SpeakerGeometry(
        neutral=_ro(neutral), uv=_ro(uv), point_names=tuple(names),
        groups=MappingProxyType({k: _ro(v.astype(np.int64)) for k, v in groups.items()}),
        triangles=_ro(tri.astype(np.int32)), feature_points=MappingProxyType(fp),
        ring=_ro(ring_all), angle=_ro(ang_all), weights=MappingProxyType(frozen),
        pairs=_ro(pairs), quirks=_ro(quirks), fapu_overrides=MappingProxyType({"IRISD0": 11.5}),
        seed=seed,
    )


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _weights(x0: np.ndarray, ring: np.ndarray, ang: np.ndarray, teeth: np.ndarray) -> dict:
    """Per-point articulation weights (N,) from the neutral geometry."""
    x, y = x0[:, 0], x0[:, 1]
    s, c = np.sin(ang), np.cos(ang)
    on_grid = ring >= 0
    is_lip = on_grid & (ring < LIP_RINGS)
    t = np.where(ring >= LIP_RINGS, SKIN_T[np.clip(ring - LIP_RINGS, 0, None)], 0.0)
    lip_w = np.where(is_lip, 1.0, np.exp(-((t / 0.2) ** 2))) * on_grid
    mid = np.abs(s) ** 0.6
    upper = (s > 1e-9) * np.where(is_lip, 1.0, np.exp(-((t / 0.13) ** 2))) * on_grid * mid
    lower = (s < -1e-9) * np.where(is_lip, 1.0, np.exp(-((t / 0.13) ** 2))) * on_grid * mid
    corner = np.abs(c) ** 10 * np.where(is_lip, 1.0, np.exp(-((t / 0.3) ** 2))) * on_grid
    fold_s, fold_u = nasolabial_distance(x, y)
    cheek = (smooth_step(fold_s / 3.0) * np.exp(-(((fold_s - 9.0) / 9.0) ** 2))
             * smooth_step(fold_u * 5.0) * smooth_step((1.2 - fold_u) * 5.0))
    height = 3.0 + 0.25 * np.abs(x)
    jaw = smooth_step(-(y - 0.15 * np.abs(x)) / height)
    jaw *= smooth_step((y - (jaw_border_y(x) - 22.0)) / 7.0)
    lip_jaw = 0.5 * (1.0 - np.tanh(4.0 * s) / np.tanh(4.0))
    jaw = np.where(is_lip, lip_jaw, jaw)
    jaw[teeth] = 1.0
    jaw[~on_grid & ~np.isin(np.arange(x.size), teeth)] = 0.0
    throat = smooth_step((jaw_border_y(x) - 14.0 - y) / 6.0) * on_grid
    cheek_flat = (np.exp(-(((np.abs(x) - 42.0) / 14.0) ** 2 + ((y + 8.0) / 18.0) ** 2))
                  * on_grid * (1.0 - is_lip))
    return {"lip": lip_w, "upper": upper, "lower": lower, "corner": corner,
            "cheek": cheek * on_grid, "jaw": jaw, "throat": throat, "cheek_flat": cheek_flat,
            "inner": (ring == 0).astype(np.float64)}


# ---------------------------------------------------------------- articulation
def _check_controls(controls: np.ndarray) -> np.ndarray:
    c = np.asarray(controls, dtype=np.float64)
    if c.shape[-1:] != (len(PARAM_NAMES),):
        raise InputError(f"controls must end in ({len(PARAM_NAMES)},), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise InputError("controls must be finite")
    return c


def jaw_transform(geom: SpeakerGeometry, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion of the mandible: ``x' = x @ R.T + t`` for points fixed to the jaw.

    controls : (..., 7). Returns R (..., 3, 3) and t (..., 3) (mm, head frame).
    """
    c = _check_controls(controls)
    phi = np.radians(JAW_DEG_PER_UNIT) * c[..., 0]
    q = geom.quirks
    cos, sin = np.cos(phi), np.sin(phi)
    rx = np.zeros(c.shape[:-1] + (3, 3))
    rx[..., 0, 0] = 1.0
    rx[..., 1, 1], rx[..., 1, 2] = cos, sin
    rx[..., 2, 1], rx[..., 2, 2] = -sin, cos
    roll = q[5] * phi  # a little rotation about z: the chin deviates as it opens
    rz = np.zeros_like(rx)
    rz[..., 0, 0], rz[..., 0, 1] = np.cos(roll), -np.sin(roll)
    rz[..., 1, 0], rz[..., 1, 1] = np.sin(roll), np.cos(roll)
    rz[..., 2, 2] = 1.0
    rot = rz @ rx
    hinge = np.array([0.0, *HINGE_YZ])
    t = hinge - np.einsum("...ij,j->...i", rot, hinge)
    t[..., 0] += q[0] * phi
    t[..., 2] += 2.5 * c[..., 5]
    t[..., 1] -= 0.3 * c[..., 5] ** 2
    return rot, t


def articulate(geom: SpeakerGeometry, controls: np.ndarray) -> np.ndarray:
    """True geometry at ``controls``.

    controls : (..., 7) dimensionless (see module docstring).
    Returns (..., N, 3) float64 mm, head frame.
    """
    c = _check_controls(controls)
    lead = c.shape[:-1]
    c = c.reshape(-1, c.shape[-1])[:, :, None]  # (B, 7, 1)
    w = geom.weights
    q = geom.quirks
    x0 = geom.neutral
    x, y, z = (np.broadcast_to(x0[:, k], (c.shape[0], x0.shape[0])).copy() for k in range(3))
    side = np.tanh(x0[:, 0] / 6.0)  # -1 right ... +1 left
    mid = np.abs(np.sin(geom.angle))

    # lips1: asymmetric spreading/rounding; lips slide along the curved face
    s = c[:, 1]
    scale = 0.16 * s - 0.08 * s * np.tanh(2.0 * s)  # +0.08 at s=1, -0.24 at s=-1
    scale = scale * (1.0 + q[3] * side) * (1.0 + 0.5 * w["inner"] * (s < 0))  # round aperture
    x_new = x * (1.0 + w["lip"] * scale)
    rnd = softplus(-s, 0.5) - softplus(np.zeros(1), 0.5)  # +0.72 at s=-1, -0.28 at s=+1
    stretch = 1.0 / (1.0 + 0.3 * np.clip(c[:, 0], 0, None))  # an open jaw limits protrusion
    z = z + (x**2 - x_new**2) / (2 * 48.0) * w["lip"]
    z = z + 7.0 * rnd * stretch * w["lip"] * (0.6 + 0.4 * mid)
    y = y + np.sign(y) * 0.8 * np.clip(rnd, 0, None) * w["inner"] * mid
    x = x_new

    # lips2 / lips3: lower lip up, upper lip down (with a little eversion)
    l2, l3 = 3.0 * np.tanh(c[:, 2] / 3.0), 3.0 * np.tanh(c[:, 3] / 3.0)  # tissue saturates
    y = y + (LIPS2_MM + q[4] * side) * l2 * w["lower"] - LIPS3_MM * l3 * w["upper"]
    z = z - 0.6 * l2 * w["lower"] - 0.6 * l2 * np.abs(l2) * w["lower"] + 0.6 * l3 * w["upper"]
    # the lower lip thins and tucks in as the jaw opens wide (tissue stretch)
    z = z - 0.35 * np.clip(c[:, 0], 0, None) ** 2 * w["lower"]
    y = y + 0.3 * np.clip(c[:, 0], 0, None) ** 2 * w["lower"] * w["inner"]

    # lips4: corners up and out, cheeks bulge beside the nasolabial fold
    l4 = c[:, 4]
    gain = np.where(x0[:, 0] >= 0, q[1], q[2])
    y = y + LIPS4_MM * l4 * w["corner"] * gain
    x = x + 1.5 * l4 * w["corner"] * np.sign(x0[:, 0]) * gain
    z = z + (2.5 * softplus(l4, 0.6) - 2.5 * softplus(np.zeros(1), 0.6)) * w["cheek"]
    z = z - 0.8 * l4 * w["corner"]

    # spreading thins the lips (they stretch over the teeth); an open jaw flattens the cheeks
    y = y - 0.06 * np.clip(s, 0, None) ** 2 * (y - 0.0) * (geom.ring[None, :] >= 0) * w["lip"]
    z = z - (0.5 * np.clip(c[:, 0], 0, None) ** 2 + 0.8 * rnd**2) * w["cheek_flat"]

    # jaw: each point rotates by its weight's share of the jaw angle (skin stretches)
    phi = np.radians(JAW_DEG_PER_UNIT) * c[:, 0] * w["jaw"]
    hy, hz = HINGE_YZ
    dy, dz = y - hy, z - hz
    cos, sin = np.cos(phi), np.sin(phi)
    y, z = hy + dy * cos - dz * sin, hz + dy * sin + dz * cos
    x = x + (q[0] * phi) - q[5] * phi * (y - hy)
    z = z + 2.5 * c[:, 5] * w["jaw"]
    y = y - 0.3 * c[:, 5] ** 2 * w["jaw"]  # the condyles slide down the eminence

    # lar1: the throat rises and goes back a little
    y = y + 5.0 * 1.5 * np.tanh(c[:, 6] / 1.5) * w["throat"]
    z = z - 1.0 * c[:, 6] * w["throat"] + 1.2 * c[:, 6] ** 2 * w["throat"]  # larynx bulges

    out = np.stack([x, y, z], -1)
    # lower teeth are rigid with the jaw
    teeth = geom.groups["lower_teeth"]
    rot, t = jaw_transform(geom, c[:, :, 0])
    out[:, teeth] = np.einsum("bij,nj->bni", rot, x0[teeth]) + t[:, None, :]
    _lip_contact(out, geom.pairs)
    return out.reshape(lead + out.shape[1:])


def _lip_contact(points: np.ndarray, pairs: np.ndarray, k: float = 0.3) -> None:
    """Lips cannot cross: a soft floor (softplus, ``k`` mm) on the gap of facing points.

    points : (B, N, 3) modified in place; pairs : (P, 2) upper/lower indices.
    """
    up, lo = pairs[:, 0], pairs[:, 1]
    gap = points[:, up, 1] - points[:, lo, 1]
    centre = 0.5 * (points[:, up, 1] + points[:, lo, 1])
    gap = softplus(gap, k)
    points[:, up, 1] = centre + 0.5 * gap
    points[:, lo, 1] = centre - 0.5 * gap

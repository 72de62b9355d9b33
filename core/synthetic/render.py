"""Software renderer of the synthetic speaker: z-buffered, textured, Gouraud-lit triangles.

Scene (head frame, mm): the articulated model mesh (skin, lips), the mouth cavity hanging
from the inner lip contour, upper teeth fixed to the head, lower teeth moving rigidly with the
jaw, and a head ellipsoid and neck behind the face so it does not float; a textured wall
behind everything. Vertices are posed (:class:`articast.core.model.camera.Pose`) and projected with
:class:`articast.core.model.camera.Camera` (distortion included, per vertex); triangles are
rasterised in
numpy, vectorised per row span, with a real depth test on 1/z. Attributes (texture
coordinates and light) are interpolated perspective-correctly; light is ambient + Lambert on
smooth per-vertex normals.

Output: (H, W, 3) uint8 BGR, OpenCV convention. Deterministic for given inputs and seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.errors import InputError
from articast.core.model.camera import Camera, Pose
from articast.core.synthetic.scene import Scene

OCCLUDERS = ("none", "hand", "black")
NEAR_MM = 20.0


@dataclass(frozen=True)
class RenderOptions:
    """How to render a frame.

    noise_sigma : s.d. of additive Gaussian sensor noise, grey levels (per channel).
    blur_sigma : Gaussian blur (optics/defocus), px; 0 = sharp.
    gain : global gain applied to the whole image (exposure), 1 = nominal.
    light_azimuth_deg, light_elevation_deg : direction *towards* the light in the camera
        frame: 0/0 = from the camera, positive azimuth from the image's right, positive
        elevation from above. Vary them over frames for illumination drift.
    ambient, diffuse : light terms (intensity = ambient + diffuse * max(0, n.l)).
    occluder : "none", "hand" (a skin-coloured blob over the mouth) or "black" (a black frame).
    occluder_shift : (dx, dy) displacement of the hand from the mouth centre, in mouth widths.
    seed : noise seed; the same seed gives the same image.
    background : draw the textured wall (False: black background).
    """

    noise_sigma: float = 2.0
    blur_sigma: float = 0.0
    gain: float = 1.0
    light_azimuth_deg: float = -20.0
    light_elevation_deg: float = 25.0
    ambient: float = 0.45
    diffuse: float = 0.7
    occluder: str = "none"
    occluder_shift: tuple[float, float] = (0.0, 0.0)
    seed: int = 0
    background: bool = True

    def __post_init__(self) -> None:
        for name in ("noise_sigma", "blur_sigma", "gain", "ambient", "diffuse"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise InputError(f"RenderOptions.{name} must be finite and >= 0, got {v!r}")
        for name in ("light_azimuth_deg", "light_elevation_deg"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(f"RenderOptions.{name} must be finite")
        if self.occluder not in OCCLUDERS:
            raise InputError(f"occluder must be one of {OCCLUDERS}, got {self.occluder!r}")
        if len(self.occluder_shift) != 2 or not np.all(np.isfinite(self.occluder_shift)):
            raise InputError("occluder_shift must be two finite numbers")
        if int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"seed must be a non-negative integer, got {self.seed!r}")

    def light_vector(self) -> np.ndarray:
        """(3,) unit vector towards the light, camera frame."""
        az, el = np.radians(self.light_azimuth_deg), np.radians(self.light_elevation_deg)
        return np.array([np.sin(az) * np.cos(el), -np.sin(el), -np.cos(az) * np.cos(el)])


# ---------------------------------------------------------------- rasteriser
def rasterize(xy: np.ndarray, inv_z: np.ndarray, triangles: np.ndarray, cull: np.ndarray,
              width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Visible triangle per pixel, with a depth test on 1/z.

    xy : (V, 2) px image coordinates (pixel centres at integers). inv_z : (V,) 1/mm, camera
    depth inverse (> 0 in front). triangles : (T, 3) int. cull : (T,) bool, True to drop the
    triangle when it faces away (counter-clockwise from the front in the head frame is
    clockwise in the y-down image).
    Returns ids (H, W) int32 (-1 where empty) and inverse depth (H, W) float64 (0 where empty).
    """
    tri = np.asarray(triangles)
    p = xy[tri]  # (T, 3, 2)
    w = inv_z[tri]
    x0, y0 = p[:, 0, 0], p[:, 0, 1]
    x1, y1 = p[:, 1, 0], p[:, 1, 1]
    x2, y2 = p[:, 2, 0], p[:, 2, 1]
    with np.errstate(invalid="ignore"):
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        ok = np.isfinite(area) & (np.abs(area) > 1e-9) & np.all(w > 0, 1)
        ok &= ~np.asarray(cull, bool) | (area < 0)
        ymin = np.ceil(np.fmin(np.fmin(y0, y1), y2))
        ymax = np.floor(np.fmax(np.fmax(y0, y1), y2))
        xmin = np.ceil(np.fmin(np.fmin(x0, x1), x2))
        xmax = np.floor(np.fmax(np.fmax(x0, x1), x2))
        ymin, xmin = np.maximum(ymin, 0), np.maximum(xmin, 0)
        ymax, xmax = np.minimum(ymax, height - 1), np.minimum(xmax, width - 1)
        ok &= (ymax >= ymin) & (xmax >= xmin)
    ids = np.full(height * width, -1, np.int32)
    zbuf = np.zeros(height * width)
    t = np.flatnonzero(ok)
    if t.size == 0:
        return ids.reshape(height, width), zbuf.reshape(height, width)
    sig = np.sign(area[t])
    vx, vy = p[t, :, 0], p[t, :, 1]  # (T', 3)
    dx, dy = np.roll(vx, -1, 1) - vx, np.roll(vy, -1, 1) - vy
    a_e, b_e = -sig[:, None] * dy, sig[:, None] * dx  # inside: a x + b y + c >= 0
    c_e = -sig[:, None] * (-vx * dy + vy * dx)
    wa, wb, wc = _plane(vx, vy, w[t], area[t])
    # each edge bounds the span of a row from the left (a > 0) or the right (a < 0):
    # x >= m y + q or x <= m y + q; horizontal edges never cut a row inside the bounding box
    with np.errstate(divide="ignore", invalid="ignore"):
        m_e, q_e = -b_e / a_e, -c_e / a_e
    left, right = a_e > 0, a_e < 0
    m_lo, q_lo = np.where(left, m_e, 0.0), np.where(left, q_e - 1e-7, -1e9)
    m_hi, q_hi = np.where(right, m_e, 0.0), np.where(right, q_e + 1e-7, 1e9)
    # rows
    ny = (ymax[t] - ymin[t] + 1).astype(np.int64)
    start = np.cumsum(ny) - ny
    rt = np.repeat(np.arange(t.size), ny)
    ry = np.repeat(ymin[t] - start, ny) + np.arange(rt.size)
    lo_k = m_lo[rt] * ry[:, None] + q_lo[rt]
    hi_k = m_hi[rt] * ry[:, None] + q_hi[rt]
    lo = np.maximum(np.maximum(lo_k[:, 0], lo_k[:, 1]), lo_k[:, 2])
    hi = np.minimum(np.minimum(hi_k[:, 0], hi_k[:, 1]), hi_k[:, 2])
    xs = np.maximum(np.ceil(lo), xmin[t][rt])
    xe = np.minimum(np.floor(hi), xmax[t][rt])
    n = np.maximum(xe - xs + 1, 0).astype(np.int64)
    # pixels, in chunks of rows so that a face filling the view from very close cannot ask for
    # an unbounded amount of memory; one chunk in normal use
    ends = np.cumsum(n)
    cuts = np.searchsorted(ends, np.arange(MAX_SPAN_PIXELS, ends[-1], MAX_SPAN_PIXELS))
    bounds = np.unique(np.concatenate([[0], cuts + 1, [n.size]]))
    chunks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    spans = (ry, xs, n, wa[rt], wb[rt] * ry + wc[rt])
    done = []
    for c in chunks:  # pass 1: nearest 1/z per pixel
        pid, depth = _span_pixels(width, *(a[c] for a in spans))
        np.maximum.at(zbuf, pid, depth)
        done.append((pid, depth) if len(chunks) == 1 else None)
    for c, kept in zip(chunks, done, strict=True):  # pass 2: who is the nearest
        pid, depth = kept or _span_pixels(width, *(a[c] for a in spans))
        win = depth >= zbuf[pid]
        ids[pid[win]] = np.repeat(t[rt[c]], n[c])[win]
    return ids.reshape(height, width), zbuf.reshape(height, width)


MAX_SPAN_PIXELS = 4_000_000
"""Largest number of candidate pixels rasterised at once (bounds memory)."""


def _span_pixels(width: int, ry: np.ndarray, xs: np.ndarray, n: np.ndarray,
                 slope: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index and 1/z of every pixel of row spans.

    Span r covers pixels xs[r] .. xs[r] + n[r] - 1 of image row ry[r], where 1/z is
    slope[r] * x + offset[r].
    """
    pstart = np.cumsum(n) - n
    g = np.arange(int(n.sum()))
    pid = np.repeat((ry * width + xs - pstart).astype(np.int64), n) + g
    depth = np.repeat(slope * (xs - pstart) + offset, n) + np.repeat(slope, n) * g
    return pid, depth


def _plane(vx: np.ndarray, vy: np.ndarray, f: np.ndarray, area: np.ndarray):
    """Coefficients (a, b, c) with f = a x + b y + c through a triangle's 3 vertices.

    vx, vy : (T, 3); f : (T, 3) or (T, 3, A); area : (T,) twice the signed area.
    """
    if f.ndim == 3:
        vx, vy, area = vx[..., None], vy[..., None], area[:, None]
    df1, df2 = f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]
    dx1, dx2 = vx[:, 1] - vx[:, 0], vx[:, 2] - vx[:, 0]
    dy1, dy2 = vy[:, 1] - vy[:, 0], vy[:, 2] - vy[:, 0]
    a = (df1 * dy2 - df2 * dy1) / area
    b = (df2 * dx1 - df1 * dx2) / area
    return a, b, f[:, 0] - a * vx[:, 0] - b * vy[:, 0]


# ---------------------------------------------------------------- shading
def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a mesh (outward = counter-clockwise side)."""
    p = points[triangles]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    acc = np.zeros_like(points)
    for k in range(3):
        for d in range(3):
            acc[:, d] += np.bincount(triangles[:, k], fn[:, d], minlength=points.shape[0])
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return acc / np.where(norm > 0, norm, 1.0)


def shade_scene(scene: Scene, pose: Pose, camera: Camera, options: RenderOptions,
                atlas: np.ndarray) -> tuple[tuple[slice, slice], np.ndarray, np.ndarray]:
    """Render a scene without background, occluder, blur, gain or noise.

    Returns the region of interest (row slice, column slice) of the image that the scene
    touches, its colour (h, w, 3) float32 BGR and its mask (h, w) bool (True where covered).
    """
    rot = pose.matrix
    cam_pts = scene.vertices @ rot.T + pose.translation
    normals = scene.normals @ rot.T
    flip = np.einsum("ij,ij->i", normals, -cam_pts) < 0
    normals[flip & scene.two_sided_vertex] *= -1.0
    light = options.light_vector()
    intensity = options.ambient + options.diffuse * np.clip(normals @ light, 0.0, None)
    intensity *= scene.occlusion
    xy, inv_z = _project(cam_pts, camera)
    ids, _ = rasterize(xy, inv_z, scene.triangles, scene.cull, camera.width, camera.height)
    covered = ids >= 0
    rows, cols = np.flatnonzero(covered.any(1)), np.flatnonzero(covered.any(0))
    if rows.size == 0:
        return (slice(0, 0), slice(0, 0)), np.zeros((0, 0, 3), np.float32), covered[:0, :0]
    roi_slices = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    roi = ids[roi_slices]
    mask = roi >= 0
    tri = scene.triangles
    vx, vy = xy[tri, 0], xy[tri, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        area = ((vx[:, 1] - vx[:, 0]) * (vy[:, 2] - vy[:, 0])
                - (vx[:, 2] - vx[:, 0]) * (vy[:, 1] - vy[:, 0]))
        wv = inv_z[tri]
        attrs = np.concatenate([scene.uv[tri], intensity[tri][..., None]], -1)
        f = np.concatenate([wv[..., None], attrs * wv[..., None]], -1)  # (T, 3, 4): w, uw, vw, Iw
        planes = _plane(vx, vy, f, area)
    # Per-pixel plane coefficients: a nearest-neighbour lookup of a (1, T + 1) 4-channel table
    # indexed by triangle id, done by cv2.remap (far faster than numpy fancy indexing).
    # Entry T (empty pixels) gives w = 1 and zero attributes.
    table_x = np.where(mask, roi, tri.shape[0]).astype(np.float32)
    table_y = np.zeros_like(table_x)
    gx, gy = _pixel_grid(camera.width, camera.height)
    val = None
    for q, coord in zip(planes, (gx[roi_slices], gy[roi_slices], None), strict=True):
        table = np.zeros((1, tri.shape[0] + 1, 4), np.float32)
        table[0, :-1] = np.nan_to_num(q)
        if coord is None:
            table[0, -1, 0] = 1.0
        g = cv2.remap(table, table_x, table_y, cv2.INTER_NEAREST)
        if coord is not None:
            g *= coord[..., None]
        val = g if val is None else val + g
    w = val[..., 0]
    w[~mask] = 1.0
    mapx = np.ascontiguousarray(val[..., 1] / w)
    mapy = np.ascontiguousarray(val[..., 2] / w)
    light_img = val[..., 3] / w
    tex = cv2.remap(atlas, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    colour = tex.astype(np.float32) * light_img[..., None]
    return roi_slices, colour, mask


def _project(cam_pts: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame vertices (V, 3) -> pixels (V, 2) (NaN behind the near plane), 1/z (V,)."""
    z = cam_pts[:, 2]
    front = z > NEAR_MM
    inv_z = np.where(front, 1.0 / np.where(front, z, 1.0), -1.0)
    return camera.project(np.where(front[:, None], cam_pts, np.nan)), inv_z


def visible_points(scene: Scene, points: np.ndarray, pose: Pose, camera: Camera,
                   tolerance: float = 0.01) -> np.ndarray:
    """Which head-frame points (M, 3) are seen by the camera (not hidden, inside the image).

    A point is visible when the nearest surface at its pixel is no nearer than the point
    itself (relative depth ``tolerance``). Points on hidden parts of the mesh (the lower teeth
    behind the lips, the far cheek of a turned head) are not. Returns (M,) bool.
    """
    xy, inv_z = _project(scene.vertices @ pose.matrix.T + pose.translation, camera)
    _, zbuf = rasterize(xy, inv_z, scene.triangles, scene.cull, camera.width, camera.height)
    p_xy, p_inv = _project(pose.transform(np.asarray(points, np.float64)), camera)
    inside = camera.inside(p_xy) & (p_inv > 0)
    px = np.clip(np.round(np.nan_to_num(p_xy)).astype(np.int64), 0,
                 [camera.width - 1, camera.height - 1])
    nearest = zbuf[px[:, 1], px[:, 0]]
    return inside & (p_inv * (1.0 + tolerance) >= nearest)


def _pixel_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel x and y coordinates (H, W) float32 (cached per size)."""
    key = (width, height)
    grids = _GRIDS.get(key)
    if grids is None:
        gy, gx = np.mgrid[0:height, 0:width].astype(np.float32)
        grids = (gx, gy)
        _GRIDS.clear()
        _GRIDS[key] = grids
    return grids


_GRIDS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


# ---------------------------------------------------------------- post-processing
def draw_hand(img: np.ndarray, centre: np.ndarray, mouth_width_px: float, seed: int) -> None:
    """Paint a skin-coloured hand-like blob (in place) over ``centre`` (x, y) px."""
    h, w = img.shape[:2]
    ax, ay = 1.4 * mouth_width_px, 0.8 * mouth_width_px
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r = ((xx - centre[0]) / ax) ** 2 + ((yy - centre[1]) / ay) ** 2
    # fingers: four bumps on the upper edge
    for k in range(4):
        fx = centre[0] + (k - 1.5) * 0.45 * ax
        finger = ((xx - fx) / (0.2 * ax)) ** 2 + ((yy - centre[1] + 0.6 * ay) / (0.7 * ay)) ** 2
        r = np.minimum(r, finger)
    alpha = np.clip((1.0 - r) * 6.0, 0, 1)[..., None]
    rng = np.random.default_rng([seed, 0x4A4D])
    grain = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.2)
    shade = np.clip(1.05 - 0.35 * r, 0.6, 1.1)[..., None]
    skin = np.array([125.0, 150.0, 198.0], np.float32) * shade + 6.0 * grain[..., None]
    img[:] = img * (1 - alpha) + skin * alpha


NOISE_MARGIN = 251


def _noise_bank(height: int, width: int) -> np.ndarray:
    """Unit Gaussian noise (H + margin, W + margin, 3) float32, cached per size."""
    key = (height, width)
    bank = _NOISE.get(key)
    if bank is None:  # (thread-safe: a racing thread at worst builds the same bank twice)
        rng = np.random.default_rng([height, width, 0x5E45])
        bank = rng.standard_normal((height + NOISE_MARGIN, width + NOISE_MARGIN, 3),
                                   dtype=np.float32)
        bank.setflags(write=False)
        _NOISE.clear()
        _NOISE[key] = bank
    return bank


_NOISE: dict[tuple[int, int], np.ndarray] = {}


def sensor_noise(height: int, width: int, seed: int) -> np.ndarray:
    """Unit Gaussian noise image (H, W, 3) float32 for ``seed``.

    A window of a cached noise bank at a seed-dependent offset, flipped by the seed: frames
    with different seeds get different (practically independent) noise at no cost.
    """
    bank = _noise_bank(height, width)
    rng = np.random.default_rng([seed, 0x0FF5])
    dy, dx = rng.integers(0, NOISE_MARGIN + 1, 2)
    win = bank[dy:dy + height, dx:dx + width]
    flip = rng.integers(0, 4)
    if flip & 1:
        win = win[:, ::-1]
    if flip & 2:
        win = -win
    return win


def finish(colour: np.ndarray, options: RenderOptions) -> np.ndarray:
    """Blur, gain and sensor noise on a float32 BGR image (modified) -> uint8 BGR."""
    img = colour
    if options.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), options.blur_sigma)
    if options.gain != 1.0:
        img *= np.float32(options.gain)
    if options.noise_sigma > 0:
        noise = sensor_noise(img.shape[0], img.shape[1], options.seed)
        img += noise * np.float32(options.noise_sigma)
    img += np.float32(0.5)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


def composite(scene: Scene, pose: Pose, camera: Camera, options: RenderOptions,
              atlas: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """The full frame: scene over background, occluder, blur, gain, noise -> (H, W, 3) uint8."""
    if not isinstance(options, RenderOptions):
        raise InputError("options must be a RenderOptions")
    if options.occluder == "black":
        return finish(np.zeros((camera.height, camera.width, 3), np.float32), options)
    roi, part, mask = shade_scene(scene, pose, camera, options, atlas)
    if background is not None:
        colour = background.astype(np.float32)
    else:
        colour = np.zeros((camera.height, camera.width, 3), np.float32)
    np.copyto(colour[roi], part, where=mask[..., None])
    if options.occluder == "hand":
        pts = camera.project(pose.transform(scene.mouth_anchor))
        if np.all(np.isfinite(pts)):
            width = float(np.linalg.norm(pts[1] - pts[2]))
            shift = np.asarray(options.occluder_shift) * width
            draw_hand(colour, pts[0] + shift, width, options.seed)
    return finish(colour, options)

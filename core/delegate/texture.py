"""The delegate's texture from video frames at known states, and the delegate drawn back.

METHOD.md §2 (``tex``): each frame, from the geometry at its state theta, is warped into a
fixed 2D frame, here the face mesh's own UV layout (piecewise-affine per triangle: every texel
is a fixed barycentric point of one triangle, looked up where that point projects in the
frame). The texture is modelled as linear in the articulation,

    T(alpha) = T0 + sum_k alpha_k T_k          (tex lin; T0 alone is tex cst)

fitted per texel by weighted least squares over the frames, the weight being how well the
frame sees the texel (hidden: 0; facing away or grazing: 0; facing the camera: 1).

Before the fit, **lighting is evened out**: each frame's texture is brought to the running
mean by a smooth gain field (per colour channel, log-gain affine in the texel position), so a
frame lit from the left does not paint the left cheek brighter for the articulation it
happened to have. Texels no frame saw (the far side of a face always seen from one side, the
gutter between UV islands) are **filled** by inpainting from their neighbours, and their
articulation terms are zero. The mouth opening is covered by the mesh's own inner-lip
triangles: what the camera saw between the lips (teeth, the dark cavity) is their texture, and
it comes and goes with jaw opening through the ``T_k``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.delegate.geometry import DelegateMesh
from articast.core.errors import InputError
from articast.core.model.camera import Camera, Pose
from articast.core.synthetic.render import NEAR_MM, rasterize

TEXTURE_SIZE = 256
"""Texels on a side of the delegate's texture (a 640x480 webcam face spans ~200 px)."""
MIN_WEIGHT = 2.0
"""A texel seen with less total weight (about two frames facing it) is filled, not measured."""
FULL_MODES_WEIGHT = 8.0
"""Articulation terms of texels seen with less weight than this are shrunk towards 0."""
RIDGE = 0.05
"""Ridge of the articulation terms, relative to each texel's total weight."""


@dataclass(frozen=True, eq=False)
class UVRaster:
    """Which triangle and barycentric point each covered texel is.

    size : texels on a side; texel : (P,) flat index (row-major) of each covered texel;
    tri : (P,) its triangle; bary : (P, 3) its barycentric weights; uv : (P, 2) its centre.
    """

    size: int
    texel: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    uv: np.ndarray


def uv_raster(uv: np.ndarray, triangles: np.ndarray, size: int = TEXTURE_SIZE) -> UVRaster:
    """Rasterise the UV layout: texel (i, j) has its centre at ((j + 0.5) / size,
    (i + 0.5) / size)."""
    xy = np.asarray(uv, np.float64) * size - 0.5
    ids, _ = rasterize(xy, np.ones(len(xy)), triangles, np.zeros(len(triangles), bool),
                       size, size)
    texel = np.flatnonzero(ids.ravel() >= 0)
    tri = ids.ravel()[texel]
    py, px = np.divmod(texel, size)
    bary = _barycentric(xy[triangles[tri]], np.stack([px, py], 1).astype(np.float64))
    centre = (np.stack([px, py], 1) + 0.5) / size
    return UVRaster(int(size), texel, tri.astype(np.int64), bary, centre)


def _barycentric(corners: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(P, 3) barycentric weights of 2D points p (P, 2) in triangles corners (P, 3, 2)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) > 1e-12, den, 1e-12)
    wb = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    wc = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    return np.clip(np.stack([1.0 - wb - wc, wb, wc], 1), -0.01, 1.01)


def _project(cam: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    front = cam[:, 2] > NEAR_MM
    inv_z = np.where(front, 1.0 / np.where(front, cam[:, 2], 1.0), -1.0)
    return camera.project(np.where(front[:, None], cam, np.nan)), inv_z


def sample_frame(mesh: DelegateMesh, raster: UVRaster, image: np.ndarray, alpha: np.ndarray,
                 pose: Pose, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Colours (P, 3) float32 BGR of the covered texels in ``image`` at state (alpha, pose),
    and the weight (P,) of each: 0 where the texel is hidden, outside the image or seen
    edge-on, up to 1 facing the camera."""
    if image.ndim != 3 or image.shape[:2] != (camera.height, camera.width):
        raise InputError(f"frame of shape {image.shape} for a {camera.width}x{camera.height} "
                         "camera")
    cam = pose.transform(mesh.shape(alpha))
    xy, inv_z = _project(cam, camera)
    tris = mesh.triangles
    _, zbuf = rasterize(xy, inv_z, tris, np.ones(len(tris), bool), camera.width,
                        camera.height)
    pts = np.einsum("pc,pcd->pd", raster.bary, cam[tris[raster.tri]])
    pix, p_inv = _project(pts, camera)
    inside = camera.inside(pix, 1.0) & (p_inv > 0)
    ip = np.clip(np.round(np.nan_to_num(pix)).astype(np.int64), 0,
                 [camera.width - 1, camera.height - 1])
    seen = inside & (p_inv * 1.01 >= zbuf[ip[:, 1], ip[:, 0]])
    p = cam[tris]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    view = -pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-12)
    facing = np.einsum("pd,pd->p", normal[raster.tri], view)
    weight = np.where(seen, np.clip((facing - 0.15) / 0.45, 0.0, 1.0), 0.0)
    colour = _lookup(image, np.nan_to_num(pix)).astype(np.float32)
    return colour, weight.astype(np.float32)


def _lookup(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear colours (P, 3) of ``image`` at pixel positions xy (P, 2) (cv2.remap, on a
    grid of at most 1024 columns: remap's maps are limited to 32767 a side)."""
    n = len(xy)
    cols = 1024
    rows = max(1, -(-n // cols))
    flat = np.zeros((rows * cols, 2), np.float32)
    flat[:n] = xy
    grid = flat.reshape(rows, cols, 2)
    out = cv2.remap(image, grid[..., 0], grid[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, -1)[:n]


def even_lighting(colours: np.ndarray, weights: np.ndarray, uv: np.ndarray,
                  rounds: int = 2) -> np.ndarray:
    """Each frame's colours (F, P, 3) times a smooth gain field fitted so the frame matches
    the weighted mean of all frames: per channel, log-gain = a + b u + c v (least squares over
    the texels the frame sees well). Returns the corrected colours."""
    out = colours.astype(np.float32).copy()
    design = np.c_[np.ones(len(uv)), uv - 0.5]
    for _ in range(rounds):
        ref = _weighted_mean(out, weights)
        lref = np.log(ref + 1.0)
        for f in range(len(out)):
            w = weights[f] * (weights[f] > 0.3)
            if w.sum() < 50:
                continue
            sw = np.sqrt(w)[:, None]
            lhs = design * sw
            rhs = (lref - np.log(out[f] + 1.0)) * sw
            coef, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
            out[f] = np.clip((out[f] + 1.0) * np.exp(design @ coef) - 1.0, 0.0, 255.0)
    return out


def _weighted_mean(colours: np.ndarray, weights: np.ndarray) -> np.ndarray:
    wsum = weights.sum(0)
    return np.einsum("fp,fpc->pc", weights, colours) / np.maximum(wsum, 1e-9)[:, None]


def fit_tex_lin(colours: np.ndarray, weights: np.ndarray, alphas: np.ndarray,
                use: np.ndarray, ridge: float = RIDGE) -> tuple[np.ndarray, np.ndarray]:
    """Per texel, T0 (P, 3) and T_k (K, P, 3) minimising
    sum_f w_fp |T0 + sum_k alpha_fk T_k - c_fp|^2 + ridge * W_p * sum_k |T_k|^2 (W_p the
    texel's total weight); parameters outside ``use`` (K,) bool get T_k = 0."""
    f_n, p_n, _ = colours.shape
    k_all = alphas.shape[1]
    a = alphas[:, use]
    design = np.c_[np.ones(f_n), a]  # (F, J)
    j = design.shape[1]
    outer = (design[:, :, None] * design[:, None, :]).reshape(f_n, j * j)
    lhs = (weights.T @ outer).reshape(p_n, j, j)
    wsum = weights.sum(0)
    reg = np.eye(j)
    reg[0, 0] = 0.0
    lhs += (ridge * np.maximum(wsum, 1e-6))[:, None, None] * reg + 1e-9 * np.eye(j)
    rhs = np.stack([(weights * colours[..., c]).T @ design for c in range(3)], -1)  # (P, J, 3)
    sol = np.linalg.solve(lhs, rhs)  # (P, J, 3)
    modes = np.zeros((k_all, p_n, 3))
    modes[use] = np.moveaxis(sol[:, 1:], 1, 0)
    return sol[:, 0], modes


def build_texture(mesh: DelegateMesh, frames: Sequence[tuple[np.ndarray, np.ndarray, Pose]],
                  camera: Camera, size: int = TEXTURE_SIZE, use: np.ndarray | None = None,
                  support: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texture of ``mesh`` from ``frames`` (image BGR uint8, alpha (K,), pose).

    use : (K,) bool, the parameters the texture may vary with (default: every parameter
    that moves the mesh). support : (V,) in [0, 1], how far each vertex's position can be
    trusted (default 1): a texel's weights are scaled by it, so where the surface is only
    extrapolated the texture is filled from its neighbours rather than sampled at the wrong
    place of the image. Returns T0 (S, S, 3) float32 BGR grey levels, T_k (K, S, S, 3)
    float32 grey levels per unit alpha, and the total weight each texel was seen with (S, S).
    """
    if len(frames) < 2:
        raise InputError("a delegate's texture needs frames of the speaker (at least 2)")
    raster = uv_raster(mesh.uv, mesh.triangles, size)
    samples = [sample_frame(mesh, raster, img, a, pose, camera) for img, a, pose in frames]
    colours = np.stack([s[0] for s in samples])
    weights = np.stack([s[1] for s in samples])
    if support is not None:
        sup = np.einsum("pc,pc->p", raster.bary, np.asarray(support)[mesh.triangles[raster.tri]])
        weights *= np.clip(sup, 0.0, 1.0).astype(np.float32)[None]
    alphas = np.array([np.asarray(a, np.float64) for _, a, _ in frames])
    if use is None:
        use = np.abs(mesh.modes).reshape(len(mesh.modes), -1).max(1) > 0
    colours = even_lighting(colours, weights, raster.uv)
    t0, modes = fit_tex_lin(colours, weights, alphas, np.asarray(use, bool))
    wsum = weights.sum(0)
    modes *= np.clip((wsum - MIN_WEIGHT) / (FULL_MODES_WEIGHT - MIN_WEIGHT), 0, 1)[None, :, None]
    flat = np.zeros((size * size, 3), np.float32)
    seen = wsum >= MIN_WEIGHT
    flat[raster.texel[seen]] = t0[seen]
    mask = np.ones(size * size, np.uint8)
    mask[raster.texel[seen]] = 0
    image = np.clip(flat, 0, 255).reshape(size, size, 3).astype(np.uint8)
    filled = fill_unseen(image, mask.reshape(size, size)).astype(np.float32)
    tex_modes = np.zeros((len(modes), size * size, 3), np.float32)
    tex_modes[:, raster.texel] = modes
    weight_map = np.zeros(size * size, np.float32)
    weight_map[raster.texel] = wsum
    return (filled, tex_modes.reshape(len(modes), size, size, 3),
            weight_map.reshape(size, size))


def fill_unseen(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (S, S, 3) uint8 with the texels where ``mask`` (S, S) is non-zero filled from
    their neighbours: a push-pull average over a pyramid (every hole gets the mean of its
    nearest seen surroundings, however large), then a light inpainting at the borders."""
    known = (mask == 0).astype(np.float32)
    levels = [(image.astype(np.float32) * known[..., None], known)]
    while min(levels[-1][1].shape) > 2:
        c, w = levels[-1]
        levels.append((cv2.pyrDown(c), cv2.pyrDown(w)))
    c, w = levels[-1]
    est = c / np.maximum(w, 1e-6)[..., None]
    for c, w in reversed(levels[:-1]):
        up = cv2.resize(est, (w.shape[1], w.shape[0]), interpolation=cv2.INTER_LINEAR)
        mine = c / np.maximum(w, 1e-6)[..., None]
        a = np.clip(w, 0, 1)[..., None]
        est = a * mine + (1 - a) * up
    out = np.where(known[..., None] > 0, image.astype(np.float32), est)
    return np.clip(out, 0, 255).astype(np.uint8)


def texture_at(t0: np.ndarray, modes: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """T(alpha) (S, S, 3) uint8."""
    a = np.asarray(alpha, np.float64).reshape(-1)
    return np.clip(t0 + np.tensordot(a, modes, 1), 0, 255).astype(np.uint8)


def render(mesh: DelegateMesh, texture: np.ndarray, alpha: np.ndarray, pose: Pose,
           camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The delegate at (alpha, pose) seen by ``camera``: image (H, W, 3) uint8 BGR (black
    where it is not) and its mask (H, W) bool. The texture carries the enrolment's own
    lighting (no shading is added): what the camera saw, on the moved surface."""
    cam = pose.transform(mesh.shape(alpha))
    xy, inv_z = _project(cam, camera)
    tris = mesh.triangles
    ids, _ = rasterize(xy, inv_z, tris, np.ones(len(tris), bool), camera.width, camera.height)
    mask = ids >= 0
    py, px = np.nonzero(mask)
    t = ids[py, px]
    bary = _barycentric(xy[tris[t]], np.stack([px, py], 1).astype(np.float64))
    uv = np.einsum("pc,pcd->pd", bary, mesh.uv[tris[t]])
    size = texture.shape[0]
    out = np.zeros((camera.height, camera.width, 3), np.uint8)
    if len(t):
        out[py, px] = _lookup(texture, uv * size - 0.5)
    return out, mask


def face_ssim(real: np.ndarray, drawn: np.ndarray, mask: np.ndarray, erode_px: int = 5
              ) -> float:
    """Mean structural similarity (grey, OpenCV's SSIM: 11x11 Gaussian window, sigma 1.5)
    of ``drawn`` against ``real`` over the face region ``mask`` eroded by ``erode_px`` (so
    every window averaged lies on the face). NaN when the region is empty."""
    inner = cv2.erode(mask.astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8)) > 0
    if not inner.any():
        return float("nan")
    rows, cols = np.nonzero(mask)
    r0, r1 = max(rows.min() - 8, 0), rows.max() + 9
    c0, c1 = max(cols.min() - 8, 0), cols.max() + 9
    a = cv2.cvtColor(real[r0:r1, c0:c1], cv2.COLOR_BGR2GRAY)
    comp = np.where(mask[..., None], drawn, real)[r0:r1, c0:c1]
    b = cv2.cvtColor(np.ascontiguousarray(comp), cv2.COLOR_BGR2GRAY)
    _, smap = cv2.quality.QualitySSIM_compute(a, b)  # type: ignore[attr-defined]
    return float(np.mean(np.asarray(smap)[inner[r0:r1, c0:c1]]))

"""Appearance models (METHOD.md §2): local appearance (la) and texture (tex), cst or lin.

Both kinds are features sampled from the image at *sample points* on the face: each sample
point is a fixed barycentric combination of up to three model points, so its head-frame
position is linear in alpha like the model itself. la samples 8 Gaussian-derivative
responses at selected model points; tex samples the smoothed, luminance-normalised Y channel
at a dense grid of points spread over the mesh in its normalized shape (the piecewise-affine
texture frame of the paper).

Descriptor channels of la, from the Gaussian-smoothed Y, Cr, Cb image S (sigma px):
``(Yx, Yy, Cr, Crx, Cry, Cb, Cbx, Cby)`` — derivatives scale-normalised (x sigma).
The model predicts, per feature value, ``f(alpha) = W[0] + alpha @ W[1:K+1]`` (lin), or
``W[0]`` (cst); ``la_quad`` (ours, beyond the paper) adds ``alpha**2 @ W[K+1:]`` so the
appearance of lip-contour points, which changes non-linearly as lips open and round, is
predicted without bias at the extremes. ``channel_weight`` balances the features in the cost.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import cv2
import numpy as np

from core.bundle import load_bundle, require, save_bundle
from core.camera import Camera, Pose
from core.errors import InputError
from core.model import FaceModel

APPEARANCE_KIND = "appearance-model"
APPEARANCE_VERSION = 1
KINDS = ("la_cst", "la_lin", "la_quad", "tex_cst", "tex_lin")
LA_CHANNELS = ("Yx", "Yy", "Cr", "Crx", "Cry", "Cb", "Cbx", "Cby")
SELECTIONS = ("auto", "information", "displacement")


# --------------------------------------------------------------------------- image maps
@dataclass(frozen=True, eq=False)
class ImageMaps:
    """The smoothed Y, Cr, Cb image over a region of interest, at one pyramid level.

    smooth : (h, w, 3) float32, Gaussian-smoothed Y, Cr, Cb (0..255).
    origin : (x0, y0) of the ROI in image pixels; scale : map px per image px (1 or 1/2^n).
    sigma : smoothing scale in map pixels.
    source, done, rows, rows_done, taps : set on *lazy* maps (``image_pyramid(lazy=True)``):
        the unsmoothed YCrCb ROI (uint8), and buffers the compiled cost kernel fills on
        demand — only the pixels around the sample points are ever smoothed, instead of the
        whole face. ``smooth`` is then valid only where ``done`` is set; :meth:`dense`
        completes it (the numpy path does so).
    """

    smooth: np.ndarray
    origin: tuple[int, int]
    scale: float
    sigma: float
    source: np.ndarray | None = None
    done: np.ndarray | None = None
    rows: np.ndarray | None = None
    rows_done: np.ndarray | None = None
    taps: np.ndarray | None = None

    @property
    def lazy(self) -> bool:
        return self.source is not None

    def dense(self) -> np.ndarray:
        """The fully smoothed map (smooths what a lazy map has not yet)."""
        if self.source is not None and self.done is not None and not self.done.all():
            k = self.taps.size if self.taps is not None else 0
            self.smooth[...] = cv2.GaussianBlur(self.source.astype(np.float32), (k, k),
                                                self.sigma)
            self.done[...] = 1
        return self.smooth

    def to_map(self, uv: np.ndarray) -> np.ndarray:
        """Image pixels (M, 2) -> map pixels (M, 2)."""
        return (uv - np.asarray(self.origin)) * self.scale + 0.5 * (self.scale - 1.0)


def _lazy_maps(part: np.ndarray, origin: tuple[int, int], scale: float, sigma: float,
               k: int) -> ImageMaps:
    h, w = part.shape[:2]
    src = np.ascontiguousarray(part)
    return ImageMaps(np.empty((h, w, 3), np.float32), origin, scale, float(sigma), src,
                     np.zeros((h, w), np.uint8), np.empty((h, w, 3), np.float32),
                     np.zeros((h, w), np.uint8), cv2.getGaussianKernel(k, sigma).ravel())


def image_maps(
    image: np.ndarray, roi: tuple[int, int, int, int], sigma: float, level: int = 0
) -> ImageMaps:
    """Smooth the ROI ``(x0, y0, x1, y1)`` of a BGR uint8 image in YCrCb at scale ``sigma``.

    ``level`` n halves the ROI n times first (coarse-to-fine); ``sigma`` is in the reduced
    pixels, so the effective scale in image pixels is ``sigma * 2**level``.
    """
    return image_pyramid(image, roi, sigma, (level,))[level]


def image_pyramid(image: np.ndarray, roi: tuple[int, int, int, int], sigma: float,
                  levels: tuple[int, ...],
                  fine_roi: tuple[int, int, int, int] | None = None,
                  lazy: bool = False) -> dict[int, ImageMaps]:
    """:func:`image_maps` for several levels from one colour conversion of one ROI.

    fine_roi : a smaller ROI for level 0 (inside ``roi``): the coarse levels need the wide
    margin of their wider filters and search, the full-resolution level does not, and its blur
    is the most expensive step of a frame.
    lazy : level 0 as lazy maps (see :class:`ImageMaps`), smoothed on demand by the compiled
    kernel: a frame's fit touches a few thousand of its ~150 000 face pixels.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"expected a BGR uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    x0, y0 = max(0, int(roi[0])), max(0, int(roi[1]))
    x1, y1 = min(w, int(roi[2])), min(h, int(roi[3]))
    if x1 - x0 < 8 or y1 - y0 < 8:
        x0, y0, x1, y1 = 0, 0, w, h
    crop = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2YCrCb)
    k = 2 * int(np.ceil(3.0 * sigma)) + 1
    out: dict[int, ImageMaps] = {}
    for level in range(max(levels) + 1):
        if level:
            crop = cv2.pyrDown(crop)
        if level not in levels:
            continue
        part, ox, oy = crop, x0, y0
        if level == 0 and fine_roi is not None:
            fx0, fy0 = max(int(fine_roi[0]), x0), max(int(fine_roi[1]), y0)
            fx1, fy1 = min(int(fine_roi[2]), x1), min(int(fine_roi[3]), y1)
            if fx1 - fx0 >= 8 and fy1 - fy0 >= 8:
                part, ox, oy = crop[fy0 - y0:fy1 - y0, fx0 - x0:fx1 - x0], fx0, fy0
        if lazy and level == 0 and min(part.shape[:2]) > k:
            out[level] = _lazy_maps(part, (ox, oy), 1.0, sigma, k)
            continue
        smooth = cv2.GaussianBlur(part.astype(np.float32), (k, k), sigma)
        out[level] = ImageMaps(smooth, (ox, oy), 0.5**level, float(sigma))
    return out


def _interpolate(maps: ImageMaps, uv: np.ndarray) -> tuple[np.ndarray, ...]:
    """Bilinear interpolation of S and of its central differences at image points.

    Returns ival, idx, idy, each (M, 9) in map px units, and valid (M,) bool (False where the
    4x4 neighbourhood leaves the map or uv is NaN). Columns: S (Y, Cr, Cb), then its central
    differences Sx, Sy, interpolated bilinearly (ival); idx, idy are the exact x and y
    derivatives of those interpolants, so the optimiser's Jacobians are those of the very
    values the cost samples.
    """
    s = maps.dense()
    hh, ww, nc = s.shape
    m = maps.to_map(np.asarray(uv, dtype=np.float64))
    valid = np.isfinite(m).all(1)
    m = np.where(valid[:, None], m, 0.0)
    ix = np.floor(m[:, 0]).astype(np.int64)
    iy = np.floor(m[:, 1]).astype(np.int64)
    valid &= (ix >= 1) & (ix <= ww - 3) & (iy >= 1) & (iy <= hh - 3)
    ix = np.clip(ix, 1, ww - 3)
    iy = np.clip(iy, 1, hh - 3)
    fx = (m[:, 0] - ix)[:, None]
    fy = (m[:, 1] - iy)[:, None]
    # one flat gather of the 4x4 neighbourhoods (much cheaper than 2-D fancy indexing):
    # p: (M, 4, 4, C), rows y = iy-1..iy+2, cols x = ix-1..ix+2
    d = np.arange(-1, 3)
    window = ((d[:, None] * ww + d[None, :]) * nc)[:, :, None] + np.arange(nc)
    p = np.take(s.reshape(-1), ((iy * ww + ix) * nc)[:, None, None, None] + window)
    # corner values, central differences in x and y, side by side: (M, 2, 2, 9)
    c = np.concatenate([p[:, 1:3, 1:3], (p[:, 1:3, 2:4] - p[:, 1:3, 0:2]) * 0.5,
                        (p[:, 2:4, 1:3] - p[:, 0:2, 1:3]) * 0.5], axis=-1)
    top = c[:, 0, 0] + (c[:, 0, 1] - c[:, 0, 0]) * fx
    bot = c[:, 1, 0] + (c[:, 1, 1] - c[:, 1, 0]) * fx
    ival = top + (bot - top) * fy
    idx = (c[:, 0, 1] - c[:, 0, 0]) + ((c[:, 1, 1] - c[:, 1, 0]) - (c[:, 0, 1] - c[:, 0, 0])) * fy
    idy = bot - top
    return ival, idx, idy, valid


# la descriptors as columns of the interpolated (M, 9) = [S(Y Cr Cb), Sx(Y Cr Cb), Sy(Y Cr Cb)]
_LA_COLS = np.array([3, 6, 1, 4, 7, 2, 5, 8])  # Yx Yy Cr Crx Cry Cb Cbx Cby
_LA_DERIV = np.array([1, 1, 0, 1, 1, 0, 1, 1], bool)
_LA_OFFSET = np.array([0, 0, 128.0, 0, 0, 128.0, 0, 0])


def sample_la(maps: ImageMaps, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8 la descriptors at image points and their derivatives w.r.t. image position.

    uv : (M, 2) image px. Returns desc (M, 8), ddesc (M, 8, 2) per image px, valid (M,).
    """
    ival, idx, idy, valid = _interpolate(maps, uv)
    scale = np.where(_LA_DERIV, maps.sigma, 1.0)
    dd = np.stack([idx[:, _LA_COLS], idy[:, _LA_COLS]], axis=2)
    # chroma values centred on 128 (neutral grey): every descriptor then scales with gain
    return ival[:, _LA_COLS] * scale - _LA_OFFSET, dd * (scale * maps.scale)[None, :, None], valid


def sample_tex(maps: ImageMaps, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed luminance Y at image points: (M, 1), d/d(uv) (M, 1, 2) per image px, valid."""
    ival, idx, idy, valid = _interpolate(maps, uv)
    grad = np.stack([idx[:, 0], idy[:, 0]], axis=1)[:, None, :] * maps.scale
    return ival[:, :1], grad, valid


# --------------------------------------------------------------------------- sample points
@dataclass(frozen=True, eq=False)
class SamplePoints:
    """Sample points as barycentric combinations of model points.

    index : (S, 3) int model point indices; weight : (S, 3) float, rows sum to 1.
    """

    index: np.ndarray
    weight: np.ndarray

    def positions(self, model: FaceModel) -> tuple[np.ndarray, np.ndarray]:
        """Head-frame mean (S, 3) and basis (K, S, 3) of the sample points."""
        mean = np.einsum("sj,sjd->sd", self.weight, model.mean[self.index])
        basis = np.einsum("sj,ksjd->ksd", self.weight, model.basis[:, self.index])
        return mean, basis

    @classmethod
    def of_points(cls, idx: np.ndarray) -> SamplePoints:
        idx = np.asarray(idx, np.int64)
        return cls(np.repeat(idx[:, None], 3, 1), np.tile([1.0, 0.0, 0.0], (idx.size, 1)))


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) of a mesh (triangles CCW seen from outside)."""
    a, b, c = (points[triangles[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(points)
    for i in range(3):
        np.add.at(n, triangles[:, i], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def select_points(
    model: FaceModel, per_param: int = 5, candidates: np.ndarray | None = None
) -> np.ndarray:
    """Automatic point selection (METHOD.md §2): for each parameter, the ``per_param`` points
    whose displacement under its basis vector over the training range is largest; merged and
    de-duplicated. ``candidates`` restricts the choice (e.g. visible points, no markers).
    """
    spread = model.stats.max - model.stats.min
    allowed = np.arange(model.n_points) if candidates is None else np.asarray(candidates)
    chosen: set[int] = set()
    for k in range(model.n_params):
        motion = np.linalg.norm(model.basis[k, allowed], axis=1) * spread[k]
        chosen.update(int(i) for i in allowed[np.argsort(-motion)[:per_param]])
    return np.array(sorted(chosen), np.int64)


def _regress(dmat: np.ndarray, fmat: np.ndarray, ridge: float, constant: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Appearance regression of features (F, D') on regressors (F, D): weights (D, D'), fitted
    residuals and leave-one-out residuals (e / (1 - h)). Feature weights must reflect how well
    a feature is *predicted* on frames it was not fitted on, not how well it was fitted.
    ``constant``: the cst models, the training mean (no leave-one-out correction)."""
    if constant:
        w = np.zeros((dmat.shape[1], fmat.shape[1]))
        w[0] = fmat.mean(0)
        fitted = fmat - dmat @ w
        return w, fitted, fitted
    reg = ridge * len(dmat) * np.diag([0.0] + [1.0] * (dmat.shape[1] - 1))  # intercept free
    inv = np.linalg.inv(dmat.T @ dmat + reg)
    w = inv @ (dmat.T @ fmat)
    fitted = fmat - dmat @ w
    hat = np.einsum("fi,ij,fj->f", dmat, inv, dmat)
    return w, fitted, fitted / np.maximum(1.0 - hat, 0.05)[:, None]


def _feature_weights(resid: np.ndarray, c: int, floor_min: float) -> np.ndarray:
    """Inverse residual s.d. per feature (S, C), floored at half the channel's median and at
    ``floor_min`` so that none dominates the cost."""
    rms_f = np.sqrt((resid**2).mean(0)).reshape(-1, c)
    floor = np.maximum(np.median(rms_f, axis=0) * 0.5, floor_min)
    return 1.0 / np.maximum(rms_f, floor)


def informative_points(
    model: FaceModel, camera: Camera, frames: list[TrainingFrame], candidates: np.ndarray,
    n_points: int, sigma: float = 2.5, ridge: float = 1e-2, prior: float = 1.0,
    noise_floor: float = 1.0,
) -> np.ndarray:
    """Point selection by the information the la lin cost carries about alpha (ours, beyond
    the paper's largest-displacement rule).

    For every candidate point and training frame, the Jacobian of its 8 weighted residuals
    w.r.t. alpha, ``cw * (dD/duv . duv/dalpha - W_k)``, is computed at the true state (cw: the
    inverse leave-one-out residual s.d. of a la lin model of that point, so badly predicted
    points — inner lips, teeth — carry little information). Points are then added greedily,
    each time the one that most reduces the expected RMS 3D error of the estimate,
    ``trace(G (prior I + sum_i J_i^T J_i)^-1)`` with G the model's geometric metric (mm^2 per
    alpha^2 over all points): parameters that move the face a lot but are barely seen in the
    image (jaw advance, along the optical axis) get the points that do see them.
    """
    cand = np.asarray(candidates, np.int64)
    if cand.size <= n_points:
        return np.sort(cand)
    k = model.n_params
    alphas = np.stack([np.asarray(f.alpha, np.float64) for f in frames])
    dmat = design(alphas, "la_lin")
    basis = model.basis[:, cand]  # (K, S, 3)
    feats, jacs = [], []
    for fr in frames:
        pts = model.mean[cand] + np.einsum("k,ksd->sd", fr.alpha, basis)
        cam = fr.pose.transform(pts)
        uv, jp = camera.project_jacobian(cam)
        maps = image_maps(fr.image, roi_of(uv, 4 * sigma + 8), sigma, 0)
        f, df, _ = sample_la(maps, uv)
        dcam = np.einsum("de,kse->sdk", fr.pose.matrix, basis)  # (S, 3, K)
        feats.append(f)
        jacs.append(np.matmul(df, np.matmul(jp, dcam)))  # (S, 8, K)
    fmat = np.stack(feats).reshape(len(frames), -1)  # (F, S*8)
    w, _, loo = _regress(dmat, fmat, ridge, constant=False)
    cw = _feature_weights(loo, 8, noise_floor)  # (S, 8)
    wk = w[1:].T.reshape(-1, 8, k)  # (S, 8, K) model derivative
    info = np.zeros((cand.size, k, k))
    for jac in jacs:
        jr = (jac - wk) * cw[:, :, None]
        info += np.einsum("sck,scl->skl", jr, jr)
    info /= len(frames)
    gmat = np.einsum("kpd,lpd->kl", model.basis, model.basis) / model.n_points
    h = prior * np.eye(k)
    chosen: list[int] = []
    free = np.ones(cand.size, bool)
    for _ in range(n_points):
        trials = np.linalg.inv(h[None] + info)  # (S, K, K)
        score = np.einsum("kl,slk->s", gmat, trials)
        score[~free] = np.inf
        best = int(np.argmin(score))
        chosen.append(best)
        free[best] = False
        h = h + info[best]
    return np.sort(cand[chosen])


def texture_grid(model: FaceModel, spacing_mm: float = 2.0,
                 triangles: np.ndarray | None = None) -> SamplePoints:
    """A regular grid over the mesh in its normalized shape (frontal x-y of the mean face),
    each grid point bound to the triangle containing it (the piecewise-affine texture frame).
    """
    tri = model.triangles if triangles is None else np.asarray(triangles)
    if tri.size == 0:
        raise InputError("texture models need a triangulated face model")
    xy = model.mean[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing_mm), np.arange(lo[1], hi[1], spacing_mm))
    g = np.c_[gx.ravel(), gy.ravel()]
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    v0, v1 = b - a, c - a
    den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    ok_tri = np.abs(den) > 1e-9
    tri, a, v0, v1, den = tri[ok_tri], a[ok_tri], v0[ok_tri], v1[ok_tri], den[ok_tri]
    idx, wts = [], []
    for start in range(0, len(g), 4096):
        q = g[start:start + 4096, None, :] - a[None]
        l1 = (q[..., 0] * v1[:, 1] - q[..., 1] * v1[:, 0]) / den
        l2 = (v0[:, 0] * q[..., 1] - v0[:, 1] * q[..., 0]) / den
        inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
        hit = inside.any(1)
        t = np.argmax(inside, axis=1)[hit]
        rows = np.nonzero(hit)[0]
        b1, b2 = l1[rows, t], l2[rows, t]
        idx.append(tri[t])
        wts.append(np.c_[1 - b1 - b2, b1, b2])
    return SamplePoints(np.concatenate(idx), np.concatenate(wts))


# --------------------------------------------------------------------------- models
@dataclass(frozen=True, eq=False)
class AppearanceModel:
    """A trained appearance model (one of :data:`KINDS`).

    samples : where features are sampled. levels : pyramid levels trained (0 = full res).
    weights : (L, D, S*C) per level, rows of :func:`design` (D = 1 + K, or 1 + 2K for quad).
    channel_weight : (L, S*C) per-feature cost weights (inverse residual s.d. in training).
    sigma : smoothing scale in pixels of each level (image px x 2**level).
    explained : (L,) fraction of the feature variance explained on the training frames.
    """

    kind: str
    samples: SamplePoints
    levels: tuple[int, ...]
    weights: np.ndarray
    channel_weight: np.ndarray
    sigma: float
    explained: np.ndarray

    @property
    def n_channels(self) -> int:
        return 8 if self.kind.startswith("la") else 1

    @property
    def n_samples(self) -> int:
        return int(self.samples.index.shape[0])

    def sample(self, maps: ImageMaps, uv: np.ndarray):
        return sample_la(maps, uv) if self.kind.startswith("la") else sample_tex(maps, uv)

    def level_index(self, level: int) -> int:
        try:
            return self.levels.index(level)
        except ValueError:
            raise InputError(f"appearance model has no pyramid level {level}") from None

    def save(self, path: str | os.PathLike[str]) -> None:
        save_bundle(path, APPEARANCE_KIND, APPEARANCE_VERSION, {
            "index": self.samples.index, "weight": self.samples.weight,
            "weights": self.weights, "channel_weight": self.channel_weight,
            "explained": self.explained,
        }, {"appearance_kind": self.kind, "levels": list(self.levels), "sigma": self.sigma})

    @classmethod
    def load(cls, path: str | os.PathLike[str], model: FaceModel | None = None) -> AppearanceModel:
        arrays, meta = load_bundle(path, APPEARANCE_KIND, (APPEARANCE_VERSION,))
        for key in ("index", "weight", "weights", "channel_weight", "explained"):
            require(key in arrays, path, f"missing array {key!r}")
        kind = meta.get("appearance_kind")
        require(kind in KINDS, path, f"unknown appearance kind {kind!r}")
        idx, w = arrays["index"], arrays["weight"]
        s = idx.shape[0]
        require(idx.shape == (s, 3) and w.shape == (s, 3), path, "sample points are malformed")
        c = 8 if kind.startswith("la") else 1
        levels = tuple(int(v) for v in meta.get("levels", []))
        wt = arrays["weights"]
        require(wt.ndim == 3 and wt.shape[0] == len(levels) and wt.shape[2] == s * c, path,
                f"weights have shape {wt.shape}, expected ({len(levels)}, K+1, {s * c})")
        if model is not None:
            d = 2 * model.n_params + 1 if kind.endswith("quad") else model.n_params + 1
            require(wt.shape[1] == d, path,
                    f"weights have {wt.shape[1]} rows, a {kind} model of {model.n_params} "
                    f"parameters has {d}")
            require(idx.max() < model.n_points, path,
                    "sample points index points the face model does not have")
        return cls(kind, SamplePoints(idx, w), levels, wt, arrays["channel_weight"],
                   float(meta["sigma"]), arrays["explained"])


def design(alpha: np.ndarray, kind: str) -> np.ndarray:
    """Regressors of an appearance model: alpha (F, K) -> (F, D) = [1, alpha(, alpha**2)]."""
    alpha = np.atleast_2d(alpha)
    cols = [np.ones((alpha.shape[0], 1)), alpha]
    if kind.endswith("quad"):
        cols.append(alpha**2)
    return np.concatenate(cols, axis=1)


@dataclass(frozen=True)
class TrainingFrame:
    """An image with its known state: BGR uint8 (H, W, 3), alpha (K,), head pose."""

    image: np.ndarray
    alpha: np.ndarray
    pose: Pose


def roi_of(uv: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of finite image points grown by ``margin`` px."""
    finite = uv[np.isfinite(uv).all(1)]
    if finite.size == 0:
        return (0, 0, 0, 0)
    lo = np.floor(finite.min(0) - margin).astype(int)
    hi = np.ceil(finite.max(0) + margin).astype(int)
    return (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)


def visible_points(model: FaceModel, camera: Camera, frames: list[TrainingFrame],
                   min_cos: float = 0.25, margin: float = 12.0) -> np.ndarray:
    """Model points facing the camera and inside the image in every training frame."""
    ok = np.ones(model.n_points, bool)
    for fr in frames:
        pts = model.shape(fr.alpha)
        normals = vertex_normals(pts, model.triangles) @ fr.pose.matrix.T
        cam_pts = fr.pose.transform(pts)
        view = -cam_pts / np.linalg.norm(cam_pts, axis=1, keepdims=True)
        ok &= (normals * view).sum(1) > min_cos
        ok &= camera.inside(camera.project(cam_pts), margin)
    return np.nonzero(ok)[0]


def train_appearance(
    model: FaceModel,
    camera: Camera,
    frames: list[TrainingFrame],
    kind: str = "la_lin",
    *,
    sigma: float = 2.5,
    levels: tuple[int, ...] = (0, 1, 2),
    per_param: int = 8,
    tex_spacing_mm: float = 2.0,
    ridge: float | None = None,
    noise_floor: float = 1.0,
    selection: str = "auto",
    n_points: int | None = None,
) -> AppearanceModel:
    """Fit an appearance model by least squares on frames with known state.

    la: sample points among those visible in every frame, chosen by ``selection``:
    "information" (:func:`informative_points`, ``n_points`` of them, default ``per_param``
    per parameter), "displacement" (the paper's rule, :func:`select_points`), or "auto"
    (information when there are at least 2(K+1) frames to fit and cross-validate it).
    tex: a grid in the normalized shape over front-facing triangles, features z-scored per
    frame (luminance normalisation). cst models predict the training mean; lin models regress
    every feature value on [1, alpha] (ridge-regularised, intercept free; ``ridge`` default
    0.1 for la, whose few points must extrapolate beyond the enrolment's range — 0.01 gave
    ~20 % more error there — and 0.01 for tex, whose dense grid does not). Features are
    weighted by the inverse of their training residual s.d., floored at half the channel's
    median and at ``noise_floor`` grey levels (la), so that features the model predicts badly
    (occluded inner-lip points, teeth) count little and none dominates the cost.
    """
    if kind not in KINDS:
        raise InputError(f"appearance kind must be one of {KINDS}, got {kind!r}")
    n_terms = design(np.zeros((1, model.n_params)), kind).shape[1]
    if len(frames) < (2 if kind.endswith("cst") else n_terms + 1):
        raise InputError(f"{len(frames)} training frames are too few for {kind}")
    vis = visible_points(model, camera, frames)
    if ridge is None:  # measured on the teleconference condition (README, Results)
        ridge = 0.1 if kind.startswith("la") else 0.01
    if selection not in SELECTIONS:
        raise InputError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    if kind.startswith("la"):
        if selection == "auto":  # information needs a la lin fit with spare frames
            enough = len(frames) >= 2 * (model.n_params + 1)
            selection = "information" if enough else "displacement"
        if selection == "information":
            chosen = informative_points(model, camera, frames, vis,
                                        n_points or per_param * model.n_params, sigma, ridge,
                                        noise_floor=noise_floor)
        else:
            chosen = select_points(model, per_param, vis)
        samples = SamplePoints.of_points(chosen)
    else:
        tri = model.triangles
        tri = tri[np.isin(tri, vis).all(1)]
        samples = texture_grid(model, tex_spacing_mm, tri)
    if samples.index.shape[0] == 0:
        raise InputError("no model point is visible in every training frame")
    s_mean, s_basis = samples.positions(model)
    alphas = np.stack([np.asarray(f.alpha, np.float64) for f in frames])
    dmat = design(alphas, kind)
    weights, cweights, explained = [], [], []
    for level in levels:
        feats = []
        for fr in frames:
            pts = s_mean + np.einsum("k,ksd->sd", fr.alpha, s_basis)
            uv = camera.project(fr.pose.transform(pts))
            maps = image_maps(fr.image, roi_of(uv, 4 * sigma * 2**level + 8), sigma, level)
            f = (sample_la if kind.startswith("la") else sample_tex)(maps, uv)[0]
            if kind.startswith("tex"):
                f = (f - f.mean()) / max(f.std(), 1e-6)
            feats.append(f.reshape(-1))
        fmat = np.stack(feats)  # (F, S*C)
        w, fitted, loo = _regress(dmat, fmat, ridge, kind.endswith("cst"))
        c = 8 if kind.startswith("la") else 1
        cweights.append(_feature_weights(loo, c, noise_floor if c == 8 else 0.02).reshape(-1))
        total = ((fmat - fmat.mean(0)) ** 2).sum()
        explained.append(1.0 - (fitted**2).sum() / total if total > 0 else 0.0)
        weights.append(w)
    return AppearanceModel(kind, samples, tuple(levels), np.stack(weights), np.stack(cweights),
                           float(sigma), np.array(explained))

"""Descriptor maps of an image and their bilinear sampling (METHOD.md §2).

la channels, from the Gaussian-smoothed Y, Cr, Cb image S (sigma px):
``(Yx, Yy, Cr, Crx, Cry, Cb, Cbx, Cby)`` — derivatives scale-normalised (x sigma).
tex samples the smoothed, luminance-normalised Y channel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.errors import InputError
from articast.core.tracking import kernels

LA_CHANNELS = ("Yx", "Yy", "Cr", "Crx", "Cry", "Cb", "Cbx", "Cby")


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
        completes it (the numpy path does so). ``rows`` (w, h, 3) and ``rows_done`` (w, h)
        hold the horizontal passes column-major: a pixel's vertical pass reads its column's
        rows side by side (a few cache lines instead of 17 spread over the box: a live
        frame's CPU -1 % on franck, -6 % on cap13, the same numbers).
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


class MapBuffers:
    """Memory that lazy maps (:func:`image_pyramid` ``buffers=``) reuse from one call to the
    next, grown to the largest ROI seen: a tracker's frames then write into memory they
    touched the frame before, instead of into fresh allocations (their page faults and cold
    cache lines). Maps made with them are valid until the next call that uses them."""

    def __init__(self) -> None:
        self._u8 = np.empty(0, np.uint8)
        self._f32 = np.empty(0, np.float32)
        self._taps: dict[tuple[int, float], np.ndarray] = {}

    def take(self, h: int, w: int) -> tuple[np.ndarray, ...]:
        """(ycrcb (h, w, 3) uint8, smooth (h, w, 3) float32, done (h, w) uint8 zeroed,
        rows (w, h, 3) float32, rows_done (w, h) uint8 zeroed), all C-contiguous."""
        n = h * w
        if self._u8.size < 5 * n:
            self._u8 = np.empty(5 * n, np.uint8)
            self._f32 = np.empty(6 * n, np.float32)
        flags = self._u8[3 * n:5 * n]
        flags[...] = 0
        return (self._u8[:3 * n].reshape(h, w, 3), self._f32[:3 * n].reshape(h, w, 3),
                flags[:n].reshape(h, w), self._f32[3 * n:6 * n].reshape(w, h, 3),
                flags[n:].reshape(w, h))

    def taps(self, k: int, sigma: float) -> np.ndarray:
        """``cv2.getGaussianKernel(k, sigma)`` (k,), kept."""
        key = (k, float(sigma))
        if key not in self._taps:
            self._taps[key] = cv2.getGaussianKernel(k, sigma).ravel()
        return self._taps[key]


def _lazy_maps(part: np.ndarray, origin: tuple[int, int], scale: float, sigma: float,
               k: int, buffers: MapBuffers | None = None,
               taken: tuple[np.ndarray, ...] | None = None) -> ImageMaps:
    h, w = part.shape[:2]
    src = np.ascontiguousarray(part)
    if buffers is not None and taken is not None:
        _, smooth, done, rows, rows_done = taken
        return ImageMaps(smooth, origin, scale, float(sigma), src, done, rows, rows_done,
                         buffers.taps(k, sigma))
    return ImageMaps(np.empty((h, w, 3), np.float32), origin, scale, float(sigma), src,
                     np.zeros((h, w), np.uint8), np.empty((w, h, 3), np.float32),
                     np.zeros((w, h), np.uint8), cv2.getGaussianKernel(k, sigma).ravel())


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
                  lazy: bool = False, buffers: MapBuffers | None = None
                  ) -> dict[int, ImageMaps]:
    """:func:`image_maps` for several levels from one colour conversion of one ROI.

    fine_roi : a smaller ROI for level 0 (inside ``roi``): the coarse levels need the wide
    margin of their wider filters and search, the full-resolution level does not, and its blur
    is the most expensive step of a frame.
    lazy : level 0 as lazy maps (see :class:`ImageMaps`), smoothed on demand by the compiled
    kernel: a frame's fit touches a few thousand of its ~150 000 face pixels.
    buffers : where a lazy level 0 is made of the whole ROI, its colour conversion and
    buffers go there (:class:`MapBuffers`; the same numbers): the maps of the previous call
    with them are then no longer valid.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"expected a BGR uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    x0, y0 = max(0, int(roi[0])), max(0, int(roi[1]))
    x1, y1 = min(w, int(roi[2])), min(h, int(roi[3]))
    if x1 - x0 < 8 or y1 - y0 < 8:
        x0, y0, x1, y1 = 0, 0, w, h
    k = 2 * int(np.ceil(3.0 * sigma)) + 1
    taken = None
    if (buffers is not None and lazy and 0 in levels and fine_roi is None
            and min(y1 - y0, x1 - x0) > k):
        taken = buffers.take(y1 - y0, x1 - x0)
        crop = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2YCrCb, dst=taken[0])
    else:
        crop = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2YCrCb)
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
            out[level] = _lazy_maps(part, (ox, oy), 1.0, sigma, k, buffers, taken)
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


def roi_of(uv: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of finite image points (M, 2) grown by ``margin`` px.
    Compiled (:func:`~articast.core.tracking.kernels.roi_box`, the same box) for float64
    points; :func:`roi_of_numpy` is the reference."""
    if kernels.AVAILABLE and uv.dtype == np.float64 and uv.ndim == 2 and uv.shape[1] == 2:
        return kernels.roi_box(np.ascontiguousarray(uv), float(margin))
    return roi_of_numpy(uv, margin)


def roi_of_numpy(uv: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """The reference of :func:`roi_of`."""
    finite = uv[np.isfinite(uv).all(1)]
    if finite.size == 0:
        return (0, 0, 0, 0)
    lo = np.floor(finite.min(0) - margin).astype(int)
    hi = np.ceil(finite.max(0) + margin).astype(int)
    return (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)

"""The eyelids in the frame's pixels, between two readings of the landmarks: the lid gap, the
visible iris's height and the eye's contrast in a strip placed by the eye corners
(:func:`lid_gap`, :func:`iris_height`, :func:`photo_measure`), and how much an eye's pixels
changed since a reading (:func:`eye_template`, :func:`eye_change`). The upper face
(:mod:`articast.core.faces.upper`) calibrates them against the reader's closure at
enrolment."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from articast.core.tracking import kernels


def photo_measure(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray,
                  open_px: float) -> float | None:
    """The contrast of an ellipse over the open eye (white sclera, dark iris, lash line; a
    closed lid is skin): the grey levels' s.d. inside it over the mean of the skin in a ring
    round it (0: uniform; ~0.3-0.6 an open eye). The ellipse joins the corners ``inner``,
    ``outer`` (2,) px and is ``open_px`` high (the speaker's open eye at this distance); None
    outside the image. (Its darkness relative to the ring, tried first, did not follow the
    closure on the synthetic speaker, whose sclera is as bright as the iris is dark.)"""
    centre = (np.asarray(inner) + np.asarray(outer)) / 2.0
    axis = np.asarray(outer, np.float64) - inner
    half = float(np.linalg.norm(axis)) / 2.0
    if not np.isfinite(half) or half < 2.0:
        return None
    ang = math.degrees(math.atan2(axis[1], axis[0]))
    a, b = half * 0.8, max(open_px * 0.5, 1.0)
    ra, rb = half * 1.25, b + 0.5 * half
    r = int(math.ceil(max(ra, rb))) + 1
    cx, cy = int(round(centre[0])), int(round(centre[1]))
    h, w = grey.shape[:2]
    if cx - r < 0 or cy - r < 0 or cx + r + 1 > w or cy + r + 1 > h:
        return None
    patch = _grey(grey[cy - r:cy + r + 1, cx - r:cx + r + 1])
    c = (centre[0] - cx + r, centre[1] - cy + r)
    eye = np.zeros(patch.shape, np.uint8)
    ring = np.zeros(patch.shape, np.uint8)
    cv2.ellipse(ring, (c, (2 * ra, 2 * rb), ang), 1, -1)
    cv2.ellipse(eye, (c, (2 * a, 2 * b), ang), 1, -1)
    ring[eye > 0] = 0
    _, sd = cv2.meanStdDev(patch, mask=eye)
    s_eye = float(sd.ravel()[0])
    m_ring = cv2.mean(patch, ring)[0]
    if m_ring <= 1.0:
        return None
    return float(s_eye / m_ring)


CHANGE_SEARCH = 0.3
"""How far round the eye's expected place :func:`eye_change` looks for it, as a fraction of
half the corners' distance (at least 2 px): the place between readings comes from the head's
tracked motion, a pixel or two off on a 10 px eye."""

CHANGE_QUANTILE = 0.975
"""The change an open eye shows between frames that an eye without a usable photometric
measure may show between readings before the frame is read (:attr:`UpperReference.change_limit`):
one frame in 40 of the enrolment's open eyes, per eye, would be read for nothing."""

CHANGE_LAGS = (1, 2)
"""Frames apart whose changes the limit is taken over: the frames between two readings at the
live reader's cadence (every 3rd frame)."""


def _eye_box(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float,
             margin: int = 0) -> np.ndarray | None:
    """The grey levels (float32) of the box over the eye whose corners are ``inner``,
    ``outer`` px: as wide as the corners apart, 1.6 times ``open_px`` high (the open eye at
    this distance), grown by ``margin`` px on every side; None where it leaves the image."""
    cx, cy = (float(inner[0]) + float(outer[0])) / 2.0, (float(inner[1]) + float(outer[1])) / 2.0
    hw = math.hypot(float(outer[0] - inner[0]), float(outer[1] - inner[1])) / 2.0
    hh = max(0.8 * open_px, 1.0)
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(hw)) or hw < 2.0:
        return None
    x0, x1 = int(round(cx - hw)) - margin, int(round(cx + hw)) + 1 + margin
    y0, y1 = int(round(cy - hh)) - margin, int(round(cy + hh)) + 1 + margin
    h, w = grey.shape[:2]
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return None
    return _grey(grey[y0:y1, x0:x1]).astype(np.float32)


def eye_template(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float
                 ) -> np.ndarray | None:
    """The eye's pixels at a reading, for :func:`eye_change` (None outside the image or
    uniform)."""
    box = _eye_box(grey, inner, outer, open_px)
    return None if box is None or float(box.std()) < 1e-3 else box


def eye_change(template: np.ndarray, grey: np.ndarray, inner: np.ndarray, outer: np.ndarray,
               open_px: float) -> float | None:
    """How much the eye changed since ``template`` (:func:`eye_template`) was taken: 1 - the
    best normalised cross-correlation of the template within :data:`CHANGE_SEARCH` of where
    the eye is now expected (corners ``inner``, ``outer`` px). 0: the same pixels, shifted at
    most; a lid closing over an open eye, ~0.3-1. None outside the image. (The eye's contrast
    relative to the reading's, tried first, moved as much with a pixel's misplacement on
    carphone's 10 px eyes: 13 % of its open frames read for nothing, against none:
    docs/UPPER_FACE.md.)"""
    half = math.hypot(float(outer[0] - inner[0]), float(outer[1] - inner[1])) / 2.0
    if not math.isfinite(half):
        return None
    margin = max(2, int(math.ceil(CHANGE_SEARCH * half)))
    area = _eye_box(grey, inner, outer, open_px, margin)
    if area is None or area.shape[0] < template.shape[0] or area.shape[1] < template.shape[1]:
        return None
    return 1.0 - float(cv2.matchTemplate(area, template, cv2.TM_CCOEFF_NORMED).max())


LEVELS_MIN_CONTRAST = 8.0
"""Grey levels whose white or iris is closer than this to the skin cannot tell an open eye."""


def lid_gap(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float,
            levels: tuple[float, float, float]) -> float | None:
    """The eye's opening height in units of ``open_px`` (the speaker's open eye at this
    distance): linear in the upper lid's travel, 0 for a lid shut on the lower one (bar its
    lash line).

    A strip along the eye's axis (the corners ``inner``, ``outer`` (2,) px), ``open_px`` each
    side of it, is resampled (rotation removed); each pixel counts as the eye by how far it
    is from the skin towards the white or the iris (``levels`` = (skin, white, iris): the
    eye's own, from the last open-eye fit), with a soft threshold between a quarter and
    three quarters of the way (a lid's shade, a quarter darker than the skin round it, is
    skin); the opening is the columns' eye-pixel count, averaged over the middle half of the
    eye. (Its predecessor, the grey levels' s.d. in an ellipse, is not linear in the visible
    area: s.d. ~ sqrt(p (1 - p)); the reader's lids saturate near closed.) None outside the
    image or with levels that cannot tell the eye from the skin."""
    skin, white, iris = (float(v) for v in levels)
    if white - skin < LEVELS_MIN_CONTRAST or skin - iris < LEVELS_MIN_CONTRAST:
        return None
    strip = _middle_strip(grey, inner, outer, open_px, 0.25)
    if strip is None:
        return None
    eye = _soft(np.maximum((strip - skin) / (white - skin), (skin - strip) / (skin - iris)))
    return float(eye.sum(0).mean()) / float(open_px)


def iris_height(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float,
                levels: tuple[float, float, float]) -> float | None:
    """The visible iris's height in units of ``open_px``: what of the iris the lids leave
    uncovered, the lash line alone when the eye is shut.

    The lid gap's strip (:func:`lid_gap`); each pixel counts as dark by how far it is from
    the skin towards the iris (the same soft threshold), and only the dark counts: a lid
    as bright as the white (a lit lid, a pale face) is not taken for the eye. The height is
    the mean dark count of the tallest quarter of the columns over the eye's middle 70 % (the
    iris's middle, about a third of the eye wide, wherever the gaze puts it). A shut eye's
    lash line still counts (thick with mascara: pexels_woman's shut eye reads half its open
    one), which the calibration's shut reference (the enrolment's deepest blinks) takes
    out. None outside the image or with levels that cannot tell the iris from the skin."""
    skin, _, iris = (float(v) for v in levels)
    if skin - iris < LEVELS_MIN_CONTRAST:
        return None
    strip = _middle_strip(grey, inner, outer, open_px, 0.15)
    if strip is None:
        return None
    if kernels.AVAILABLE and strip.shape[1] - (3 * strip.shape[1]) // 4 <= kernels.IRIS_MAX_WIDTH:
        # the same numbers in one compiled call (the numpy below: the reference)
        return float(kernels.dark_height(strip, skin, iris)) / float(open_px)
    return _dark_height_numpy(strip, skin, iris) / float(open_px)


def _dark_height_numpy(strip: np.ndarray, skin: float, iris: float) -> float:
    """:func:`iris_height`'s measure of its strip before the division by the open eye, in
    numpy (the reference of :func:`~articast.core.tracking.kernels.dark_height`)."""
    dark = _soft((skin - strip) / (skin - iris)).sum(0)
    tall = np.sort(dark)[(3 * dark.size) // 4:]
    return float(tall.mean())


def _soft(x: np.ndarray) -> np.ndarray:
    """The soft threshold of the eye measures: 0 up to a quarter of the way from the skin,
    1 from three quarters."""
    return np.clip((x - 0.25) * 2.0, 0.0, 1.0)


def _middle_strip(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float,
                  margin: float) -> np.ndarray | None:
    """The eye's strip (:func:`_eye_strip`) without ``margin`` of its width at each end."""
    strip = _eye_strip(grey, inner, outer, open_px)
    if strip is None:
        return None
    wide = strip.shape[1] - 1
    return strip[:, int(round(wide * margin)):int(round(wide * (1.0 - margin))) + 1]


def _eye_strip(grey: np.ndarray, inner: np.ndarray, outer: np.ndarray, open_px: float
               ) -> np.ndarray | None:
    """The strip along the eye's axis between the corners ``inner``, ``outer`` (2,) px,
    ``open_px`` either side of it, resampled with the rotation removed (float32, rows
    across the axis, a column per px along it); None outside the image. (Its geometry in
    Python floats: the same float64 operations as numpy's on these 2-vectors, without ~20
    small array calls, ~40 us of a ~60 us call.)"""
    ix, iy, ox, oy = float(inner[0]), float(inner[1]), float(outer[0]), float(outer[1])
    ax, ay = ox - ix, oy - iy
    length = norm2(ax, ay)
    if not math.isfinite(length) or length < 4.0 or not open_px > 1.0:
        return None
    ux, uy = ax / length, ay / length
    vx, vy = -uy, ux
    wide, high = int(round(length)), int(math.ceil(open_px))
    cx, cy = (ix + ox) / 2.0, (iy + oy) / 2.0
    dux, duy, dvx, dvy = ux * wide / 2.0, uy * wide / 2.0, vx * high, vy * high
    boxed = _inside_xy(grey, (cx - dux - dvx, cx + dux - dvx, cx - dux + dvx, cx + dux + dvx),
                       (cy - duy - dvy, cy + duy - dvy, cy - duy + dvy, cy + duy + dvy))
    if boxed is None:
        return None
    crop, x0, y0 = boxed
    c0, c1 = cx - x0, cy - y0
    m = np.array([[ux, vx, c0 - ux * wide / 2.0 - vx * high],
                  [uy, vy, c1 - uy * wide / 2.0 - vy * high]])
    return cv2.warpAffine(crop, m, (wide + 1, 2 * high + 1),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE).astype(np.float32)


def norm2(x: float, y: float) -> float:
    """The length of the 2-vector (x, y), exactly ``np.linalg.norm`` of it (the square root
    of numpy's dot product, which may round unlike ``x * x + y * y``)."""
    a = np.array((x, y))
    return math.sqrt(float(a.dot(a)))


def _inside_xy(grey: np.ndarray, xs: Sequence[float], ys: Sequence[float]
               ) -> tuple[np.ndarray, int, int] | None:
    """The grey crop (float) of ``grey`` holding the points (``xs``, ``ys``) px (finite) and
    its top-left corner, or None when a point falls outside the image (Python floats: a
    handful of comparisons instead of numpy's reductions over a (4, 2) array)."""
    h, w = grey.shape[:2]
    lx, hx, ly, hy = min(xs), max(xs), min(ys), max(ys)
    if lx < 0 or ly < 0 or hx > w - 1 or hy > h - 1:
        return None
    x0, y0 = math.floor(lx), math.floor(ly)
    x1, y1 = math.ceil(hx) + 1, math.ceil(hy) + 1
    return _grey(grey[y0:y1, x0:x1]), x0, y0


def _grey(patch: np.ndarray) -> np.ndarray:
    """A crop of a grey or BGR image, grey (only the crop is converted: cheaper than the
    frame)."""
    return patch if patch.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(patch),
                                                       cv2.COLOR_BGR2GRAY)

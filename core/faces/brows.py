"""The brows' dark band above each eye, found in the frame's pixels (issue 28's brows): how
high the brow sits above the eye corners' line, inner and outer halves, mm of the aligned
head frame (:func:`brow_band_mm`). The upper face (:mod:`articast.core.faces.upper`) reads
it against the speaker's neutral brows."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from articast.core.faces.eye_landmarks import EYE_CORNERS
from articast.core.faces.lids import _inside_xy, norm2
from articast.core.tracking import kernels

if TYPE_CHECKING:
    from articast.core.faces.upper import Aligned

BROW_ABOVE_READER_MM = 6.0
"""At enrolment a brow half is looked for from just above the open eye's upper lid to this
many mm above the reader's own brow points for that half (the speaker's geometry, not a fixed
height: a person's brow is ~10-25 mm above the eyes' corners). The reader's points are within
a few mm of the brow (the synthetic one's band lies 4 mm below them, franck's within 2 mm);
further up, a fringe or the synthetic head's hair (26 mm above its eyes, its brows' points
15 mm) would win the search: 8 mm found the hair. Where no band is found inside the window,
the reader's brow points are used."""
BROW_WINDOW_MM = 8.0
"""Live, a brow is looked for this many mm either side of the speaker's neutral brow."""


def brow_band_mm(grey: np.ndarray, landmarks: np.ndarray, aligned: Aligned, side: str,
                 window: tuple[tuple[float, float] | None, ...]
                 ) -> tuple[float | None, float | None] | None:
    """The brow's height above the eye's corners' line (mm; inner half, outer half), from
    the pixels: the landmark network's brow points follow its face prior more than the
    brow (docs/UPPER_FACE.md).

    A strip along the eye's axis, 1.2 eye widths wide and up from the corners' line, is
    resampled (rotation removed; 1 px per px, heights in mm by the alignment's scale) and
    smoothed vertically; in each column the brow is the darkest point within ``window``
    (inner (lo, hi), outer (lo, hi) mm, None: that half is not looked for; at enrolment from
    just above the open eye's lid to ``BROW_ABOVE_READER_MM`` above the reader's brow points,
    live the neutral brow +- ``BROW_WINDOW_MM``), sub-pixel by a parabola
    through its neighbours; each half's height is the median of its columns (the nasal half
    is ``inner``). None outside the image; a half is None when it has no dark band (a
    minimum on the window's edge in most of its columns: e.g. a brow gone under a fringe, or
    raised off the synthetic face's mesh)."""
    lm = np.asarray(landmarks, np.float64)
    inner, outer = lm[EYE_CORNERS[side][0], :2], lm[EYE_CORNERS[side][1], :2]
    # (the geometry in Python floats: numpy's float64 operations on these 2-vectors, one at
    # a time, without ~20 small array calls)
    ix, iy, ox, oy = float(inner[0]), float(inner[1]), float(outer[0]), float(outer[1])
    ax, ay = ox - ix, oy - iy
    length = norm2(ax, ay)
    if not math.isfinite(length) or length < 6.0:
        return None
    ux, uy = ax / length, ay / length
    flipped = ux < 0
    if flipped:
        ux, uy = -ux, -uy  # left to right in the image
    vx, vy = uy, -ux  # up in the image
    scale = aligned.scale
    wins = [w for w in window if w is not None]
    if not wins:
        return None
    lo = min(w[0] for w in wins)
    hi = max(w[1] for w in wins)
    r0, r1 = int(math.floor(max(lo, 0.0) * scale)) - 2, int(math.ceil(hi * scale)) + 2
    wide = int(round(1.2 * length))
    cx, cy = (ix + ox) / 2.0, (iy + oy) / 2.0
    ts = (max(r0, 0), r1)
    boxed = _inside_xy(grey, [cx + s_ * ux * wide / 2.0 + t * vx for s_ in (-1, 1) for t in ts],
                       [cy + s_ * uy * wide / 2.0 + t * vy for s_ in (-1, 1) for t in ts])
    if boxed is None:
        return None
    crop, x0, y0 = boxed
    # strip pixel (j, i) <- image centre - u wide/2 + j u + (r1 - i) v: row 0 is the top
    m = np.array([[ux, -vx, cx - x0 - ux * wide / 2.0 + r1 * vx],
                  [uy, -vy, cy - y0 - uy * wide / 2.0 + r1 * vy]])
    rows = r1 - max(r0, 0) + 1
    strip = cv2.GaussianBlur(
        cv2.warpAffine(crop, m, (wide + 1, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE).astype(np.float32),
        (1, 0), sigmaX=0.1, sigmaY=max(0.5, 1.5 * scale))  # ~ a brow's half thickness
    heights = [(r1 - i) / scale for i in range(rows)]  # mm above the corners' line, per row
    # each half's columns: the nasal half is the strip's right one when the corners run right
    # to left in the image (u turned round above), else its left one; the middle column
    # (wide even) is the outer half's (the masks of column - wide / 2 times the inner corner's
    # side, > 0 for nasal, as runs of columns)
    nasal = (wide // 2 + 1, wide) if flipped else (0, (wide - 1) // 2)
    temporal = (0, wide // 2) if flipped else ((wide + 1) // 2, wide)
    out: list[float | None] = []
    for (c0, c1), win in zip((nasal, temporal), window, strict=True):
        if win is None:
            out.append(None)
            continue
        rs = [i for i, h in enumerate(heights) if win[0] <= h <= win[1]]  # (one run of rows)
        if len(rs) < 3 or c1 - c0 + 1 < 3:
            out.append(None)
            continue
        sub = strip[rs[0]:rs[-1] + 1, c0:c1 + 1]
        if kernels.AVAILABLE:  # the same numbers in one compiled call (the numpy below: the
            # reference)
            found, at = kernels.brow_half(sub, heights[rs[0]], float(scale))
            out.append(float(at) if found else None)
            continue
        out.append(_brow_half_numpy(sub, heights[rs[0]], scale))
    return out[0], out[1]


def _brow_half_numpy(sub: np.ndarray, top_mm: float, scale: float) -> float | None:
    """:func:`brow_band_mm`'s search of one half's window ``sub`` of the smoothed strip (row
    0 ``top_mm`` above the eye line), in numpy (the reference of
    :func:`~articast.core.tracking.kernels.brow_half`): the half's height, None without a
    dark band inside the window."""
    k = np.argmin(sub, axis=0)
    inside = (k > 0) & (k < sub.shape[0] - 1)
    if inside.mean() < 0.5:
        return None  # no dark band inside the window
    kk, cc = k[inside], np.flatnonzero(inside)
    y_m, y_0, y_p = sub[kk - 1, cc], sub[kk, cc], sub[kk + 1, cc]
    den = y_m - 2.0 * y_0 + y_p
    frac = np.where(den > 1e-6, 0.5 * (y_m - y_p) / np.maximum(den, 1e-6), 0.0)
    hs = top_mm - (kk + np.clip(frac, -0.5, 0.5)) / scale
    hs = np.sort(hs)  # (the median: np.median's own overhead is most of this step's)
    return float(hs[(hs.size - 1) // 2] + hs[hs.size // 2]) / 2.0

"""The iris and the eye opening in the frame's pixels: an iris circle fitted to its visible
edge and the opening's own centre (:func:`fit_iris`), for the gaze and the grey levels the
lid measures use (:mod:`articast.core.faces.upper`, docs/UPPER_FACE.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.faces import kernels as faces_kernels
from articast.core.faces.eye_landmarks import EYE_CONTOUR, EYE_CORNERS
from articast.core.faces.lids import LEVELS_MIN_CONTRAST, _grey
from articast.core.tracking import kernels


@dataclass(frozen=True)
class IrisFit:
    """One eye's iris and opening in image px: ``centre`` (2,) the iris circle's centre;
    ``half_width`` the widest chord of the visible iris over 2 (the radius, when the iris's
    equator is visible); ``eye`` (2,) the eye opening's own centre (horizontally the middle of
    the opening on its widest rows, vertically its widest row); ``rows`` the iris rows used."""

    centre: np.ndarray
    half_width: float
    eye: np.ndarray
    rows: int
    levels: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    # (skin, white, iris) grey levels, for the closure's measures: None where the eye is
    # fitted but would not have been before the shaded scleras (:func:`_former_accepts`)


IRIS_MIN_ROWS = 3
"""An iris seen on fewer rows (chords bounded by white on both sides) is not fitted."""
_SUB = np.array([-0.25, 0.25])  # sub-rows of a pixel row (a chord is a row's mean)
_FINE = np.arange(-0.5, 0.5001, 0.05)  # the fine search's steps round the coarse height
_GLINT = np.ones((1, 3), np.uint8)  # the chords' opening (a glint narrower than 3 px)
_GROW = np.ones((5, 5), np.uint8)  # the contour grown by 2 px
_CONTOUR = {side: np.array(EYE_CONTOUR[side]) for side in EYE_CONTOUR}


def _circle_height(ys: np.ndarray, wk: np.ndarray, r: float, cys: np.ndarray) -> float:
    """Of the circle heights ``cys``, the one whose chords (radius ``r``, each row ``ys``
    the mean of its sub-rows) fit the widths ``wk`` best (least absolute deviations; the
    first best): :func:`fit_iris`'s search, in numpy (the reference of
    :func:`~articast.core.tracking.kernels.iris_circle_height`)."""
    yy = (ys[:, None] + _SUB[None, :]).ravel()[None, :] - cys[:, None]
    pred = (2.0 * np.sqrt(np.clip(r * r - yy * yy, 0.0, None))).reshape(
        len(cys), len(ys), len(_SUB)).mean(-1)
    return float(cys[int(np.argmin(np.abs(pred - wk[None, :]).sum(1)))])


def fit_iris(grey: np.ndarray, landmarks: np.ndarray, side: str,
             radius_px: float | None = None) -> IrisFit | None:
    """The iris as a circle fitted to its visible edge, and the eye opening it sits in.

    In the eye's crop (the reader's contour grown by 3 px: the contour is a guide, the pixels
    decide), the grey levels give the iris (the median of what is darker than midway between
    the contour's darkest and lightest tenths), the white (the 75th percentile of the rest)
    and the skin (the median round the contour). Each row's **chord** is the run of iris
    round the iris's column, bounded by white on both sides (a row that meets a lid, a lash
    line or the crop's edge is left out), its width the sum of the pixels' iris fractions
    (sub-pixel); the white is each row's own on each side (:func:`_chords`: a real sclera
    is shaded, darker on one side than on the other). The lids cover the iris's top and
    bottom, so its dark centroid hardly moves vertically; the chords' widths do: a circle of
    radius r whose centre is at height c has chords 2 sqrt(r^2 - (y - c)^2), and c is the
    height that fits the widths best (least absolute deviations on a grid of 1/20 px), r
    the speaker's iris radius (``radius_px``, from enrolment) or this frame's widest chord
    / 2. The iris's x is the chords' centroid.

    The **eye's own centre** replaces the reader's corners (which jitter by ~1 px and move
    with the iris on a rendered eye): the opening is what is whiter than midway between skin
    and white inside the grown contour; its widest row is its height (a parabola through the
    widths round the widest), the middle of its ends on the rows within 2 of it (ends
    sub-pixel from the next pixel's white fraction) its x. The upper lid's margin carries a
    dark lash line over the opening's top: the white alone ends at the line's lower edge, the
    white with what is darker than midway between skin and iris at its upper edge; the lid's
    margin is taken between them (the line straddles it: lashes over the eye below, over the
    lid above), the mean of the two openings' centres (:func:`_opening_centres`). Where the
    white is no brighter than the skin round the eye (a shaded sclera under a lit brow: the
    desk webcams of cap12 and cap13) the pixels cannot tell the opening from the skin and
    the middle of the reader's corners is its centre. None when the eye is too closed, too
    small or outside the image, or no iris/white contrast is found."""
    poly = np.asarray(landmarks, np.float64)[_CONTOUR[side], :2]
    xs, ys = poly[:, 0].tolist(), poly[:, 1].tolist()  # (the bounds in Python floats: the
    # same numbers as numpy's min, max, floor and ceil, without their calls)
    if not all(map(math.isfinite, xs + ys)):
        return None
    x0, y0 = math.floor(min(xs)) - 3, math.floor(min(ys)) - 3
    x1, y1 = math.ceil(max(xs)) + 4, math.ceil(max(ys)) + 4
    h, w = grey.shape[:2]
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h or x1 - x0 < 12 or y1 - y0 < 8:
        return None
    crop = _grey(grey[y0:y1, x0:x1])
    if (faces_kernels.AVAILABLE and grey.dtype == np.uint8
            and crop.size <= faces_kernels.IRIS_MAX_PIXELS):  # the same numbers in one
        # compiled call, the contour's mask, its growth and the glints' opening included
        # (below and _fit_steps: the reference; a C-ordered crop, the type the kernel is
        # compiled for)
        got = faces_kernels.iris_fit(
            crop if crop.flags.c_contiguous else crop.copy(), poly, x0, y0,
            float(radius_px) if radius_px else 0.0, _FINE, ROW_WHITE, IRIS_MIN_ROWS,
            LEVELS_MIN_CONTRAST)
        status, cx, cy, half, ex, ey, rows, skin, white, iris_l, levels = got
        if status == 0:
            return None
        if status == 2:  # (a shaded sclera: the corners' midpoint, as _fit_steps)
            lm = np.asarray(landmarks, np.float64)
            ex, ey = (lm[EYE_CORNERS[side][0], :2] + lm[EYE_CORNERS[side][1], :2]) / 2.0 - [
                x0, y0]
        return IrisFit(np.array([cx + x0, cy + y0]), float(half),
                       np.array([ex + x0, ey + y0]), int(rows),
                       (float(skin), float(white), float(iris_l)) if levels else None)
    contour = np.zeros(crop.shape, np.uint8)
    cv2.fillPoly(contour, [np.round(poly - [x0, y0]).astype(np.int32)], 1)
    return _fit_steps(crop.astype(np.float32), contour, cv2.dilate(contour, _GROW), landmarks,
                      side, radius_px, x0, y0)


def _fit_steps(patch: np.ndarray, contour: np.ndarray, grown: np.ndarray,
               landmarks: np.ndarray, side: str, radius_px: float | None, x0: int, y0: int
               ) -> IrisFit | None:
    """:func:`fit_iris` after the crop (``patch`` float32 at (``x0``, ``y0``) px of the
    frame, the reader's ``contour`` in it and that ``grown``), step by step (the reference
    of :func:`~articast.core.faces.kernels.iris_fit`)."""
    inside = patch[contour > 0]
    outside = patch[grown == 0]
    if inside.size < 12 or outside.size < 12:
        return None
    srt = np.sort(inside)
    n = srt.size
    thr = float(srt[n // 10] + srt[(9 * n) // 10]) / 2.0
    nd = int(np.searchsorted(srt, thr))
    if nd < 4 or n - nd < 4:
        return None
    iris_l, white = float(srt[nd // 2]), float(srt[nd + (3 * (n - nd)) // 4])
    skin = float(np.partition(outside, outside.size // 2)[outside.size // 2])
    if white - iris_l < 20.0:
        return None  # no iris/white contrast (a closed or unlit eye)
    # --- the iris's chords
    wgt = np.clip(thr - patch, 0.0, None) * contour
    if float(wgt.sum()) <= 0:
        return None
    cx0 = float((wgt.sum(0) * np.arange(patch.shape[1])).sum() / wgt.sum())
    widths, cxs, bounded = _chords(patch, contour, grown, thr, iris_l, white, cx0)
    rows = _iris_rows(widths, bounded, radius_px)
    if rows is None:
        return None
    keep, r, half = rows
    levels = ((skin, white, iris_l) if white - skin >= LEVELS_MIN_CONTRAST
              and _former_accepts(patch, grown, iris_l, white, cx0, radius_px) else None)
    ys = np.flatnonzero(keep).astype(np.float64)
    wk = widths[keep]
    height = kernels.iris_circle_height if kernels.AVAILABLE else _circle_height
    cy = float(height(ys, wk, r, np.arange(ys[0] - r, ys[-1] + r, 0.5)))  # coarse,
    cy = float(height(ys, wk, r, cy + _FINE))  # then fine
    cx = float((cxs[keep] * wk).sum() / wk.sum())
    if white - skin < LEVELS_MIN_CONTRAST:
        # a sclera no brighter than the skin round the eye (shaded under the brow and the
        # lid, the skin lit: desk webcams, cap12, cap13): the pixels cannot tell the opening
        # from the skin, and the reader's corners are its only evidence; the opening's
        # widest row joins its corners, so their midpoint is its centre (noisier: ~1 px of
        # the corners' jitter, docs/UPPER_FACE.md)
        lm = np.asarray(landmarks, np.float64)
        ex, ey = (lm[EYE_CORNERS[side][0], :2] + lm[EYE_CORNERS[side][1], :2]) / 2.0 - [x0, y0]
        return IrisFit(np.array([cx + x0, cy + y0]), half, np.array([ex + x0, ey + y0]),
                       int(keep.sum()), levels)
    # --- the eye opening's own centre: the upper lid's dark lash line covers the opening's
    # top, so the white alone puts the lid's margin at the line's lower edge (its widest row
    # 0.44 mm low on the synthetic eye), the white with what is darker than the skin at its
    # upper edge (0.29 mm high); the margin is taken between the two (the line straddles it:
    # docs/UPPER_FACE.md), the mean of both openings' centres (-0.08 mm; both agree, +0.06
    # and +0.01 mm, on an eye without a lash line)
    white_frac = np.clip((patch - skin) / (white - skin), 0.0, 1.0) * (grown > 0)
    fracs = [white_frac]
    if skin - iris_l >= LEVELS_MIN_CONTRAST:  # (a lash line darker than the skin can be told)
        dark = np.clip((skin - patch) / (skin - iris_l), 0.0, 1.0) * (grown > 0)
        fracs.append(np.maximum(white_frac, dark))
    eyes = _opening_centres(fracs)
    if eyes[0] is None:
        return None
    ex, ey = (eyes[0] if len(eyes) < 2 or eyes[1] is None
              else ((eyes[0][0] + eyes[1][0]) / 2.0, (eyes[0][1] + eyes[1][1]) / 2.0))
    return IrisFit(np.array([cx + x0, cy + y0]), half, np.array([ex + x0, ey + y0]),
                   int(keep.sum()), levels)


ROW_WHITE = 0.75
"""A row's side is sclera when its brightest pixel inside the reader's contour is at least
this far from the iris's grey to that side's white (:func:`_chords`): a lid's skin in the
contour, on the rendered eye about half way from the iris to the white, is not (with it
taken for sclera, the rendered eye rolled by 8 deg read 0.8 px off)."""


def _chords(patch: np.ndarray, contour: np.ndarray, grown: np.ndarray, thr: float,
            iris: float, white: float, cx0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's iris chord (widths, centres px, bounded): the run of iris round the
    row's dark pixel nearest ``cx0``, bounded on both sides by sclera, each pixel counted
    by its iris fraction (sub-pixel), as :func:`fit_iris` describes, with **each side's own
    white**: the row's brightest pixel on that side inside the ``contour``. The sclera is a
    sphere lit from one side and shaded by the lids and the brow: its grey differs between
    the sides and along the rows (franck's inner white is darker than his outer; cap12's
    right eye's a fifth darker than the 75th percentile ``white``), so one eye-wide white
    (the former bound) left the rows on the shaded side unbounded: their sclera never came
    within 12 % of it. Where the sclera is uniform (the rendered eye) each side's white is
    ``white`` and the chords are the former ones. A row's side counts as sclera when its
    white is :data:`ROW_WHITE` of the way from ``iris`` to the side's own (the 75th
    percentile of that side's bright pixels; a lid's skin in the contour is not sclera);
    a specular glint narrower than 3 px is removed first (a grey opening along the rows: it
    would end the chord inside the iris; a monotonic edge is kept as it is)."""
    p = cv2.morphologyEx(patch, cv2.MORPH_OPEN, _GLINT)
    if kernels.AVAILABLE and p.shape[1] <= kernels.IRIS_MAX_WIDTH:  # the same numbers in one
        # compiled call (the numpy below: the reference)
        return kernels.iris_chords(p, contour, grown, thr, iris, white, cx0, ROW_WHITE)
    return _chords_numpy(p, contour, grown, thr, iris, white, cx0)


def _chords_numpy(p: np.ndarray, contour: np.ndarray, grown: np.ndarray, thr: float,
                  iris: float, white: float, cx0: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_chords` after the opening of the patch (``p``), in numpy (the reference of
    :func:`~articast.core.tracking.kernels.iris_chords`)."""
    h, w = p.shape
    cols = np.arange(w, dtype=np.float64)
    ri = np.arange(h)
    inside = contour > 0
    dist = np.where((p < thr) & inside, np.abs(cols - cx0)[None, :], np.inf)
    j = np.argmin(dist, axis=1)
    rows_ok = dist[ri, j] < 0.25 * w
    left = cols[None, :] < j[:, None]
    bright = inside & (p >= thr)
    white_l, white_r = (_white(p[bright & (cols[None, :] < cx0)], white),
                        _white(p[bright & (cols[None, :] >= cx0)], white))
    lo = np.where(left & inside, p, -np.inf).max(1)
    hi = np.where(~left & inside, p, -np.inf).max(1)
    rows_ok &= (lo - iris >= ROW_WHITE * (white_l - iris)) & (
        hi - iris >= ROW_WHITE * (white_r - iris))
    side = np.where(left, lo[:, None], hi[:, None])  # each pixel's row's side's white
    cov = np.clip((side - p) / np.maximum(side - iris, 1e-6), 0.0, 1.0) * (grown > 0)
    return _runs_round(cov, j, rows_ok, grown)


def _runs_round(cov: np.ndarray, j: np.ndarray, rows_ok: np.ndarray, grown: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's run of iris (``cov``: the pixels' iris fractions) round its column ``j``,
    ended where the fraction falls to 0.12 (white, or outside the grown contour): widths
    (the fractions' sum), centres px, and whether the row (``rows_ok``) is bounded inside
    the ``grown`` contour on both sides."""
    h, w = cov.shape
    cols = np.arange(w, dtype=np.float64)
    ri = np.arange(h)
    brk = cov <= 0.12  # white, or outside: a chord's bound
    run = np.cumsum(brk, axis=1)
    mine = (run == run[ri, j][:, None]) & ~brk
    first = np.argmax(mine, axis=1)
    last = w - 1 - np.argmax(mine[:, ::-1], axis=1)
    bounded = rows_ok & (first > 0) & (last < w - 1)
    bounded &= grown[ri, np.maximum(first - 1, 0)] > 0
    bounded &= grown[ri, np.minimum(last + 1, w - 1)] > 0
    widths = (cov * mine).sum(1)
    cxs = (cov * mine * cols).sum(1) / np.maximum(widths, 1e-9)
    return widths, cxs, bounded


def _iris_rows(widths: np.ndarray, bounded: np.ndarray, radius_px: float | None
               ) -> tuple[np.ndarray, float, float] | None:
    """The rows whose chords an iris of radius r can have (bounded, no wider than 2 r + 1
    px), r (``radius_px``, else the widest bounded chord / 2) and that half width; None with
    fewer than :data:`IRIS_MIN_ROWS` of them or r under 1.5 px."""
    half = float(widths[bounded].max()) / 2.0 if bounded.any() else 0.0
    r = float(radius_px) if radius_px else half
    keep = bounded & (widths <= 2.0 * r + 1.0) & (widths > 0.5)
    if keep.sum() < IRIS_MIN_ROWS or r < 1.5:
        return None
    return keep, r, half


def _former_accepts(patch: np.ndarray, grown: np.ndarray, iris: float, white: float,
                    cx0: float, radius_px: float | None) -> bool:
    """Whether the iris fit before the shaded scleras would have fitted this eye (its
    chords bounded by one eye-wide white, ``IRIS_MIN_ROWS`` of them): only such fits give
    the closure's measures their grey levels (:class:`IrisFit` ``levels``). The closure's
    calibration (the lid gap's and the iris height's levels, which measure is kept, the brow
    band's floor) was chosen on these frames; letting the newly fitted ones in moved
    franck's blink recall from 1.00 to 0.93 and pexels_woman's from 1.00 to 0.75 (its right
    eye then took the lid gap), a change for the closure's owner to make on its own
    evidence, not a side effect of the gaze (docs/UPPER_FACE.md)."""
    if kernels.AVAILABLE and patch.shape[1] <= kernels.IRIS_MAX_WIDTH:  # the same numbers,
        # one compiled call
        widths, bounded = kernels.iris_former_rows(patch, grown, iris, white, cx0)
    else:
        widths, bounded = _former_rows_numpy(patch, grown, iris, white, cx0)
    return _iris_rows(widths, bounded, radius_px) is not None


def _former_rows_numpy(patch: np.ndarray, grown: np.ndarray, iris: float, white: float,
                       cx0: float) -> tuple[np.ndarray, np.ndarray]:
    """The chords' widths and bounded rows of :func:`_former_accepts`, in numpy (the
    reference of :func:`~articast.core.tracking.kernels.iris_former_rows`)."""
    cov = np.clip((white - patch) / (white - iris), 0.0, 1.0) * (grown > 0)
    w = patch.shape[1]
    dist = np.where(cov > 0.5, np.abs(np.arange(w) - cx0)[None, :], np.inf)
    j = np.argmin(dist, axis=1)
    widths, _, bounded = _runs_round(cov, j, dist[np.arange(len(j)), j] < 0.25 * w, grown)
    return widths, bounded


def _white(vals: np.ndarray, white: float) -> float:
    """One side's white: the 75th percentile of its pixels brighter than the eye's midway
    (as :func:`fit_iris`'s ``white``), the eye's ``white`` when it has fewer than 4."""
    if vals.size < 4:
        return white
    v = np.sort(vals)
    return float(v[(3 * v.size) // 4])


def _opening_centres(fracs: list[np.ndarray]) -> list[tuple[float, float] | None]:
    """(x, y) px in the crop of each opening given by its pixels' fractions (0 .. 1; arrays
    of one shape): vertically its widest row (a parabola through the widths round the
    widest), horizontally the middle of its ends on the rows within 2 of it (ends sub-pixel
    from the next pixel's fraction); None for an opening with fewer than 3 rows. (The rows of
    all of them in one array: the row-wise steps once.)"""
    frac = np.concatenate(fracs, axis=0) if len(fracs) > 1 else fracs[0]
    if kernels.AVAILABLE and frac.dtype == np.float32:  # the same numbers in one compiled
        # call (the numpy below: the reference)
        got = kernels.opening_centres(np.ascontiguousarray(frac), len(fracs))
        return [(float(x), float(y)) if found else None for x, y, found in got]
    return _opening_centres_numpy(fracs[0].shape, frac, len(fracs))


def _opening_centres_numpy(shape: tuple[int, ...], frac: np.ndarray, n_open: int
                           ) -> list[tuple[float, float] | None]:
    """:func:`_opening_centres` of the ``n_open`` openings of ``shape`` stacked in ``frac``,
    in numpy (the reference of :func:`~articast.core.tracking.kernels.opening_centres`)."""
    rows, cols = shape
    bright = frac >= 0.5
    has = np.asarray(bright.any(axis=1))
    a = np.argmax(bright, axis=1)
    b = cols - 1 - np.argmax(bright[:, ::-1], axis=1)
    ri = np.arange(len(a))
    left = a - 0.5 - np.where(a > 0, frac[ri, np.maximum(a - 1, 0)], 0.0)
    right = b + 0.5 + np.where(b < cols - 1, frac[ri, np.minimum(b + 1, cols - 1)], 0.0)
    widths = np.where(has, right - left, 0.0)
    mids = (left + right) / 2.0
    out: list[tuple[float, float] | None] = []
    for n in range(n_open):
        sl = slice(n * rows, (n + 1) * rows)
        if int(has[sl].sum()) < 3:
            out.append(None)
            continue
        width, mid = widths[sl], mids[sl]
        k = int(np.argmax(width))
        near = (np.abs(ri[:rows] - k) <= 2) & (width > 0.6 * width[k])
        ex = float(mid[near].mean())
        ey = float(k)
        lo, hi = max(k - 3, 0), min(k + 4, rows)
        pts = [(float(t - k), w) for t, w in zip(range(lo, hi), width[lo:hi].tolist(),
                                                  strict=True) if w > 0]
        if len(pts) >= 3:  # a parabola through the widths round the widest row
            a2, b2 = _parabola(pts)
            if a2 < 0 and abs(b2 / (2.0 * a2)) <= 1.5:
                ey = k - b2 / (2.0 * a2)
        out.append((ex, ey))
    return out


def _parabola(pts: list[tuple[float, float]]) -> tuple[float, float]:
    """(a, b) of the least-squares parabola a t^2 + b t + c through the points (t, w)
    (3 or more, t distinct), by the normal equations in closed form (a 3 x 3 system: numpy's
    solver costs more than the sums on these 3-7 points)."""
    t = np.array([p[0] for p in pts], np.float64)
    w = np.array([p[1] for p in pts], np.float64)
    a, b = kernels.parabola_of(t, w, len(pts))  # (compiled; plain Python without numba)
    return float(a), float(b)

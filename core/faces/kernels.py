"""Compiled steps of the upper face's pixel measures (:mod:`articast.core.faces.iris`).

:func:`iris_fit` is :func:`~articast.core.faces.iris.fit_iris` after its crop, in one call:
the grey levels, the dark centroid, the chords, the circle's height and the opening's
centres (some 30 small numpy calls per eye before, ~0.2 ms of a reading's frame). It is
the same arithmetic as the step-by-step code (:func:`~articast.core.faces.iris._fit_steps`,
the reference, which a test compares it with): numpy's float32 operations where numpy does
them in float32, its pairwise sums (:func:`~articast.core.tracking.kernels._pairwise_sum`)
where numpy sums a row or a whole array, its row-by-row accumulation where it sums down the
columns, its ``arange`` fill; so the same numbers to the bit. The compiled chords, circle
search and opening centres it calls are :mod:`articast.core.tracking.kernels`' own.

Compiled with numba when available (``ARTICAST_JIT=0`` or numba missing: the step-by-step
code runs); cached on disk like the tracker's kernels.
"""

from __future__ import annotations

import os

import numpy as np

from articast.core.outputs import lips
from articast.core.tracking.kernels import (
    AVAILABLE,
    _pairwise_sum,
    iris_chords,
    iris_circle_height,
    iris_former_rows,
    njit,
    opening_centres,
)

__all__ = ["AVAILABLE", "IRIS_MAX_PIXELS", "aligned", "compiled_on_disk", "iris_fit", "warm_up"]

IRIS_MAX_PIXELS = 4096
"""The largest eye crop (rows x columns) :func:`iris_fit` takes: its whole-crop pairwise sum
is numpy's up to this length (a larger crop is fitted step by step)."""


@njit(cache=True, nogil=True)
def _arange(start, stop, step):  # pragma: no cover - compiled
    """``np.arange(start, stop, step)`` of floats as numpy fills it (its second value minus
    its first as the step of the rest)."""
    n = int(np.ceil((stop - start) / step))
    out = np.empty(max(n, 0))
    if n >= 1:
        out[0] = start
    if n >= 2:
        out[1] = start + step
        d = out[1] - out[0]
        for i in range(2, n):
            out[i] = start + i * d
    return out


@njit(cache=True, nogil=True)
def _kth(hist, k):  # pragma: no cover - compiled
    """The k-th (from 0) of the sorted values whose histogram over 0..255 is ``hist``, as
    float32 (the crop's dtype)."""
    seen = 0
    for v in range(256):
        seen += hist[v]
        if seen > k:
            return np.float32(v)
    return np.float32(255.0)


@njit(cache=True, nogil=True)
def _iris_rows(widths, bounded, radius_px, min_rows):  # pragma: no cover - compiled
    """iris._iris_rows: (found, keep, r, half); ``radius_px`` 0: none given."""
    h = widths.shape[0]
    any_b = False
    top = np.float32(0.0)
    for y in range(h):
        if bounded[y] and (not any_b or widths[y] > top):
            top = widths[y]
            any_b = True
    half = np.float64(top) / 2.0 if any_b else 0.0
    r = radius_px if radius_px != 0.0 else half
    wide32 = np.float32(2.0 * r + 1.0)  # (numpy compares the float32 widths in float32)
    least = np.float32(0.5)
    keep = np.zeros(h, np.bool_)
    n = 0
    for y in range(h):
        if bounded[y] and widths[y] <= wide32 and widths[y] > least:
            keep[y] = True
            n += 1
    return n >= min_rows and r >= 1.5, keep, r, half


@njit(cache=True, nogil=True)
def _tdiv(a, b):  # pragma: no cover - compiled
    """C's integer division of ``a`` by ``b`` != 0 (rounded toward zero, not floored)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


@njit(cache=True, nogil=True)
def _line8(mask, xa, ya, xb, yb):  # pragma: no cover - compiled
    """Set the pixels of OpenCV's 8-connected line from (xa, ya) to (xb, yb) px (both inside
    ``mask``) to 1: its ``LineIterator``, left to right, one step along the longer axis a
    pixel, one along the other where the error goes negative."""
    dx, dy = xb - xa, yb - ya
    if dx < 0:
        xa, ya, dx, dy = xb, yb, -dx, -dy
    sy = 1
    if dy < 0:
        dy, sy = -dy, -1
    steep = dy > dx
    if steep:
        dx, dy = dy, dx
    err = dx - 2 * dy
    x, y = xa, ya
    for _ in range(dx + 1):
        mask[y, x] = 1
        if err < 0:
            err += 2 * dx - 2 * dy
            x += 1
            y += sy
        else:
            err -= 2 * dy
            if steep:
                y += sy
            else:
                x += 1


_XY_SHIFT = 16  # (OpenCV's drawing: x in 16.16 fixed point)


@njit(cache=True, nogil=True)
def _contour(poly, x0, y0, h, w):  # pragma: no cover - compiled
    """``cv2.fillPoly`` of the (n, 2) float64 polygon ``poly`` px, less (``x0``, ``y0``) and
    rounded (numpy's round, half to even), with 1 on an (h, w) uint8 zero mask: the points
    must fall inside it (fit_iris's crop: the contour grown by 3 px). OpenCV's own integer
    steps (drawing.cpp, 8-connected lines, shift 0): each edge drawn as a line, then the
    scan lines filled between pairs of the edges' 16.16 fixed-point crossings in x order
    (each edge's crossing its top's x stepped by its dx a line, dx C's division rounded
    toward zero), so the same pixels, without a cold OpenCV call and its arguments'
    conversions (~1 s more compile from an empty cache than OpenCV's own edge list, its
    sorts and bubble sort written out, which gave the same pixels)."""
    n = poly.shape[0]
    px = np.empty(n, np.int64)
    py = np.empty(n, np.int64)
    for k in range(n):
        px[k] = int(np.rint(poly[k, 0] - np.float64(x0)))
        py[k] = int(np.rint(poly[k, 1] - np.float64(y0)))
    mask = np.zeros((h, w), np.uint8)
    ey0 = np.empty(n, np.int64)
    ey1 = np.empty(n, np.int64)
    ex = np.empty(n, np.int64)
    edx = np.empty(n, np.int64)
    total = 0
    xa, ya = px[n - 1], py[n - 1]
    for k in range(n):  # CollectPolyEdges
        xb, yb = px[k], py[k]
        _line8(mask, xa, ya, xb, yb)
        if ya != yb:
            if ya < yb:
                ey0[total], ey1[total], ex[total] = ya, yb, xa << _XY_SHIFT
            else:
                ey0[total], ey1[total], ex[total] = yb, ya, xb << _XY_SHIFT
            edx[total] = _tdiv((xb - xa) << _XY_SHIFT, yb - ya)
            total += 1
        xa, ya = xb, yb
    if total < 2:
        return mask
    # FillEdgeCollection, per scan line: OpenCV keeps the edges the line crosses in a list
    # in x order (new edges put in place, a bubble sort after each line) and steps each by
    # its dx once a line, filling between the first and second, third and fourth...; the
    # same crossings sorted here each line (equal x's give the same spans in any order)
    y_lo, y_hi = ey0[0], ey1[0]
    for k in range(total):
        y_lo, y_hi = min(y_lo, ey0[k]), max(y_hi, ey1[k])
    xs = np.empty(total, np.int64)
    one = 1 << _XY_SHIFT
    for y in range(max(y_lo, 0), min(y_hi, h)):
        m = 0
        for k in range(total):
            if ey0[k] <= y < ey1[k]:
                v = ex[k] + (y - ey0[k]) * edx[k]
                j = m  # (an insertion sort)
                while j > 0 and xs[j - 1] > v:
                    xs[j] = xs[j - 1]
                    j -= 1
                xs[j] = v
                m += 1
        for k in range(0, m - 1, 2):
            for xx in range(max((xs[k] + one - 1) >> _XY_SHIFT, 0),
                            min(xs[k + 1] >> _XY_SHIFT, w - 1) + 1):
                mask[y, xx] = 1
    return mask


@njit(cache=True, nogil=True)
def _slide(a, half, along_x, largest):  # pragma: no cover - compiled
    """OpenCV's flat morphology of the (h, w) ``a`` along one axis: each pixel the largest
    (``largest``; dilation) or smallest (erosion) of the ``2 * half + 1`` along its row
    (``along_x``) or its column, inside the array (OpenCV leaves out what lies outside)."""
    h, w = a.shape
    out = np.empty_like(a)
    for y in range(h):
        for x in range(w):
            m = a[y, x]
            if along_x:
                for k in range(max(0, x - half), min(w, x + half + 1)):
                    v = a[y, k]
                    if (v > m) if largest else (v < m):
                        m = v
            else:
                for k in range(max(0, y - half), min(h, y + half + 1)):
                    v = a[k, x]
                    if (v > m) if largest else (v < m):
                        m = v
            out[y, x] = m
    return out


@njit(cache=True, nogil=True)
def _grown(contour):  # pragma: no cover - compiled
    """``cv2.dilate(contour, iris._GROW)`` of the (h, w) uint8 mask: a row's 5-wide maximum,
    then a column's (the same maxima as the 5 x 5 square's)."""
    return _slide(_slide(contour, 2, True, True), 2, False, True)


@njit(cache=True, nogil=True)
def _opened(patch):  # pragma: no cover - compiled
    """``cv2.morphologyEx(patch, cv2.MORPH_OPEN, iris._GLINT)`` of the (h, w) float32 patch:
    its 3-wide row minimum (erosion), then that's 3-wide row maximum (dilation)."""
    return _slide(_slide(patch, 1, True, False), 1, True, True)


@njit(cache=True, nogil=True)
def iris_fit(crop, poly, x0, y0, radius_px, fine, row_white, min_rows,
             min_contrast):  # pragma: no cover - compiled
    """iris.fit_iris in the eye's crop: ``crop`` (h, w) uint8 grey at (``x0``, ``y0``) px
    of the frame (whole grey levels 0..255: their order statistics are taken from
    histograms; the step-by-step code's float32 ``patch``), ``poly`` (n, 2) float64 the
    reader's eye contour px (its mask ``contour``, that mask's dilation ``grown`` and the
    patch's (1, 3) opening, the chords' glint removal, are made here: :func:`_contour`,
    :func:`_grown`, :func:`_opened`, OpenCV's own numbers without three cold OpenCV calls,
    ~40 us a reading's eye in the live loop), ``radius_px`` the speaker's iris radius px
    (0: this frame's widest chord), ``fine`` iris._FINE, ``row_white`` iris.ROW_WHITE,
    ``min_rows`` iris.IRIS_MIN_ROWS, ``min_contrast`` lids.LEVELS_MIN_CONTRAST.

    Returns (status, cx, cy, half, ex, ey, rows, skin, white, iris, levels): status 0 no
    fit (fit_iris's None), 1 fitted, 2 fitted on a sclera no brighter than the skin (ex, ey
    not measured: the caller takes the corners' midpoint); (cx, cy) the circle's centre and
    (ex, ey) the opening's, px in the crop; ``levels`` whether the grey levels are given
    (iris._former_accepts)."""
    h, w = crop.shape
    patch = crop.astype(np.float32)
    contour = _contour(poly, x0, y0, h, w)
    grown = _grown(contour)
    fail = (0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0.0, 0.0, 0.0, False)
    # the grey levels' order statistics from their histograms (the values are whole grey
    # levels 0..255: the k-th of the sorted values is the level where the count passes k)
    hist_in = np.zeros(256, np.int64)
    hist_out = np.zeros(256, np.int64)
    for y in range(h):
        for x in range(w):
            if contour[y, x] > 0:
                hist_in[int(patch[y, x])] += 1
            if grown[y, x] == 0:
                hist_out[int(patch[y, x])] += 1
    n = 0
    n_out = 0
    for v in range(256):
        n += hist_in[v]
        n_out += hist_out[v]
    if n < 12 or n_out < 12:
        return fail
    thr = np.float64(_kth(hist_in, n // 10) + _kth(hist_in, (9 * n) // 10)) / 2.0
    nd = 0  # (np.searchsorted: the values below thr)
    for v in range(256):
        if np.float64(v) < thr:
            nd += hist_in[v]
    if nd < 4 or n - nd < 4:
        return fail
    iris = np.float64(_kth(hist_in, nd // 2))
    white = np.float64(_kth(hist_in, nd + (3 * (n - nd)) // 4))
    skin = np.float64(_kth(hist_out, n_out // 2))
    if white - iris < 20.0:
        return fail
    # the dark centroid: the weights' column sums row by row, as numpy's sum(0)
    thr32 = np.float32(thr)
    zero = np.float32(0.0)
    wgt = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            v = thr32 - patch[y, x]
            wgt[y, x] = (v if v > zero else zero) * np.float32(contour[y, x])
    total = _pairwise_sum(wgt.ravel(), 0, h * w)
    if not total > zero:
        return fail
    col = wgt[0].copy()
    for y in range(1, h):
        for x in range(w):
            col[x] += wgt[y, x]
    moment = np.empty(w)
    for x in range(w):
        moment[x] = np.float64(col[x]) * np.float64(x)
    cx0 = _pairwise_sum(moment, 0, w) / np.float64(total)
    widths, cxs, bounded = iris_chords(_opened(patch), contour, grown, thr, iris, white, cx0,
                                       row_white)
    found, keep, r, half = _iris_rows(widths, bounded, radius_px, min_rows)
    if not found:
        return fail
    levels = False
    if white - skin >= min_contrast:
        w2, b2 = iris_former_rows(patch, grown, iris, white, cx0)
        levels = _iris_rows(w2, b2, radius_px, min_rows)[0]
    nk = 0
    for y in range(h):
        if keep[y]:
            nk += 1
    ys = np.empty(nk)
    wk = np.empty(nk, np.float32)
    wc = np.empty(nk)
    i = 0
    for y in range(h):
        if keep[y]:
            ys[i] = np.float64(y)
            wk[i] = widths[y]
            wc[i] = cxs[y] * np.float64(widths[y])
            i += 1
    cy = iris_circle_height(ys, wk, r, _arange(ys[0] - r, ys[nk - 1] + r, 0.5))  # coarse,
    cy = iris_circle_height(ys, wk, r, cy + fine)  # then fine
    cx = _pairwise_sum(wc, 0, nk) / np.float64(_pairwise_sum(wk, 0, nk))
    if white - skin < min_contrast:
        return (2, cx, cy, half, 0.0, 0.0, nk, skin, white, iris, levels)
    # the opening: the white, and the white or what is darker than the skin (iris.fit_iris)
    skin32 = np.float32(skin)
    span_w = np.float32(white - skin)
    span_d = np.float32(skin - iris)
    dark = skin - iris >= min_contrast
    one = np.float32(1.0)
    frac = np.empty((2 * h if dark else h, w), np.float32)
    for y in range(h):
        for x in range(w):
            if grown[y, x] == 0:
                frac[y, x] = zero
                if dark:
                    frac[h + y, x] = zero
                continue
            v = (patch[y, x] - skin32) / span_w
            v = zero if v < zero else (one if v > one else v)
            frac[y, x] = v
            if dark:
                d = (skin32 - patch[y, x]) / span_d
                d = zero if d < zero else (one if d > one else d)
                frac[h + y, x] = v if v >= d else d
    eyes = opening_centres(frac, 2 if dark else 1)
    if eyes[0, 2] == 0.0:
        return fail
    ex, ey = eyes[0, 0], eyes[0, 1]
    if dark and eyes[1, 2] != 0.0:
        ex, ey = (eyes[0, 0] + eyes[1, 0]) / 2.0, (eyes[0, 1] + eyes[1, 1]) / 2.0
    return (1, cx, cy, half, ex, ey, nk, skin, white, iris, levels)


@njit(cache=True, nogil=True)
def _det3(m):  # pragma: no cover - compiled
    """The determinant of a 3 x 3 matrix by its first row's cofactors (upper._det3)."""
    return (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
            - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))


@njit(cache=True, nogil=True)
def _svd3(a):  # pragma: no cover - compiled
    """(u, s, vt) of a 3 x 3 matrix, ``np.linalg.svd``'s to rounding (s descending; each
    pair of singular vectors up to a common sign): one-sided Jacobi rotations of its columns
    until every pair is orthogonal to the machine's precision (Hestenes), then u's columns
    the rotated columns over their norms, the third u's first two's cross product (signed as
    the rotated column: exact where that column is ~0). A few dozen operations in place of
    LAPACK's SVD, whose code, cold after the landmark network's run, cost ~35 us a call in
    the live loop (against ~1 us warm)."""
    w = a.copy()
    v = np.eye(3)
    eps = 2.220446049250313e-16
    for _ in range(30):
        rotated = False
        for p in range(2):
            for q in range(p + 1, 3):
                al = w[0, p] * w[0, p] + w[1, p] * w[1, p] + w[2, p] * w[2, p]
                be = w[0, q] * w[0, q] + w[1, q] * w[1, q] + w[2, q] * w[2, q]
                ga = w[0, p] * w[0, q] + w[1, p] * w[1, q] + w[2, p] * w[2, q]
                if ga == 0.0 or abs(ga) <= eps * np.sqrt(al * be):
                    continue
                rotated = True
                zeta = (be - al) / (2.0 * ga)
                t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
                c = 1.0 / np.sqrt(1.0 + t * t)
                sn = c * t
                for r in range(3):
                    x, y = w[r, p], w[r, q]
                    w[r, p], w[r, q] = c * x - sn * y, sn * x + c * y
                    x, y = v[r, p], v[r, q]
                    v[r, p], v[r, q] = c * x - sn * y, sn * x + c * y
        if not rotated:
            break
    norms = np.empty(3)
    for k in range(3):
        norms[k] = np.sqrt(w[0, k] * w[0, k] + w[1, k] * w[1, k] + w[2, k] * w[2, k])
    order = np.empty(3, np.int64)  # (descending, the first of equals first)
    for k in range(3):
        order[k] = k
    for i in range(3):
        for j in range(2 - i):
            if norms[order[j]] < norms[order[j + 1]]:
                order[j], order[j + 1] = order[j + 1], order[j]
    u = np.zeros((3, 3))
    sv = np.empty(3)
    vt = np.empty((3, 3))
    for j in range(3):
        k = order[j]
        sv[j] = norms[k]
        for r in range(3):
            vt[j, r] = v[r, k]
            if j < 2 and norms[k] > 0.0:
                u[r, j] = w[r, k] / norms[k]
    c0 = u[1, 0] * u[2, 1] - u[2, 0] * u[1, 1]
    c1 = u[2, 0] * u[0, 1] - u[0, 0] * u[2, 1]
    c2 = u[0, 0] * u[1, 1] - u[1, 0] * u[0, 1]
    k = order[2]
    sign = -1.0 if c0 * w[0, k] + c1 * w[1, k] + c2 * w[2, k] < 0.0 else 1.0
    u[0, 2], u[1, 2], u[2, 2] = sign * c0, sign * c1, sign * c2
    return u, sv, vt


@njit(cache=True, nogil=True)
def aligned(lm, ids, wn, b, mb):  # pragma: no cover - compiled
    """upper.align in one call (its numpy code, :func:`~articast.core.faces.upper.align_numpy`,
    is the reference; a test checks they agree to rounding): the similarity Procrustes of a
    reading ``lm`` (N, 3) px (x right, y down, z away) onto the canonical face's rigid points
    ``b`` (len(ids), 3) mm, weights ``wn`` (summing to 1), their weighted mean ``mb`` (3,),
    on the reading's points ``ids``. Returns (ok, points (N, 3) mm in the head frame, scale
    px per mm, yaw deg); ok False for a degenerate reading (a point not finite, no spread, a
    scale not positive). The same operations as the numpy code, its sums in another order
    (~25 small numpy calls and the SVD's wrapper, ~0.25 ms of a reading's frame in the live
    loop). The SVD is :func:`_svd3`'s, not LAPACK's (rounding-level differences: the
    test)."""
    n = lm.shape[0]
    m = ids.shape[0]
    fail = (False, np.empty((0, 3)), 0.0, 0.0)
    ma = np.zeros(3)
    for j in range(m):
        i = ids[j]
        ma[0] += wn[j] * lm[i, 0]
        ma[1] += wn[j] * -lm[i, 1]
        ma[2] += wn[j] * -lm[i, 2]
    cov = np.zeros((3, 3))
    var = 0.0
    for j in range(m):
        i = ids[j]
        a0, a1, a2 = lm[i, 0] - ma[0], -lm[i, 1] - ma[1], -lm[i, 2] - ma[2]
        var += wn[j] * (a0 * a0 + a1 * a1 + a2 * a2)
        for r in range(3):
            bw = (b[j, r] - mb[r]) * wn[j]
            cov[r, 0] += bw * a0
            cov[r, 1] += bw * a1
            cov[r, 2] += bw * a2
    for r in range(3):
        for c in range(3):
            if not np.isfinite(cov[r, c]):
                return fail
    u, sv, vt = _svd3(cov)
    d = 1.0 if _det3(u) * _det3(vt) > 0 else -1.0  # (the sign of det(u @ vt), as align's)
    rot = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            rot[r, c] = u[r, 0] * vt[0, c] + u[r, 1] * vt[1, c] + d * u[r, 2] * vt[2, c]
    if var <= 1e-9:
        return fail
    scale = (0.0 + sv[0] + sv[1] + sv[2] * d) / var  # mm per px
    if not np.isfinite(scale) or scale <= 0:
        return fail
    pts = np.empty((n, 3))
    for k in range(n):
        s0, s1, s2 = lm[k, 0] - ma[0], -lm[k, 1] - ma[1], -lm[k, 2] - ma[2]
        for c in range(3):
            pts[k, c] = (s0 * rot[c, 0] + s1 * rot[c, 1] + s2 * rot[c, 2]) * scale + mb[c]
    # rot maps the face's frame as seen to the canonical: its inverse is the head's rotation
    return True, pts, 1.0 / scale, np.degrees(np.arctan2(rot[2, 0], rot[2, 2]))


def warm_up() -> None:
    """Compile (or load from the on-disk cache) :func:`iris_fit`, :func:`aligned` and the lips'
    lengths (:func:`articast.core.outputs.lips.lip_lengths`) for the live fit's types:
    ~3 s of CPU once the tracker's kernels are compiled (a cold cache), ~20 ms loaded from
    the cache; the live tracker calls it when built, before its first frame."""
    if not AVAILABLE:
        return
    u = np.zeros((12, 16), np.uint8)
    iris_fit(u, np.full((3, 2), 4.0), 0, 0, 0.0, np.arange(-0.5, 0.5001, 0.05), 0.75, 3, 8.0)
    aligned(np.zeros((468, 3)), np.arange(4, dtype=np.int32), np.full(4, 0.25), np.zeros((4, 3)),
            np.zeros(3))
    lips.warm_up()  # (the lips' lengths of every live frame)


def compiled_on_disk() -> bool:
    """Whether numba's on-disk cache already holds :func:`iris_fit` and :func:`aligned`
    (False: :func:`warm_up` will compile them, ~4 s); True when it cannot tell (as
    :func:`articast.core.tracking.kernels.compiled_on_disk`)."""
    if not AVAILABLE:
        return True
    try:
        return all(os.path.exists(k._cache._cache_file._index_path)  # noqa: SLF001
                   for k in (iris_fit, aligned, lips.lip_lengths))
    except AttributeError:  # another numba's internals
        return True

"""Compiled inner loop of the la cost: sampling, descriptors, residuals and their Jacobian.

:meth:`articast.core.tracking.fitting.Problem.residuals` is the definition (numpy, readable,
the reference);
this is the same computation fused into one pass over the sample points, compiled with
numba. At ~50 points the numpy version is bound by the overhead of its ~60 array operations
(~330 us per evaluation on this project's machine); the fused loop does the same arithmetic
in a few tens of microseconds. Tests check that both give the same numbers.

Lazy maps (:class:`core.appearance.ImageMaps` made with ``lazy=True``): the kernel also
Gaussian-smooths the full-resolution image itself, one pixel when a sample first reads it
(:func:`_smooth_pixel`), instead of the tracker blurring the whole face box every frame.

:func:`fit_terms` is one Gauss-Newton evaluation of
:func:`articast.core.tracking.fitting.fit_gauss_newton` in one call (the la cost with its
rotation terms, the Cauchy weights, the landmark term, the priors), the dense products left to
numpy's BLAS: assembled in numpy, the ~40 small array operations around the kernels cost as
much as the la kernel itself (~0.3 ms a frame of fused live tracking).

``ARTICAST_JIT=0`` in the environment (or numba missing) selects the numpy path.
Compiled functions are cached on disk (numba's ``cache=True``) so only the first process
pays the compilation (a few seconds).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

try:  # pragma: no cover - exercised by whichever path the environment has
    if os.environ.get("ARTICAST_JIT", "1") == "0":
        raise ImportError("disabled by ARTICAST_JIT=0")
    from numba import njit

    AVAILABLE = True
except ImportError:  # pragma: no cover
    AVAILABLE = False

    def njit(*args, **kwargs):
        def wrap(f):
            return f
        return wrap

# descriptor column -> (quantity, channel): quantity 0 = S, 1 = Sx, 2 = Sy; channel Y, Cr, Cb
# order of LA_CHANNELS: Yx Yy Cr Crx Cry Cb Cbx Cby
_QUANTITY = np.array([1, 2, 0, 1, 2, 0, 1, 2], np.int64)
_CHANNEL = np.array([0, 0, 1, 1, 1, 2, 2, 2], np.int64)
_OFFSET = np.array([0.0, 0.0, 128.0, 0.0, 0.0, 128.0, 0.0, 0.0])


@njit(cache=True, nogil=True, inline="always")
def _reflect(i, n):  # pragma: no cover - compiled
    """OpenCV's default border (BORDER_REFLECT_101): ... 2 1 | 0 1 2 ... n-1 | n-2 ..."""
    if i < 0:
        i = -i
    if i >= n:
        i = 2 * n - 2 - i
    return min(max(i, 0), n - 1)


@njit(cache=True, nogil=True)
def _smooth_pixel(src, sm, done, rows, rdone, taps, y, x):  # pragma: no cover - compiled
    """Gaussian-smooth pixel (y, x) of src into sm (separable: a horizontal pass kept per
    pixel in rows, then a vertical pass), unless done already: :func:`_smooth_column` of one
    pixel."""
    _smooth_column(src, sm, done, rows, rdone, taps, x, y, y, np.empty(taps.shape[0] + 3,
                                                                         np.int64))


@njit(cache=True, nogil=True)
def _smooth_column(src, sm, done, rows, rdone, taps, x, y0, y1,
                   need):  # pragma: no cover - compiled
    """Gaussian-smooth the pixels (y0..y1, x) of src into sm that are not done (at most 4;
    separable: a horizontal pass kept per pixel in rows, then a vertical pass). Each value is
    summed in the same order as ever, tap by tap in float64 and kept in float32; the passes
    of up to four rows (or pixels) run side by side, so that their sums do not wait on each
    other (one pass's 17 sums are a chain of dependent additions). ``need`` : a scratch
    buffer of at least len(taps) + 3 ints."""
    h, w = src.shape[0], src.shape[1]
    n = taps.shape[0]
    rad = n // 2
    # the row passes the pixels read that no earlier pixel did
    cnt = 0
    for y in range(y0, y1 + 1):
        if done[y, x]:
            continue
        for j in range(-rad, rad + 1):
            yy = _reflect(y + j, h)
            if rdone[x, yy]:
                continue
            rdone[x, yy] = 1
            need[cnt] = yy
            cnt += 1
    inside = x - rad >= 0 and x + rad < w
    i = 0
    while i + 4 <= cnt:
        _rows4(src, rows, taps, x, inside, need[i], need[i + 1], need[i + 2], need[i + 3])
        i += 4
    while i < cnt:
        yy = need[i]
        r0 = r1 = r2 = 0.0
        for m in range(n):
            xx = x - rad + m if inside else _reflect(x - rad + m, w)
            r0, r1, r2 = _tap3(src, yy, xx, taps[m], r0, r1, r2)
        _put3(rows, x, yy, r0, r1, r2)
        i += 1
    # the vertical passes
    cnt = 0
    for y in range(y0, y1 + 1):
        if not done[y, x]:
            need[cnt] = y
            cnt += 1
    i = 0
    while i + 2 <= cnt:
        ya, yb = need[i], need[i + 1]
        a0 = a1 = a2 = b0 = b1 = b2 = 0.0
        for m in range(n):
            tp = taps[m]
            a0, a1, a2 = _tap3(rows, x, _reflect(ya - rad + m, h), tp, a0, a1, a2)
            b0, b1, b2 = _tap3(rows, x, _reflect(yb - rad + m, h), tp, b0, b1, b2)
        _put3(sm, ya, x, a0, a1, a2)
        _put3(sm, yb, x, b0, b1, b2)
        done[ya, x] = 1
        done[yb, x] = 1
        i += 2
    if i < cnt:
        y = need[i]
        a0 = a1 = a2 = 0.0
        for m in range(n):
            a0, a1, a2 = _tap3(rows, x, _reflect(y - rad + m, h), taps[m], a0, a1, a2)
        _put3(sm, y, x, a0, a1, a2)
        done[y, x] = 1


@njit(cache=True, nogil=True)
def _smooth_cell(src, sm, done, rows, rdone, taps, ix, iy, need):  # pragma: no cover
    """Gaussian-smooth the 12 pixels a sample in the cell (ix, iy) reads (its 2x2 values and
    their central differences: columns ix-1..ix+2), as :func:`_smooth_column` of each of
    its four columns. Away from the left and right borders the four columns' row passes
    run side by side first, each row's pixels read once for the four sums (each summed in
    the same order as ever: the same numbers); the columns' calls then find them done."""
    w = src.shape[1]
    n = taps.shape[0]
    rad = n // 2
    x0 = ix - 1
    if x0 - rad >= 0 and x0 + 3 + rad < w:
        h = src.shape[0]
        for j in range(-rad - 1, rad + 3):  # every row a column's pixels read
            yy = _reflect(iy + j, h)
            if rdone[x0, yy] and rdone[x0 + 1, yy] and rdone[x0 + 2, yy] and rdone[x0 + 3, yy]:
                continue
            _row4(src, rows, taps, x0, yy)
            rdone[x0, yy] = rdone[x0 + 1, yy] = rdone[x0 + 2, yy] = rdone[x0 + 3, yy] = 1
    _smooth_column(src, sm, done, rows, rdone, taps, ix - 1, iy, iy + 1, need)
    _smooth_column(src, sm, done, rows, rdone, taps, ix, iy - 1, iy + 2, need)
    _smooth_column(src, sm, done, rows, rdone, taps, ix + 1, iy - 1, iy + 2, need)
    _smooth_column(src, sm, done, rows, rdone, taps, ix + 2, iy, iy + 1, need)


@njit(cache=True, nogil=True, inline="always")
def _row4(src, rows, taps, x0, yy):  # pragma: no cover - compiled
    """The horizontal passes of row yy at the four columns x0..x0+3 (inside the image), each
    as one column's, the row's pixels loaded once."""
    n = taps.shape[0]
    rad = n // 2
    a0 = a1 = a2 = b0 = b1 = b2 = c0 = c1 = c2 = d0 = d1 = d2 = 0.0
    left = x0 - rad
    # the pixels m, m + 1, m + 2, m + 3 of the window slide along the row
    p0, p1, p2 = float(src[yy, left, 0]), float(src[yy, left, 1]), float(src[yy, left, 2])
    q0, q1, q2 = (float(src[yy, left + 1, 0]), float(src[yy, left + 1, 1]),
                  float(src[yy, left + 1, 2]))
    r0, r1, r2 = (float(src[yy, left + 2, 0]), float(src[yy, left + 2, 1]),
                  float(src[yy, left + 2, 2]))
    for m in range(n):
        tp = taps[m]
        s0, s1, s2 = (float(src[yy, left + m + 3, 0]), float(src[yy, left + m + 3, 1]),
                      float(src[yy, left + m + 3, 2]))
        a0 += tp * p0
        a1 += tp * p1
        a2 += tp * p2
        b0 += tp * q0
        b1 += tp * q1
        b2 += tp * q2
        c0 += tp * r0
        c1 += tp * r1
        c2 += tp * r2
        d0 += tp * s0
        d1 += tp * s1
        d2 += tp * s2
        p0, p1, p2, q0, q1, q2, r0, r1, r2 = q0, q1, q2, r0, r1, r2, s0, s1, s2
    _put3(rows, x0, yy, a0, a1, a2)
    _put3(rows, x0 + 1, yy, b0, b1, b2)
    _put3(rows, x0 + 2, yy, c0, c1, c2)
    _put3(rows, x0 + 3, yy, d0, d1, d2)


@njit(cache=True, nogil=True, inline="always")
def _rows4(src, rows, taps, x, inside, ya, yb, yc, yd):  # pragma: no cover - compiled
    """The horizontal passes of four rows at column x (each as one row's)."""
    w = src.shape[1]
    n = taps.shape[0]
    rad = n // 2
    a0 = a1 = a2 = b0 = b1 = b2 = c0 = c1 = c2 = d0 = d1 = d2 = 0.0
    for m in range(n):
        xx = x - rad + m if inside else _reflect(x - rad + m, w)
        tp = taps[m]
        a0, a1, a2 = _tap3(src, ya, xx, tp, a0, a1, a2)
        b0, b1, b2 = _tap3(src, yb, xx, tp, b0, b1, b2)
        c0, c1, c2 = _tap3(src, yc, xx, tp, c0, c1, c2)
        d0, d1, d2 = _tap3(src, yd, xx, tp, d0, d1, d2)
    _put3(rows, x, ya, a0, a1, a2)
    _put3(rows, x, yb, b0, b1, b2)
    _put3(rows, x, yc, c0, c1, c2)
    _put3(rows, x, yd, d0, d1, d2)


@njit(cache=True, nogil=True, inline="always")
def _tap3(a, y, x, tap, s0, s1, s2):  # pragma: no cover - compiled
    """The three channels' sums plus ``tap`` x a[y, x] (each channel summed as before)."""
    return s0 + tap * a[y, x, 0], s1 + tap * a[y, x, 1], s2 + tap * a[y, x, 2]


@njit(cache=True, nogil=True, inline="always")
def _put3(a, y, x, s0, s1, s2):  # pragma: no cover - compiled
    a[y, x, 0] = s0
    a[y, x, 1] = s1
    a[y, x, 2] = s2


@njit(cache=True, nogil=True)
def la_residuals(smooth, ox, oy, mscale, sigma, alpha, rot, t, s_mean, basis_sdk, intr, dist,
                 w0, w1, w2, gain, cw, want_jac, with_gain, src, done, rows, rdone,
                 taps):  # pragma: no cover - compiled
    """Weighted la residuals r (S*8,), Jacobian (S*8, P) and valid (S,) at one state.

    smooth (h, w, 3) float32 map; (ox, oy, mscale, sigma) its origin, scale and filter scale;
    alpha (K,), rot (3, 3), t (3,) the state; s_mean (S, 3), basis_sdk (S, 3, K) the sample
    points' head-frame mean and basis; intr (fx, fy, cx, cy), dist (k1, k2, p1, p2, k3) the
    camera; w0 (S*8,), w1 (K, S*8), w2 (K, S*8) or (0, 0) the appearance model (lin, quad);
    cw (S, 8) feature weights. P = K + 6 (+1 with_gain: d/d gain).
    src, done, rows, rdone, taps: a lazy map's buffers (see ImageMaps), src of shape
    (0, 0, 3) for a map smoothed already.
    """
    lazy = src.shape[0] > 0
    hh, ww = smooth.shape[0], smooth.shape[1]
    s_count = s_mean.shape[0]
    k = basis_sdk.shape[2]
    quad = w2.shape[0] > 0
    p_count = k + 6 + (1 if with_gain else 0)
    r = np.zeros(s_count * 8)
    jac = np.zeros((s_count * 8 if want_jac else 0, p_count))
    valid = np.zeros(s_count, np.bool_)
    fxl, fyl, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    half = 0.5 * (mscale - 1.0)
    vals = np.empty((3, 3))  # quantity (S, Sx, Sy) x channel (Y, Cr, Cb)
    dxs = np.empty((3, 3))
    dys = np.empty((3, 3))
    q = np.empty((3, 4))  # corners q00 q01 q10 q11 of one quantity
    head = np.empty(3)
    rh = np.empty(3)
    jp = np.empty((2, 3))
    dcam = np.zeros((3, p_count))
    duv = np.empty((2, p_count))
    need = np.empty(taps.shape[0] + 3 if lazy else 0, np.int64)  # _smooth_column's scratch
    for s in range(s_count):
        # geometry: head-frame point, camera-frame point, projection and its Jacobian
        for d in range(3):
            v = s_mean[s, d]
            for kk in range(k):
                v += basis_sdk[s, d, kk] * alpha[kk]
            head[d] = v
        for d in range(3):
            rh[d] = rot[d, 0] * head[0] + rot[d, 1] * head[1] + rot[d, 2] * head[2]
        zc = rh[2] + t[2]
        if not zc > 1e-6:
            continue
        iz = 1.0 / zc
        x = (rh[0] + t[0]) * iz
        y = (rh[1] + t[1]) * iz
        if distorted:
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            dr = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r2 * r2
            da = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
            db = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
            dc = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
        else:
            xd, yd, da, db, dc = x, y, 1.0, 0.0, 1.0
        u = fxl * xd + cx
        vv = fyl * yd + cy
        # sampling: bilinear S and central differences on the 2x2 cell, exact derivatives
        mx = (u - ox) * mscale + half
        my = (vv - oy) * mscale + half
        if not (np.isfinite(mx) and np.isfinite(my)):
            continue
        ix = int(np.floor(mx))
        iy = int(np.floor(my))
        if ix < 1 or ix > ww - 3 or iy < 1 or iy > hh - 3:
            continue
        valid[s] = True
        fx = mx - ix
        fy = my - iy
        if lazy:  # the 12 pixels the cell's values and central differences read
            # (done checked here: a call passes every buffer, mostly to find it done)
            if not (done[iy, ix - 1] and done[iy, ix] and done[iy, ix + 1]
                    and done[iy, ix + 2] and done[iy + 1, ix - 1] and done[iy + 1, ix]
                    and done[iy + 1, ix + 1] and done[iy + 1, ix + 2] and done[iy - 1, ix]
                    and done[iy - 1, ix + 1] and done[iy + 2, ix] and done[iy + 2, ix + 1]):
                _smooth_cell(src, smooth, done, rows, rdone, taps, ix, iy, need)
        for ch in range(3):
            for a in range(2):
                for b in range(2):
                    yy = iy + a
                    xx = ix + b
                    q[0, 2 * a + b] = smooth[yy, xx, ch]
                    q[1, 2 * a + b] = 0.5 * (smooth[yy, xx + 1, ch] - smooth[yy, xx - 1, ch])
                    q[2, 2 * a + b] = 0.5 * (smooth[yy + 1, xx, ch] - smooth[yy - 1, xx, ch])
            for qu in range(3):
                top = q[qu, 0] + (q[qu, 1] - q[qu, 0]) * fx
                bot = q[qu, 2] + (q[qu, 3] - q[qu, 2]) * fx
                vals[qu, ch] = top + (bot - top) * fy
                dxs[qu, ch] = (q[qu, 1] - q[qu, 0]) + ((q[qu, 3] - q[qu, 2])
                                                       - (q[qu, 1] - q[qu, 0])) * fy
                dys[qu, ch] = bot - top
        if want_jac:
            jp[0, 0] = fxl * da * iz
            jp[0, 1] = fxl * db * iz
            jp[0, 2] = -fxl * (da * x + db * y) * iz
            jp[1, 0] = fyl * db * iz
            jp[1, 1] = fyl * dc * iz
            jp[1, 2] = -fyl * (db * x + dc * y) * iz
            # d(camera point)/d(alpha, rotation increment, translation[, gain])
            for d in range(3):
                for kk in range(k):
                    dcam[d, kk] = (rot[d, 0] * basis_sdk[s, 0, kk]
                                   + rot[d, 1] * basis_sdk[s, 1, kk]
                                   + rot[d, 2] * basis_sdk[s, 2, kk])
            dcam[0, k + 1] = rh[2]
            dcam[0, k + 2] = -rh[1]
            dcam[1, k] = -rh[2]
            dcam[1, k + 2] = rh[0]
            dcam[2, k] = rh[1]
            dcam[2, k + 1] = -rh[0]
            dcam[0, k + 3] = 1.0
            dcam[1, k + 4] = 1.0
            dcam[2, k + 5] = 1.0
            for i in range(2):
                for j in range(p_count):
                    duv[i, j] = (jp[i, 0] * dcam[0, j] + jp[i, 1] * dcam[1, j]
                                 + jp[i, 2] * dcam[2, j])
        for c in range(8):
            qu = _QUANTITY[c]
            ch = _CHANNEL[c]
            sc = sigma if qu > 0 else 1.0
            row = s * 8 + c
            pred = w0[row]
            for kk in range(k):
                pred += alpha[kk] * w1[kk, row]
                if quad:
                    pred += alpha[kk] * alpha[kk] * w2[kk, row]
            w = cw[s, c]
            r[row] = (vals[qu, ch] * sc - _OFFSET[c] - gain * pred) * w
            if want_jac:
                gx = dxs[qu, ch] * sc * mscale
                gy = dys[qu, ch] * sc * mscale
                for j in range(p_count):
                    jac[row, j] = (gx * duv[0, j] + gy * duv[1, j]) * w
                for kk in range(k):
                    dp = w1[kk, row]
                    if quad:
                        dp += 2.0 * alpha[kk] * w2[kk, row]
                    jac[row, kk] -= gain * dp * w
                if with_gain:
                    jac[row, k + 6] = -pred * w
    return r, jac, valid


@njit(cache=True, nogil=True)
def cauchy(r, jac, c, scale):  # pragma: no cover - compiled
    """The per-point Cauchy loss of :func:`articast.core.tracking.fitting._robust`: cost,
    IRLS-weighted
    residuals and Jacobian (jac may have 0 rows: no Jacobian)."""
    n = r.shape[0] // c
    s2 = scale * scale
    rw = np.empty_like(r)
    jw = np.empty_like(jac)
    cost = 0.0
    for i in range(n):
        qq = 0.0
        for j in range(c):
            qq += r[i * c + j] * r[i * c + j]
        cost += s2 * np.log1p(qq / s2)
        w = 1.0 / np.sqrt(1.0 + qq / s2)
        for j in range(c):
            row = i * c + j
            rw[row] = r[row] * w
            if jac.shape[0] > 0:
                for p in range(jac.shape[1]):
                    jw[row, p] = jac[row, p] * w
    return cost, rw, jw


@njit(cache=True, nogil=True, inline="always")
def _posed(mean, basis_mk, alpha, rot, i):  # pragma: no cover - compiled
    """Point i of mean + basis_mk @ alpha in the head frame (hx, hy, hz) and turned by rot
    (p0, p1, p2; the translation not added)."""
    hx, hy, hz = mean[i, 0], mean[i, 1], mean[i, 2]
    for kk in range(alpha.shape[0]):
        hx += alpha[kk] * basis_mk[i, 0, kk]
        hy += alpha[kk] * basis_mk[i, 1, kk]
        hz += alpha[kk] * basis_mk[i, 2, kk]
    return (hx, hy, hz, rot[0, 0] * hx + rot[0, 1] * hy + rot[0, 2] * hz,
            rot[1, 0] * hx + rot[1, 1] * hy + rot[1, 2] * hz,
            rot[2, 0] * hx + rot[2, 1] * hy + rot[2, 2] * hz)


@njit(cache=True, nogil=True)
def point_residuals(mean, basis_mk, alpha, rot, t, intr, inv_sigma, uv,
                    jacobian):  # pragma: no cover - compiled
    """The landmark term of :meth:`articast.core.tracking.points.PointTerm.residuals` for a
    camera without distortion: whitened reprojection residuals (2M,) of the points
    mean + basis_mk @ alpha (M, 3) posed by (rot, t), and their Jacobian (2M, K + 6) w.r.t.
    (alpha, rotation increment on the left, translation); 0 rows without ``jacobian``."""
    m, k = mean.shape[0], alpha.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    r = np.empty(2 * m)
    jac = np.zeros((2 * m if jacobian else 0, k + 6))
    for i in range(m):
        hx, hy, hz, p0, p1, p2 = _posed(mean, basis_mk, alpha, rot, i)
        x, y, z = p0 + t[0], p1 + t[1], p2 + t[2]
        iz = 1.0 / z
        w = inv_sigma[i]
        r[2 * i] = (fx * x * iz + cx - uv[i, 0]) * w
        r[2 * i + 1] = (fy * y * iz + cy - uv[i, 1]) * w
        if not jacobian:
            continue
        a0, a2 = fx * iz * w, -fx * x * iz * iz * w  # d u / d (x, z), whitened
        b1, b2 = fy * iz * w, -fy * y * iz * iz * w  # d v / d (y, z)
        for kk in range(k):
            bx, by, bz = basis_mk[i, 0, kk], basis_mk[i, 1, kk], basis_mk[i, 2, kk]
            rx = rot[0, 0] * bx + rot[0, 1] * by + rot[0, 2] * bz
            ry = rot[1, 0] * bx + rot[1, 1] * by + rot[1, 2] * bz
            rz = rot[2, 0] * bx + rot[2, 1] * by + rot[2, 2] * bz
            jac[2 * i, kk] = a0 * rx + a2 * rz
            jac[2 * i + 1, kk] = b1 * ry + b2 * rz
        # d(cam)/d(omega) = -[p]x: omega0 (0, -p2, p1), omega1 (p2, 0, -p0), omega2 (-p1, p0, 0)
        jac[2 * i, k] = a2 * p1
        jac[2 * i + 1, k] = -b1 * p2 + b2 * p1
        jac[2 * i, k + 1] = a0 * p2 - a2 * p0
        jac[2 * i + 1, k + 1] = -b2 * p0
        jac[2 * i, k + 2] = -a0 * p1
        jac[2 * i + 1, k + 2] = b1 * p0
        jac[2 * i, k + 3] = a0
        jac[2 * i, k + 5] = a2
        jac[2 * i + 1, k + 4] = b1
        jac[2 * i + 1, k + 5] = b2
    return r, jac


@njit(cache=True, nogil=True)
def _axis_angle(rot):  # pragma: no cover - compiled
    """:func:`articast.core.model.camera.axis_angle` (all three branches), compiled."""
    tr = rot[0, 0] + rot[1, 1] + rot[2, 2]
    cos = min(max((tr - 1.0) / 2.0, -1.0), 1.0)
    theta = np.arccos(cos)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if theta < 1e-8:
        return w / 2
    if np.pi - theta < 1e-4:
        theta = np.arctan2(np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) / 2.0,
                           (tr - 1.0) / 2.0)
        m = ((rot + rot.T) / 2.0 - np.cos(theta) * np.eye(3)) / (1.0 - np.cos(theta))
        i = 0
        for j in range(1, 3):
            if m[j, j] > m[i, i]:
                i = j
        axis = m[i] / np.sqrt(m[i, i])
        if w[0] * axis[0] + w[1] * axis[1] + w[2] * axis[2] < 0:
            axis = -axis
        return axis / np.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]) * theta
    return w / (2.0 * np.sin(theta)) * theta


@njit(cache=True, nogil=True, inline="always")
def _mul_t(a, b):  # pragma: no cover - compiled
    """a @ b.T of two (3, 3) matrices (loops: numba's @ would call BLAS)."""
    d = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            d[i, j] = a[i, 0] * b[j, 0] + a[i, 1] * b[j, 1] + a[i, 2] * b[j, 2]
    return d


@njit(cache=True, nogil=True, inline="always")
def _dot(a, b):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(a.shape[0]):
        acc += a[i] * b[i]
    return acc


@njit(cache=True, nogil=True, inline="always")
def _small_turn(a, b):  # pragma: no cover - compiled
    """:func:`articast.core.model.camera.small_turn` of a @ b.T (both (3, 3))."""
    d = _mul_t(a, b)
    return 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])


@njit(cache=True, nogil=True)
def _weigh(r, jac, c, scale, factor, out_r, out_j, row0):  # pragma: no cover - compiled
    """The per-point Cauchy loss of ``cauchy`` (scale <= 0: least squares), its weighted rows
    times ``factor`` written into out_r, out_j from ``row0`` (the columns jac has; the others
    left 0). Returns the cost."""
    n = r.shape[0] // c
    s2 = scale * scale
    p = jac.shape[1]
    cost = 0.0
    for i in range(n):
        qq = 0.0
        for j in range(c):
            qq += r[i * c + j] * r[i * c + j]
        if scale > 0:
            cost += s2 * np.log1p(qq / s2)
            w = 1.0 / np.sqrt(1.0 + qq / s2)
        else:
            cost += qq
            w = 1.0
        for j in range(c):
            row = i * c + j
            out_r[row0 + row] = r[row] * w * factor
            for q in range(p):
                out_j[row0 + row, q] = jac[row, q] * w * factor
    return cost


@njit(cache=True, nogil=True)
def fit_terms(smooth, ox, oy, mscale, sigma, alpha, rot, t, s_mean, basis_sdk, intr, dist,
              w0, w1, w2, gain, cw, with_gain, src, done, rows, rdone, taps,
              rot_w, rot_ref, rot_scale, app_weight, app_scale,
              p_mean, p_basis_mk, p_intr, p_inv_sigma, p_uv, p_scale,
              bound, prior_weight, prior_softness,
              sp_alpha, sp_rot, sp_t, sp_info,
              ref_rot, ref_t, ref_wr, ref_wt):  # pragma: no cover - compiled
    """Everything one Gauss-Newton evaluation of
    :func:`articast.core.tracking.fitting.fit_gauss_newton` needs at one state, in one call
    (its ``evaluate`` in numpy is the reference; a test checks the fits agree):

    - the la residuals (``la_residuals``, these arguments) with the rotation terms
      (``rot_w`` (3, S*8) weighted by the channel weights, (0, 0): none; ``rot_ref`` the
      reference rotation matrix, ``rot_scale`` their unit), Cauchy-weighted (``app_scale``,
      <= 0: least squares) and scaled by sqrt(``app_weight``);
    - the landmark term (``point_residuals`` on ``p_*``, M = 0 rows: none), Cauchy-weighted
      (``p_scale``, <= 0: least squares), its rows padded with 0 for the gain;
    - the priors: on alpha (``bound``, ``prior_weight``, ``prior_softness``), the state
      prior (``sp_*``, ``sp_info`` of 0 rows: none) and the pose prior (``ref_*``,
      ``ref_wr`` <= 0: none).

    Returns the stacked weighted rows rw (N,) and jw (N, P) (appearance rows first), the
    appearance residuals r (S*8,) and valid (S,), the appearance's robust cost (x
    app_weight), the landmarks' (before the shared-error correction), the alpha prior's
    cost, gradient and diagonal Hessian (K,), the state and pose priors' cost, gradient
    (K + 6,) and Hessian (K + 6, K + 6) together, and the pose prior's cost."""
    k = alpha.shape[0]
    r, jac, valid = la_residuals(smooth, ox, oy, mscale, sigma, alpha, rot, t, s_mean,
                                 basis_sdk, intr, dist, w0, w1, w2, gain, cw, True, with_gain,
                                 src, done, rows, rdone, taps)
    n_app = r.shape[0]
    p_count = jac.shape[1]
    if rot_w.shape[0] > 0:  # f(alpha) + om @ Wr (Problem.residuals)
        om = _axis_angle(_mul_t(rot, rot_ref)) / rot_scale
        for row in range(n_app):
            if not valid[row // 8]:
                continue  # invalid samples contribute 0
            d = om[0] * rot_w[0, row] + om[1] * rot_w[1, row] + om[2] * rot_w[2, row]
            r[row] = r[row] - gain * d
            for j in range(3):
                jac[row, k + j] -= gain * rot_w[j, row] / rot_scale
            if p_count > k + 6:
                jac[row, k + 6] -= d
    m = p_mean.shape[0]
    rw = np.zeros(n_app + 2 * m)
    jw = np.zeros((n_app + 2 * m, p_count))
    rc = app_weight * _weigh(r, jac, 8, app_scale, np.sqrt(app_weight), rw, jw, 0)
    pc = 0.0
    if m > 0:
        pr, pj = point_residuals(p_mean, p_basis_mk, alpha, rot, t, p_intr, p_inv_sigma, p_uv,
                                 True)
        pc = _weigh(pr, pj, 2, p_scale, 1.0, rw, jw, n_app)
    # the articulation's prior (Problem.prior_terms)
    e = np.empty(k)
    for i in range(k):
        e[i] = prior_weight * np.exp(min((np.abs(alpha[i]) - bound[i]) / prior_softness, 50.0))
    prior = e.sum()
    g_p = np.sign(alpha) * e / prior_softness
    h_p = e / prior_softness ** 2
    g_s = np.zeros(k + 6)
    h_s = np.zeros((k + 6, k + 6))
    sp = 0.0
    if sp_info.shape[0] > 0:  # StatePrior.terms
        d = np.empty(k + 6)
        d[:k] = alpha - sp_alpha
        d[k:k + 3] = _small_turn(rot, sp_rot)
        d[k + 3:] = t - sp_t
        le = np.empty(k + 6)
        for i in range(k + 6):
            le[i] = _dot(sp_info[i], d)
        sp = _dot(d, le)
        g_s += 2.0 * le
        h_s += 2.0 * sp_info
    pp = 0.0
    if ref_wr > 0:  # _pose_prior
        d_rot = _small_turn(rot, ref_rot)
        d_t = t - ref_t
        for i in range(3):
            g_s[k + i] += 2 * ref_wr * d_rot[i]
            g_s[k + 3 + i] += 2 * ref_wt * d_t[i]
            h_s[k + i, k + i] += 2 * ref_wr
            h_s[k + 3 + i, k + 3 + i] += 2 * ref_wt
        pp = ref_wr * _dot(d_rot, d_rot) + ref_wt * _dot(d_t, d_t)
    return rw, jw, r, valid, rc, pc, prior, g_p, h_p, sp, g_s, h_s, pp


@njit(cache=True, nogil=True)
def lm_system(jtj, jtr, h_p, g_p, wa, alpha, a_ref, h_s, g_s, wg, gain,
              gain0):  # pragma: no cover - compiled
    """The normal equations (h, g) of one Levenberg-Marquardt iteration of
    :func:`articast.core.tracking.fitting.fit_gauss_newton` from the data's J^T J and J^T r
    and the priors' terms: the same sums, element by element, as its numpy code."""
    k = alpha.shape[0]
    p = jtj.shape[0]
    h = jtj.copy()
    g = jtr.copy()
    for i in range(k):
        h[i, i] += h_p[i] / 2 + wa
        g[i] += g_p[i] / 2 + wa * (alpha[i] - a_ref[i])
    for i in range(k + 6):
        for j in range(k + 6):
            h[i, j] += h_s[i, j] / 2
        g[i] += g_s[i] / 2
    if p > k + 6:  # gain prior around its start value
        h[k + 6, k + 6] += wg
        g[k + 6] += wg * (gain - gain0)
    return h, g


@njit(cache=True, nogil=True, inline="always")
def _lu(a):  # pragma: no cover - compiled
    """LU factors of a small square ``a`` (n, n), partial pivoting as LAPACK's getrf (the
    first largest |pivot| of each column, the column scaled by the pivot's reciprocal):
    returns (lu (n, n): L below the diagonal (unit diagonal implied), U on and above it;
    piv (n,): the row swapped with row i at step i). ``a`` is only read. Raises numpy's
    LinAlgError on a non-finite entry or a zero pivot (singular), as numba's
    np.linalg.solve does (a compiled loop instead of LAPACK's call: its code is cold after
    the network's run, ~tens of us a frame, and these systems are 6 to 20 unknowns)."""
    n = a.shape[0]
    lu = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            x = a[i, j]
            if not np.isfinite(x):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
            lu[i, j] = x
    piv = np.empty(n, np.int64)
    for c in range(n):
        p = c
        big = abs(lu[c, c])
        for r in range(c + 1, n):
            if abs(lu[r, c]) > big:
                p, big = r, abs(lu[r, c])
        if big == 0.0:
            raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
        piv[c] = p
        if p != c:
            for j in range(n):
                lu[c, j], lu[p, j] = lu[p, j], lu[c, j]
        inv = 1.0 / lu[c, c]
        for r in range(c + 1, n):
            lu[r, c] *= inv
        for r in range(c + 1, n):
            f = lu[r, c]
            for j in range(c + 1, n):
                lu[r, j] -= f * lu[c, j]
    return lu, piv


@njit(cache=True, nogil=True, inline="always")
def _lu_solve(lu, piv, b):  # pragma: no cover - compiled
    """Solve in place ``b`` (n, r) <- A^-1 b from :func:`_lu`'s factors of A (getrs's
    order: the row swaps, L forward, U backward)."""
    n, m = b.shape
    for c in range(n):
        p = piv[c]
        if p != c:
            for j in range(m):
                b[c, j], b[p, j] = b[p, j], b[c, j]
    for j in range(m):
        for r in range(n):
            acc = b[r, j]
            for i in range(r):
                acc -= lu[r, i] * b[i, j]
            b[r, j] = acc
        for r in range(n - 1, -1, -1):
            acc = b[r, j]
            for i in range(r + 1, n):
                acc -= lu[r, i] * b[i, j]
            b[r, j] = acc / lu[r, r]
    return b


@njit(cache=True, nogil=True)
def solve_small(a, b):  # pragma: no cover - compiled
    """np.linalg.solve(a, b) of a small system, a (n, n), b (n,): by :func:`_lu` and
    :func:`_lu_solve` (the same to rounding, LAPACK's blocked sums aside)."""
    lu, piv = _lu(a)
    x = np.empty((b.shape[0], 1))
    x[:, 0] = b
    return _lu_solve(lu, piv, x)[:, 0]


@njit(cache=True, nogil=True)
def inverse_small(a):  # pragma: no cover - compiled
    """np.linalg.inv(a) (as np.linalg.solve(a, I)) of a small a (n, n), C order: by
    :func:`_lu` and :func:`_lu_solve`."""
    lu, piv = _lu(a)
    return _lu_solve(lu, piv, np.eye(a.shape[0]))


@njit(cache=True, nogil=True)
def lm_solve(h, g, lam):  # pragma: no cover - compiled
    """The damped step -(h + lam diag(d))^-1 g, d the diagonal of h (1 where not positive);
    raises numpy's LinAlgError on a singular system."""
    a = h.copy()
    for i in range(h.shape[0]):
        d = h[i, i]
        if d <= 0:
            d = 1.0
        a[i, i] = h[i, i] + lam * d
    return -solve_small(a, g)


@njit(cache=True, nogil=True, inline="always")
def _rodrigues(x, y, z):  # pragma: no cover - compiled
    """:func:`articast.core.model.camera.rotation_matrix` of one vector (x, y, z)."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = th2**0.5
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    out = np.empty((3, 3))
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[0, 1] = -a * z + b * x * y
    out[0, 2] = a * y + b * x * z
    out[1, 0] = a * z + b * x * y
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[1, 2] = -a * x + b * y * z
    out[2, 0] = -a * y + b * x * z
    out[2, 1] = a * x + b * y * z
    out[2, 2] = 1.0 - b * (x * x + y * y)
    return out


@njit(cache=True, nogil=True)
def gn_terms(alpha, rot, t, gain, smooth, ox, oy, mscale, sigma, s_mean, basis_sdk, intr,
             dist, w0, w1, w2, cw, with_gain, src, done, rows, rdone, taps,
             rot_w, rot_ref, rot_scale, app_weight, app_scale,
             p_mean, p_basis_mk, p_intr, p_inv_sigma, p_uv, p_scale,
             bound, prior_weight, prior_softness,
             sp_alpha, sp_rot, sp_t, sp_info,
             ref_rot, ref_t, ref_wr, ref_wt,
             p_v, p_c, wa, a_ref, wg, gain0):  # pragma: no cover - compiled
    """One evaluation of :func:`articast.core.tracking.fitting.fit_gauss_newton` (its
    ``evaluate``; ``evaluate_numpy`` is the reference) at the state (alpha (K,), rot (3, 3),
    t (3,) mm, gain): :func:`fit_terms` (the same arguments from ``smooth`` on), the
    landmarks' shared-error correction (``PointTerm.shared``: the modes ``p_v`` (2M, R),
    ``p_c`` (R, R); R = 0: none) and the total cost with the articulation's motion prior
    (``wa``, ``a_ref`` (K,)) and the gain's prior (``wg``, ``gain0``). The dense products
    are BLAS's, as numpy's are. Returns the cost, then the appearance residuals r (S*8,),
    the valid fraction, the appearance's robust cost, the weighted rows rw (N,) and jw
    (N, P), the alpha prior's gradient and diagonal Hessian (K,), the state and pose
    priors' gradient (K + 6,) and Hessian (K + 6, K + 6) less the shared correction, and
    that correction's Hessian half (K + 6, K + 6)."""
    k = alpha.shape[0]
    (rw, jw, r, valid, rc, pc, prior, g_p, h_p, sp, g_s, h_s, pp) = fit_terms(
        smooth, ox, oy, mscale, sigma, alpha, rot, t, s_mean, basis_sdk, intr, dist, w0, w1,
        w2, gain, cw, with_gain, src, done, rows, rdone, taps, rot_w, rot_ref, rot_scale,
        app_weight, app_scale, p_mean, p_basis_mk, p_intr, p_inv_sigma, p_uv, p_scale, bound,
        prior_weight, prior_softness, sp_alpha, sp_rot, sp_t, sp_info, ref_rot, ref_t, ref_wr,
        ref_wt)
    h_shared = np.zeros((k + 6, k + 6))
    if p_mean.shape[0] > 0 and p_v.shape[1] > 0:  # PointTerm.shared
        na = r.shape[0]
        pr = rw[na:]
        pj = np.ascontiguousarray(jw[na:, :k + 6])
        vr = np.dot(p_v.T, pr)
        vj = np.dot(p_v.T, pj)  # (R, K + 6)
        cvr = np.dot(p_c, vr)
        pc -= np.dot(vr, cvr)  # the errors the landmarks share count once
        g_s -= 2.0 * np.dot(vj.T, cvr)
        h_shared = np.dot(vj.T, np.dot(p_c, vj))
        h_s -= 2.0 * h_shared
    d = alpha - a_ref
    cost = (rc + pc + prior + pp + sp + wa * np.dot(d, d)
            + wg * (gain - gain0) ** 2 * (1.0 if with_gain else 0.0))
    vf = np.count_nonzero(valid) / max(valid.shape[0], 1)
    return cost, r, vf, rc, rw, jw, g_p, h_p, g_s, h_s, h_shared


@njit(cache=True, nogil=True)
def lm_step(jtj, jtr, lam, max_rejections, cost, h_p, g_p, h_s, g_s, alpha, rot, t, gain,
            smooth, ox, oy, mscale, sigma, s_mean, basis_sdk, intr,
            dist, w0, w1, w2, cw, with_gain, src, done, rows, rdone, taps,
            rot_w, rot_ref, rot_scale, app_weight, app_scale,
            p_mean, p_basis_mk, p_intr, p_inv_sigma, p_uv, p_scale,
            bound, prior_weight, prior_softness,
            sp_alpha, sp_rot, sp_t, sp_info,
            ref_rot, ref_t, ref_wr, ref_wt,
            p_v, p_c, wa, a_ref, wg, gain0):  # pragma: no cover - compiled
    """One Levenberg-Marquardt iteration of
    :func:`articast.core.tracking.fitting.fit_gauss_newton` (its numpy loop is the
    reference): from the data's J^T J and J^T r (``jtj``, ``jtr``: numpy's products, passed
    in) and the current state's cost and prior terms, the damped steps tried at ``lam``,
    x10 after each rejection, until one lowers the cost, ``lam`` exceeds 1e6 or
    ``max_rejections`` (< 0: no limit) were rejected; each trial evaluated by
    :func:`gn_terms` (the arguments from ``smooth`` on). Returns whether a step was
    accepted, the last ``lam``, the evaluations made, the last step, its state (alpha, rot,
    t, gain) and :func:`gn_terms`'s values there."""
    k = alpha.shape[0]
    h, g = lm_system(jtj, jtr, h_p, g_p, wa, alpha, a_ref, h_s, g_s, wg, gain, gain0)
    rejected = 0
    evals = 0
    while True:
        try:
            step = lm_solve(h, g, lam)
        except Exception:  # (numpy's LinAlgError: singular)
            lam *= 10
            continue
        a_new = alpha + step[:k]
        rot_new = np.dot(_rodrigues(step[k], step[k + 1], step[k + 2]), rot)
        t_new = t + step[k + 3:k + 6]
        g_new = min(max(gain + step[k + 6], 0.2), 5.0) if step.shape[0] > k + 6 else gain
        terms = gn_terms(a_new, rot_new, t_new, g_new, smooth, ox, oy, mscale, sigma, s_mean,
                         basis_sdk, intr, dist, w0, w1, w2, cw, with_gain, src, done, rows,
                         rdone, taps, rot_w, rot_ref, rot_scale, app_weight, app_scale, p_mean,
                         p_basis_mk, p_intr, p_inv_sigma, p_uv, p_scale, bound, prior_weight,
                         prior_softness, sp_alpha, sp_rot, sp_t, sp_info, ref_rot, ref_t,
                         ref_wr, ref_wt, p_v, p_c, wa, a_ref, wg, gain0)
        evals += 1
        cost_new = terms[0]
        if cost_new <= cost or lam > 1e6:
            return (cost_new <= cost, lam, evals, step, a_new, rot_new, t_new, g_new, terms)
        rejected += 1
        if max_rejections >= 0 and rejected >= max_rejections:
            return (False, lam, evals, step, a_new, rot_new, t_new, g_new, terms)
        lam *= 10


@njit(cache=True, nogil=True)
def fit_information(h, h_shared, p, wg):  # pragma: no cover - compiled
    """A fit's data information about its first ``p`` unknowns (``fit_gauss_newton``'s
    epilogue; its numpy code, ``_marginal_information`` after the subtraction, is the
    reference): J^T J ``h`` (p, p) or (p + 1, p + 1) less the landmarks' shared errors
    ``h_shared`` (p, p) on its first p rows and columns, the image gain (the last unknown,
    prior ``wg``) marginalised out by its Schur complement, the same products and quotients
    as numpy's outer product. ``h`` is only read. Returns (p, p)."""
    out = np.empty((p, p))
    for i in range(p):
        for j in range(p):
            out[i, j] = h[i, j] - h_shared[i, j]
    if h.shape[0] == p + 1:
        d = h[p, p] + wg
        for i in range(p):
            for j in range(p):
                out[i, j] = out[i, j] - h[i, p] * h[p, j] / d
    return out


@njit(cache=True, nogil=True)
def sample_uv(s_mean, basis_flat, alpha, rot, t, intr):  # pragma: no cover - compiled
    """:meth:`articast.core.tracking.fitting.Problem.project` for an undistorted camera (its
    numpy code is the reference): image positions (S, 2) px of the sample points (head-frame
    mean s_mean (S, 3), basis_flat (K, S*3)) at alpha (K,), rot (3, 3), t (3,) mm; intr
    (fx, fy, cx, cy). The products are BLAS's, as numpy's; NaN behind the camera."""
    head = s_mean + np.dot(alpha, basis_flat).reshape(s_mean.shape)
    cam = np.dot(head, rot.T)
    uv = np.empty((cam.shape[0], 2))
    for i in range(cam.shape[0]):
        z = cam[i, 2] + t[2]
        iz = 1.0 / z if z > 1e-6 else np.nan
        uv[i, 0] = intr[0] * ((cam[i, 0] + t[0]) * iz) + intr[2]
        uv[i, 1] = intr[1] * ((cam[i, 1] + t[1]) * iz) + intr[3]
    return uv


@njit(cache=True, nogil=True)
def roi_box(uv, margin):  # pragma: no cover - compiled
    """:func:`articast.core.appearance.maps.roi_of` (its numpy code is the reference): the
    bounding box (x0, y0, x1, y1) of the finite points of uv (M, 2) grown by ``margin`` px."""
    lo0 = lo1 = np.inf
    hi0 = hi1 = -np.inf
    seen = False
    for i in range(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        if np.isfinite(u) and np.isfinite(v):
            seen = True
            lo0, lo1 = min(lo0, u), min(lo1, v)
            hi0, hi1 = max(hi0, u), max(hi1, v)
    if not seen:
        return 0, 0, 0, 0
    return (int(np.floor(lo0 - margin)), int(np.floor(lo1 - margin)),
            int(np.ceil(hi0 + margin)) + 1, int(np.ceil(hi1 + margin)) + 1)


@njit(cache=True, nogil=True)
def state_measured(p_alpha, p_rot, p_t, p_info, alpha, information):  # pragma: no cover
    """:meth:`articast.core.tracking.fitting.StatePrior.with_measurement` (its numpy code is
    the reference): the prior (p_alpha (K,), p_rot (3, 3), p_t (3,), p_info (K + 6, K + 6))
    times a measurement N(alpha, information^-1) of the articulation; returns the new
    alpha, rotation, translation and information."""
    k = p_alpha.shape[0]
    info = p_info.copy()
    for i in range(k):
        for j in range(k):
            info[i, j] += information[i, j]
    rhs = np.zeros(k + 6)
    rhs[:k] = np.dot(information, p_alpha - alpha)
    e = -solve_small(info, rhs)
    return (p_alpha + e[:k], np.dot(_rodrigues(e[k], e[k + 1], e[k + 2]), p_rot),
            p_t + e[k + 3:], info)


@njit(cache=True, nogil=True)
def _sd_of_sums(s, sq, n):  # pragma: no cover - compiled
    """OpenCV's meanStdDev from exact integer sums: mean = s / n as s * (1 / n), the s.d. the
    square root of sq / n - mean^2 (0 where that rounds below 0)."""
    scale = 1.0 / n if n else 0.0
    m = s * scale
    return np.sqrt(max(sq * scale - m * m, 0.0))


@njit(cache=True, nogil=True)
def pixels_sd3(p):  # pragma: no cover - compiled
    """``cv2.meanStdDev`` of every value of a uint8 (h, w, c) array, any strides (a frame's
    every n-th pixel, read in place: no contiguous copy), to the last bit (its sums are
    exact integers)."""
    s = 0
    sq = 0
    for i in range(p.shape[0]):
        for j in range(p.shape[1]):
            for c in range(p.shape[2]):
                v = np.int64(p[i, j, c])
                s += v
                sq += v * v
    return _sd_of_sums(s, sq, p.shape[0] * p.shape[1] * p.shape[2])


@njit(cache=True, nogil=True)
def pixels_sd2(p):  # pragma: no cover - compiled
    """:func:`pixels_sd3` of a uint8 (h, w) array (one channel's, any strides)."""
    s = 0
    sq = 0
    for i in range(p.shape[0]):
        for j in range(p.shape[1]):
            v = np.int64(p[i, j])
            s += v
            sq += v * v
    return _sd_of_sums(s, sq, p.shape[0] * p.shape[1])


@njit(cache=True, nogil=True)
def facing_cos(s_mean, normals, rot, t):  # pragma: no cover - compiled
    """:meth:`articast.core.tracking.tracker.Tracker.facing` (its numpy code is the
    reference): per sample point (S, 3 head frame, ``normals`` (S, 3)) posed by (rot, t), the
    cosine between its normal and its direction to the camera's centre."""
    p = np.dot(s_mean, rot.T)
    nr = np.dot(normals, rot.T)
    out = np.empty(s_mean.shape[0])
    for i in range(s_mean.shape[0]):
        p0, p1, p2 = p[i, 0] + t[0], p[i, 1] + t[1], p[i, 2] + t[2]
        norm = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        out[i] = -(nr[i, 0] * p0 + nr[i, 1] * p1 + nr[i, 2] * p2) / max(norm, 1e-9)
    return out


@njit(cache=True, nogil=True, inline="always")
def _nan_max(a, b):  # pragma: no cover - compiled
    """np.maximum of two numbers (NaN if either is)."""
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@njit(cache=True, nogil=True)
def occlusion_votes(q, judged, s_mean, normals, rot, t, min_facing, q_div, base, factor,
                    q_level, floor):  # pragma: no cover - compiled
    """:meth:`articast.core.tracking.tracker.Tracker.occlusion`'s per-point test (its numpy
    code, ``occlusion_numpy``, is the reference): the points ``judged`` (S,) bool with
    q (S,) > 0 and, unless ``min_facing`` is NaN, :func:`facing_cos` >= it (posed by rot,
    t) are judged; of those, out are those with q / q_div above max(base, factor *
    max(q_level, floor)) (S,). Returns (out (S,) bool, its count, the judged count)."""
    m = q.shape[0]
    use_facing = min_facing == min_facing
    if use_facing:
        p = np.dot(s_mean, rot.T)
        nr = np.dot(normals, rot.T)
    else:
        p = np.empty((0, 3))
        nr = np.empty((0, 3))
    out = np.zeros(m, np.bool_)
    n_out = 0
    n_judged = 0
    for i in range(m):
        ok = judged[i] and q[i] > 0
        if ok and use_facing:
            p0, p1, p2 = p[i, 0] + t[0], p[i, 1] + t[1], p[i, 2] + t[2]
            norm = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
            ok = -(nr[i, 0] * p0 + nr[i, 1] * p1 + nr[i, 2] * p2) / max(norm, 1e-9) >= min_facing
        if not ok:
            continue
        n_judged += 1
        if q[i] / q_div > _nan_max(base, factor * _nan_max(q_level[i], floor)):
            out[i] = True
            n_out += 1
    return out, n_out, n_judged


@njit(cache=True, nogil=True)
def reading_features(mean, rot, t, intr, uv):  # pragma: no cover - compiled
    """:meth:`articast.core.tracking.points.ReadingRegression.features` for a camera without
    distortion (intr: fx, fy, cx, cy): the reading ``uv`` (M, 2) px as head-frame x, y
    offsets (mm) from ``mean`` (M, 3) posed by (rot, t), less their least-squares fit by the
    six patterns of a small head move (the numpy reference projects them out with a QR; here
    the 6 x 6 normal equations: the same projection where the patterns are independent, as
    ~hundreds of points make them; a test checks both agree)."""
    m = mean.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    f = np.empty(2 * m)
    moves = np.empty((2 * m, 6))
    for i in range(m):
        px = rot[0, 0] * mean[i, 0] + rot[0, 1] * mean[i, 1] + rot[0, 2] * mean[i, 2]
        py = rot[1, 0] * mean[i, 0] + rot[1, 1] * mean[i, 1] + rot[1, 2] * mean[i, 2]
        pz = rot[2, 0] * mean[i, 0] + rot[2, 1] * mean[i, 1] + rot[2, 2] * mean[i, 2]
        x, y, z = px + t[0], py + t[1], pz + t[2]
        iz = 1.0 / z if z > 1e-6 else np.nan
        d0 = (uv[i, 0] - (fx * x * iz + cx)) * z / fx
        d1 = (uv[i, 1] - (fy * y * iz + cy)) * z / fy
        f[2 * i] = d0 * rot[0, 0] + d1 * rot[1, 0]
        f[2 * i + 1] = d0 * rot[0, 1] + d1 * rot[1, 1]
        # d(cam)/d(turn, translation): -[p]x then the identity; through the projection and
        # back to mm at the point's depth: the image-plane offset's x row (1, 0, -x/z),
        # y row (0, 1, -y/z)
        dcam = np.zeros((3, 6))
        dcam[0, 1], dcam[0, 2] = pz, -py
        dcam[1, 0], dcam[1, 2] = -pz, px
        dcam[2, 0], dcam[2, 1] = py, -px
        dcam[0, 3] = dcam[1, 4] = dcam[2, 5] = 1.0
        for q in range(6):
            e0 = dcam[0, q] - x * iz * dcam[2, q]
            e1 = dcam[1, q] - y * iz * dcam[2, q]
            moves[2 * i, q] = e0 * rot[0, 0] + e1 * rot[1, 0]
            moves[2 * i + 1, q] = e0 * rot[0, 1] + e1 * rot[1, 1]
    gram = moves.T @ moves
    coef = solve_small(gram, moves.T @ f)
    return f - moves @ coef


@njit(cache=True, nogil=True, inline="always")
def _lip_measures(mean, basis, a, rot, t, intr, out, row):  # pragma: no cover - compiled
    """The lips' ratio and width at articulation ``a`` into out[row] (see lip_gap)."""
    k = a.shape[0]
    pts = np.empty((6, 3))
    for j in range(6):
        for c in range(3):
            acc = mean[j, c]
            for q in range(k):
                acc += a[q] * basis[q, 3 * j + c]
            pts[j, c] = acc
    uv = np.empty((4, 2))
    for j in range(4):
        x = rot[0, 0] * pts[j, 0] + rot[0, 1] * pts[j, 1] + rot[0, 2] * pts[j, 2] + t[0]
        y = rot[1, 0] * pts[j, 0] + rot[1, 1] * pts[j, 1] + rot[1, 2] * pts[j, 2] + t[1]
        z = rot[2, 0] * pts[j, 0] + rot[2, 1] * pts[j, 1] + rot[2, 2] * pts[j, 2] + t[2]
        iz = 1.0 / z if z > 1e-6 else np.nan
        uv[j, 0] = intr[0] * x * iz + intr[2]
        uv[j, 1] = intr[1] * y * iz + intr[3]
    ax, ay = uv[3, 0] - uv[2, 0], uv[3, 1] - uv[2, 1]
    w2 = ax * ax + ay * ay
    dn = (uv[1, 0] - uv[0, 0]) * (-ay) + (uv[1, 1] - uv[0, 1]) * ax
    out[row, 0] = dn / w2 if w2 > 0.0 else np.nan
    dx, dy, dz = pts[5, 0] - pts[4, 0], pts[5, 1] - pts[4, 1], pts[5, 2] - pts[4, 2]
    out[row, 1] = np.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True)
def lip_ratio(mean, basis, rot, t, intr, alpha):  # pragma: no cover - compiled
    """The lips' projected ratio at ``alpha`` (:func:`articast.core.faces.lipgap.model_ratios`
    of one articulation, for a camera without distortion; the arguments as :func:`lip_gap`)."""
    out = np.empty((1, 2))
    _lip_measures(mean, basis, alpha, rot, t, intr, out, 0)
    return out[0, 0]


@njit(cache=True, nogil=True)
def lip_gap(mean, basis, rot, t, intr, alpha, fitted, read, share, step, max_change,
            tolerance):  # pragma: no cover - compiled
    """:meth:`articast.core.faces.live.LiveTracker._lip_gap` in one call, for a camera
    without distortion (intr: fx, fy, cx, cy): the target ratio ``share`` x ``read`` + the
    rest x the ratio at ``fitted`` (the reading alone where that is not finite), then one
    iteration of :func:`articast.core.faces.lipgap.matched` from ``alpha`` (the numpy
    reference; a test checks they agree). ``mean`` (6, 3) and ``basis`` (K, 18): the
    points of :func:`articast.core.faces.lipgap._points`."""
    k = alpha.shape[0]
    out = np.empty((2 * k + 1, 2))
    target = read
    if share < 1.0:
        _lip_measures(mean, basis, fitted, rot, t, intr, out, 0)
        if np.isfinite(out[0, 0]):
            target = share * read + (1.0 - share) * out[0, 0]
    a = alpha.copy()
    if not np.isfinite(target):
        return a
    _lip_measures(mean, basis, a, rot, t, intr, out, 0)
    probe = a.copy()
    for q in range(k):
        probe[q] = a[q] + step
        _lip_measures(mean, basis, probe, rot, t, intr, out, 1 + q)
        probe[q] = a[q] - step
        _lip_measures(mean, basis, probe, rot, t, intr, out, 1 + k + q)
        probe[q] = a[q]
    for i in range(2 * k + 1):
        if not np.isfinite(out[i, 0]):
            return alpha.copy()
    if abs(target - out[0, 0]) <= tolerance:
        return a
    grad = np.empty(k)
    gw = np.empty(k)
    g2 = 0.0
    for q in range(k):
        grad[q] = (out[1 + q, 0] - out[1 + k + q, 0]) / (2 * step)
        gw[q] = (out[1 + q, 1] - out[1 + k + q, 1]) / (2 * step)
        g2 += grad[q] * grad[q]
    if g2 <= 1e-18:
        return a
    ga, gb, gd = 0.0, 0.0, 0.0
    for q in range(k):
        ga += grad[q] * grad[q]
        gb += grad[q] * gw[q]
        gd += gw[q] * gw[q]
    r0, r1 = target - out[0, 0], 0.0  # (the width kept where it stands)
    half = 0.5 * (ga + gd)
    disc = np.sqrt(max(0.25 * (ga - gd) ** 2 + gb * gb, 0.0))
    low, high = half - disc, half + disc
    if low > 0.0 and high < 1e8 * low:
        det = ga * gd - gb * gb
        x0, x1 = (gd * r0 - gb * r1) / det, (ga * r1 - gb * r0) / det
        for q in range(k):
            a[q] += grad[q] * x0 + gw[q] * x1
    else:
        for q in range(k):
            a[q] += grad[q] * r0 / g2
    norm = 0.0
    for q in range(k):
        norm += (a[q] - alpha[q]) ** 2
    norm = np.sqrt(norm)
    if norm > max_change:
        for q in range(k):
            a[q] = alpha[q] + (a[q] - alpha[q]) * (max_change / norm)
    return a


@njit(cache=True, nogil=True)
def point_offset(mean, basis_mk, alpha, rot, t, intr, seen):  # pragma: no cover - compiled
    """:func:`articast.core.tracking.points.offset_fraction` of readings ``seen`` (M, 2) px from
    the points mean + basis_mk @ alpha (M, 3) posed by (rot, t) and projected by a camera
    without distortion (intr: fx, fy, cx, cy), as :func:`articast.core.tracking.points.
    state_offset` computes it in numpy."""
    m = mean.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    uv = np.empty((m, 2))
    for i in range(m):
        _, _, _, p0, p1, p2 = _posed(mean, basis_mk, alpha, rot, i)
        x, y, z = p0 + t[0], p1 + t[1], p2 + t[2]
        iz = 1.0 / z if z > 1e-6 else np.nan
        uv[i, 0] = fx * (x * iz) + cx
        uv[i, 1] = fy * (y * iz) + cy
    d = np.empty(m)
    n = 0
    for i in range(m):
        e0 = seen[i, 0] - uv[i, 0]
        e1 = seen[i, 1] - uv[i, 1]
        di = np.sqrt(e0 * e0 + e1 * e1)
        if np.isfinite(di):
            d[n] = di
            n += 1
    if n == 0:
        return np.nan
    c0 = 0.0
    c1 = 0.0
    for i in range(m):
        c0 += uv[i, 0]
        c1 += uv[i, 1]
    c0 /= m
    c1 /= m
    ss = 0.0
    for i in range(m):
        ss += (uv[i, 0] - c0) ** 2 + (uv[i, 1] - c1) ** 2
    size = np.sqrt(ss / m)
    return np.median(d[:n]) / max(size, 1.0)


@njit(cache=True, nogil=True)
def cv_predict(p, q, dt3, dt2, dt, alpha, v, t, rot, speaker):  # pragma: no cover
    """:meth:`articast.core.tracking.kalman.ConstantVelocity.predict` but its rotation: the
    covariance F P F^T + Q by blocks (p (2n, 2n); q (n,) the noise's density, its terms
    q * dt^3 / 3, q * dt^2 / 2 and q * dt with dt3 = dt**3 and dt2 = dt**2 as Python works
    them out) and the information of its state block, and the articulation alpha (K,) and
    translation t (3,) moved by the velocity v (n,) over dt, in one call: the same
    element-wise sums as its numpy code, the inverse by :func:`inverse_small` (numpy's inv to
    rounding). Returns (P, information, alpha, t), then, with ``speaker`` >= 0, that
    prediction (at the predicted rotation ``rot`` (3, 3)) times the speaker's distribution
    of weight ``speaker`` (:meth:`~articast.core.tracking.fitting.StatePrior.with_speaker`,
    by :func:`state_measured` on the same numbers: its alpha, rotation, translation and
    information; empty arrays where ``speaker`` < 0)."""
    n = p.shape[0] // 2
    k = alpha.shape[0]
    q3 = np.empty(n)
    q2 = np.empty(n)
    q1 = np.empty(n)
    for i in range(n):
        q3[i] = q[i] * dt3 / 3.0
        q2[i] = q[i] * dt2 / 2.0
        q1[i] = q[i] * dt
    a_new = np.empty(k)
    for i in range(k):
        a_new[i] = alpha[i] + dt * v[i]
    t_new = np.empty(3)
    for i in range(3):
        t_new[i] = t[i] + dt * v[k + 3 + i]
    out = np.empty_like(p)
    dt2 = dt * dt
    for a in range(n):
        for b in range(n):
            out[a, b] = p[a, b] + dt * (p[a, n + b] + p[b, n + a]) + dt2 * p[n + a, n + b]
            out[a, n + b] = p[a, n + b] + dt * p[n + a, n + b]
            out[n + a, b] = p[b, n + a] + dt * p[n + b, n + a]
            out[n + a, n + b] = p[n + a, n + b]
    for i in range(n):
        out[i, i] += q3[i]
        out[i, n + i] += q2[i]
        out[n + i, i] += q2[i]
        out[n + i, n + i] += q1[i]
    a = np.ascontiguousarray(out[:n, :n])
    for i in range(n):
        a[i, i] += 1e-12
    info = inverse_small(a)
    if speaker < 0:
        return out, info, a_new, t_new, np.zeros(0), np.zeros((0, 0)), np.zeros(0), \
            np.zeros((0, 0))
    s_alpha, s_rot, s_t, s_info = state_measured(a_new, rot, t_new, info, np.zeros(k),
                                                 speaker * np.eye(k))
    return out, info, a_new, t_new, s_alpha, s_rot, s_t, s_info


@njit(cache=True, nogil=True, inline="always")
def _mm(a, b):  # pragma: no cover - compiled
    """a @ b by plain loops (each entry summed in order over the inner index: small
    matrices, where BLAS's call costs more than the sums)."""
    out = np.empty((a.shape[0], b.shape[1]))
    for r in range(a.shape[0]):
        for c in range(b.shape[1]):
            acc = 0.0
            for j in range(a.shape[1]):
                acc += a[r, j] * b[j, c]
            out[r, c] = acc
    return out


@njit(cache=True, nogil=True)
def cv_update(p, info, alpha, a_p, turn, t, t_p, v, information):  # pragma: no cover
    """:meth:`articast.core.tracking.kalman.ConstantVelocity.update`'s algebra in one call:
    the innovation e = (alpha - a_p, small_turn(``turn``), t - t_p) (turn: the fitted
    rotation times the predicted one's transpose, (3, 3)), the gain P_{:,x} Pxx^-1
    (``info`` = Pxx^-1), the velocity ``v`` moved by the gain times e, and the covariance
    P - G (Pxx - post) G^T made symmetric, post the inverse of info + ``information``
    ((0, 0): none, P kept). Returns (P, v)."""
    n = info.shape[0]
    m = p.shape[0]
    k = alpha.shape[0]
    e = np.empty(n)
    for i in range(k):
        e[i] = alpha[i] - a_p[i]
    e[k] = 0.5 * (turn[2, 1] - turn[1, 2])
    e[k + 1] = 0.5 * (turn[0, 2] - turn[2, 0])
    e[k + 2] = 0.5 * (turn[1, 0] - turn[0, 1])
    for i in range(3):
        e[k + 3 + i] = t[i] - t_p[i]
    g = _mm(p[:n, :].T, info.T)  # (m, n)
    v_new = v.copy()
    for r in range(n, m):
        acc = 0.0
        for c in range(n):
            acc += g[r, c] * e[c]
        v_new[r - n] += acc
    out = p.copy()
    if information.shape[0] > 0:
        post = inverse_small(info + information)
        out -= _mm(_mm(g, p[:n, :n] - post), g.T)
    sym = np.empty_like(out)
    for r in range(m):
        for s in range(m):
            sym[r, s] = 0.5 * (out[r, s] + out[s, r])
    return sym, v_new


# ---------------------------------------------------------------------------- iris chords
# core/faces/iris.py's iris fit (_chords, _runs_round, _former_accepts) in one compiled
# call each: the same float32 arithmetic as numpy's (its Python float operands cast to
# float32 first, NEP 50) and numpy's pairwise sums, so the same numbers to the bit; the
# numpy functions are the reference (a test checks them against each other).


IRIS_MAX_WIDTH = 4096
"""The widest eye crop (px) the compiled iris chords take (their sums are numpy's up to it)."""


@njit(cache=True, nogil=True)
def _pairwise_block(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise summation of a[lo:lo + n], n <= 128 (its leaves): below 8 in order,
    else eight running sums combined as a tree, then the rest in order (float32 summed in
    float32)."""
    if n < 8:
        res = a[lo] - a[lo]  # a zero of a's type
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


# numpy halves a longer run (each half a multiple of 8 long, the rest to the second) and adds
# the halves' sums: one function per level, as numba's cache cannot hold a recursive one
# (loaded from the cache, it crashed); five levels: runs of up to 4096 (an eye's rows are
# tens of pixels; longer ones stay with numpy: IRIS_MAX_WIDTH)


@njit(cache=True, nogil=True)
def _pairwise_2(a, lo, n):  # pragma: no cover - compiled
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = n // 2 - (n // 2) % 8
    return _pairwise_block(a, lo, n2) + _pairwise_block(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def _pairwise_3(a, lo, n):  # pragma: no cover - compiled
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = n // 2 - (n // 2) % 8
    return _pairwise_2(a, lo, n2) + _pairwise_2(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def _pairwise_4(a, lo, n):  # pragma: no cover - compiled
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = n // 2 - (n // 2) % 8
    return _pairwise_3(a, lo, n2) + _pairwise_3(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def _pairwise_5(a, lo, n):  # pragma: no cover - compiled
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = n // 2 - (n // 2) % 8
    return _pairwise_4(a, lo, n2) + _pairwise_4(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def _pairwise_sum(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise summation of a[lo:lo + n] (1-D; float32 summed in float32): the
    order of its additions, hence its rounding, exactly (n up to 4096)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = n // 2 - (n // 2) % 8
    return _pairwise_5(a, lo, n2) + _pairwise_5(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def iris_runs(cov, j, rows_ok, grown):  # pragma: no cover - compiled
    """iris._runs_round: each row's run of iris (cov (h, w) float32) round its column j,
    ended where the fraction falls to 0.12: widths (float32), centres (float64) and bounded."""
    h, w = cov.shape
    brk = np.float32(0.12)
    zero = np.float32(0.0)
    widths = np.empty(h, np.float32)
    cxs = np.empty(h)
    bounded = np.zeros(h, np.bool_)
    m32 = np.empty(w, np.float32)
    m64 = np.empty(w)
    for y in range(h):
        at = 0  # the run's index at j: the breaks up to j
        for x in range(j[y] + 1):
            if cov[y, x] <= brk:
                at += 1
        run = 0
        first = -1
        last = -1
        for x in range(w):
            c = cov[y, x]
            if c <= brk:
                run += 1
                m32[x] = zero
            elif run == at:
                if first < 0:
                    first = x
                last = x
                m32[x] = c
            else:
                m32[x] = zero
            m64[x] = np.float64(m32[x]) * np.float64(x)
        if first < 0:  # (numpy's argmax of a row without any: 0, and w - 1 from the end)
            first, last = 0, w - 1
        bounded[y] = (rows_ok[y] and first > 0 and last < w - 1
                      and grown[y, max(first - 1, 0)] > 0 and grown[y, min(last + 1, w - 1)] > 0)
        wy = _pairwise_sum(m32, 0, w)
        widths[y] = wy
        cxs[y] = _pairwise_sum(m64, 0, w) / np.float64(max(wy, np.float32(1e-9)))
    return widths, cxs, bounded


@njit(cache=True, nogil=True)
def _white_of(vals, n, white):  # pragma: no cover - compiled
    """iris._white of the first n of vals."""
    if n < 4:
        return white
    v = np.sort(vals[:n])
    return np.float64(v[(3 * n) // 4])


@njit(cache=True, nogil=True)
def iris_chords(p, contour, grown, thr, iris, white, cx0, row_white):  # pragma: no cover
    """iris._chords after its opening ``p`` (h, w) float32: (widths, centres, bounded)."""
    h, w = p.shape
    thr32 = np.float32(thr)
    iris32 = np.float32(iris)
    j = np.zeros(h, np.int64)
    rows_ok = np.zeros(h, np.bool_)
    for y in range(h):
        best = np.inf
        for x in range(w):
            if p[y, x] < thr32 and contour[y, x] > 0:
                d = abs(np.float64(x) - cx0)
                if d < best:
                    best = d
                    j[y] = x
        rows_ok[y] = best < 0.25 * w
    vl = np.empty(h * w, np.float32)
    vr = np.empty(h * w, np.float32)
    nl = nr = 0
    for y in range(h):
        for x in range(w):
            if contour[y, x] > 0 and p[y, x] >= thr32:
                if np.float64(x) < cx0:
                    vl[nl] = p[y, x]
                    nl += 1
                else:
                    vr[nr] = p[y, x]
                    nr += 1
    need_l = np.float32(row_white * (_white_of(vl, nl, white) - iris))
    need_r = np.float32(row_white * (_white_of(vr, nr, white) - iris))
    cov = np.empty((h, w), np.float32)
    eps = np.float32(1e-6)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for y in range(h):
        lo = np.float32(-np.inf)
        hi = np.float32(-np.inf)
        for x in range(w):
            if contour[y, x] > 0:
                if x < j[y]:
                    lo = max(lo, p[y, x])
                else:
                    hi = max(hi, p[y, x])
        rows_ok[y] = rows_ok[y] and (lo - iris32 >= need_l) and (hi - iris32 >= need_r)
        for x in range(w):
            if grown[y, x] == 0:
                cov[y, x] = zero
                continue
            side = lo if x < j[y] else hi
            den = side - iris32
            if not den > eps:
                den = eps
            v = (side - p[y, x]) / den
            cov[y, x] = zero if v < zero else (one if v > one else v)
    return iris_runs(cov, j, rows_ok, grown)


@njit(cache=True, nogil=True)
def iris_former_rows(patch, grown, iris, white, cx0):  # pragma: no cover - compiled
    """iris._former_accepts's chords (one eye-wide white): (widths, bounded)."""
    h, w = patch.shape
    white32 = np.float32(white)
    span32 = np.float32(white - iris)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    half = np.float32(0.5)
    cov = np.empty((h, w), np.float32)
    j = np.zeros(h, np.int64)
    rows_ok = np.zeros(h, np.bool_)
    for y in range(h):
        best = np.inf
        for x in range(w):
            if grown[y, x] == 0:
                cov[y, x] = zero
                continue
            v = (white32 - patch[y, x]) / span32
            v = zero if v < zero else (one if v > one else v)
            cov[y, x] = v
            if v > half:
                d = abs(np.float64(x) - cx0)
                if d < best:
                    best = d
                    j[y] = x
        rows_ok[y] = best < 0.25 * w
    widths, _, bounded = iris_runs(cov, j, rows_ok, grown)
    return widths, bounded


# ---------------------------------------------------------------------------- eye measures
# The rest of core/faces/iris.py's fit (the iris circle's height, the opening's centres) and
# the lids' and brows' pixel measures after their resampling (lids.iris_height,
# brows.brow_band_mm), each in one compiled call: numpy's own float32 / float64 arithmetic
# and its pairwise sums, so the same numbers to the bit; the numpy code is the reference
# (a test checks each against it). Each was a chain of ~10-30 small numpy calls per eye.


@njit(cache=True, nogil=True)
def iris_circle_height(ys, wk, r, cys):  # pragma: no cover - compiled
    """iris.fit_iris's least-absolute-deviation search of the circle's height: the ``cys``
    (C,) whose chords of a circle of radius ``r`` (each row ``ys`` (N,) float64 the mean of
    two sub-rows, iris._SUB) fit the widths ``wk`` (N,) float32 best (the first minimum)."""
    n = ys.shape[0]
    sub0, sub1 = -0.25, 0.25
    rr = r * r
    dev = np.empty(n)
    best = np.inf
    at = 0
    for c in range(cys.shape[0]):
        for i in range(n):
            y0 = (ys[i] + sub0) - cys[c]
            y1 = (ys[i] + sub1) - cys[c]
            p0 = 2.0 * np.sqrt(max(rr - y0 * y0, 0.0))
            p1 = 2.0 * np.sqrt(max(rr - y1 * y1, 0.0))
            dev[i] = abs((p0 + p1) / 2.0 - np.float64(wk[i]))
        s = _pairwise_sum(dev, 0, n)
        if s < best:
            best = s
            at = c
    return cys[at]


@njit(cache=True, nogil=True)
def parabola_of(t, w, n):  # pragma: no cover - compiled
    """(a, b) of the least-squares parabola a t^2 + b t + c through (t[:n], w[:n]) by the
    normal equations in closed form (Cramer's rule): iris._parabola and opening_centres."""
    s0 = np.float64(n)
    s1 = s2 = s3 = s4 = w0 = w1 = w2 = 0.0
    for i in range(n):
        s1 += t[i]
    for i in range(n):
        s2 += t[i] * t[i]
    for i in range(n):
        s3 += t[i] ** 3
    for i in range(n):
        s4 += t[i] ** 4
    for i in range(n):
        w0 += w[i]
    for i in range(n):
        w1 += t[i] * w[i]
    for i in range(n):
        w2 += t[i] * t[i] * w[i]
    det = s4 * (s2 * s0 - s1 * s1) - s3 * (s3 * s0 - s1 * s2) + s2 * (s3 * s1 - s2 * s2)
    if abs(det) < 1e-12:
        return 0.0, 0.0
    da = w2 * (s2 * s0 - s1 * s1) - s3 * (w1 * s0 - s1 * w0) + s2 * (w1 * s1 - s2 * w0)
    db = s4 * (w1 * s0 - w0 * s1) - w2 * (s3 * s0 - s1 * s2) + s2 * (s3 * w0 - w1 * s2)
    return da / det, db / det


@njit(cache=True, nogil=True)
def opening_centres(frac, n_open):  # pragma: no cover - compiled
    """iris._opening_centres of the ``n_open`` openings stacked in ``frac`` (n_open * rows,
    cols) float32: (n_open, 3) rows of (x, y, found) px in the crop (found 0: fewer than 3
    rows of it)."""
    total, cols = frac.shape
    rows = total // n_open
    half = np.float32(0.5)
    widths = np.zeros(total)
    mids = np.empty(total)
    has = np.zeros(total, np.bool_)
    for y in range(total):
        a = -1
        b = -1
        for x in range(cols):
            if frac[y, x] >= half:
                if a < 0:
                    a = x
                b = x
        if a < 0:  # (numpy's argmax of a row without any: 0, and cols - 1 from the end)
            a, b = 0, cols - 1
        else:
            has[y] = True
        fa = np.float64(frac[y, a - 1]) if a > 0 else 0.0
        fb = np.float64(frac[y, b + 1]) if b < cols - 1 else 0.0
        left = (np.float64(a) - 0.5) - fa
        right = (np.float64(b) + 0.5) + fb
        if has[y]:
            widths[y] = right - left
        mids[y] = (left + right) / 2.0
    out = np.zeros((n_open, 3))
    t = np.empty(7)
    w = np.empty(7)
    for o in range(n_open):
        lo_row = o * rows
        n_has = 0
        for y in range(rows):
            if has[lo_row + y]:
                n_has += 1
        if n_has < 3:
            continue
        k = 0
        for y in range(1, rows):
            if widths[lo_row + y] > widths[lo_row + k]:
                k = y
        wk = widths[lo_row + k]
        acc = 0.0
        cnt = 0
        for y in range(max(k - 2, 0), min(k + 3, rows)):
            if widths[lo_row + y] > 0.6 * wk:
                acc += mids[lo_row + y]
                cnt += 1
        ex = acc / cnt
        ey = np.float64(k)
        n_pts = 0
        for y in range(max(k - 3, 0), min(k + 4, rows)):
            if widths[lo_row + y] > 0:
                t[n_pts] = np.float64(y - k)
                w[n_pts] = widths[lo_row + y]
                n_pts += 1
        if n_pts >= 3:
            a2, b2 = parabola_of(t, w, n_pts)
            if a2 < 0 and abs(b2 / (2.0 * a2)) <= 1.5:
                ey = k - b2 / (2.0 * a2)
        out[o, 0] = ex
        out[o, 1] = ey
        out[o, 2] = 1.0
    return out


@njit(cache=True, nogil=True)
def dark_height(strip, skin, iris):  # pragma: no cover - compiled
    """lids.iris_height after its strip (rows, cols) float32: the mean dark count (float32,
    as numpy's mean) of the tallest quarter of the columns, each pixel dark by the soft
    threshold of how far it is from ``skin`` towards ``iris``."""
    h, w = strip.shape
    skin32 = np.float32(skin)
    span32 = np.float32(skin - iris)
    q = np.float32(0.25)
    two = np.float32(2.0)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    dark = np.empty(w, np.float32)
    for x in range(w):
        acc = zero
        for y in range(h):
            v = ((skin32 - strip[y, x]) / span32 - q) * two
            v = zero if v < zero else (one if v > one else v)
            acc = v if y == 0 else acc + v
        dark[x] = acc
    dark = np.sort(dark)
    lo = (3 * w) // 4
    tall = np.ascontiguousarray(dark[lo:])
    s = _pairwise_sum(tall, 0, w - lo)
    return np.float32(np.float64(s) / np.float64(w - lo))


@njit(cache=True, nogil=True)
def brow_half(sub, top_mm, scale):  # pragma: no cover - compiled
    """brows.brow_band_mm's search in one half's window ``sub`` (rows, cols) float32 of the
    smoothed strip, row 0 at ``top_mm`` above the eye line, ``scale`` px per mm: (found,
    height mm): the median over the columns of the darkest row, sub-pixel by a parabola;
    found False when fewer than half of the columns have their minimum inside."""
    rows, cols = sub.shape
    k = np.empty(cols, np.int64)
    n_in = 0
    for c in range(cols):
        b = 0
        for y in range(1, rows):
            if sub[y, c] < sub[b, c]:
                b = y
        k[c] = b
        if b > 0 and b < rows - 1:
            n_in += 1
    if 2 * n_in < cols:  # (inside.mean() < 0.5)
        return False, 0.0
    hs = np.empty(n_in)
    two = np.float32(2.0)
    half = np.float32(0.5)
    eps = np.float32(1e-6)
    zero = np.float32(0.0)
    i = 0
    for c in range(cols):
        b = k[c]
        if not (b > 0 and b < rows - 1):
            continue
        y_m, y_0, y_p = sub[b - 1, c], sub[b, c], sub[b + 1, c]
        den = y_m - two * y_0 + y_p
        frac = half * (y_m - y_p) / max(den, eps) if den > eps else zero
        frac = -half if frac < -half else (half if frac > half else frac)
        hs[i] = top_mm - (np.float64(b) + np.float64(frac)) / scale
        i += 1
    hs = np.sort(hs)
    return True, (hs[(n_in - 1) // 2] + hs[n_in // 2]) / 2.0


TRACKER = ("la_residuals", "cauchy", "gn_terms", "lm_step", "fit_information", "pixels_sd2",
           "occlusion_votes", "sample_uv", "roi_box")
"""The kernels the appearance tracker calls (``core/tracking/fitting.py``; a session with no
speaker, e.g. ``articast demo``): about half of the compilation of all of them (35 of 65 s of
CPU on this 2-core machine). The landmark, iris and Kalman kernels are the live tracker's."""


def warm_up(only: tuple[str, ...] | None = None) -> None:
    """Compile (or load from the on-disk cache) the kernels for the tracker's argument
    types, so that a session's first frame does not pay a few seconds of compilation.
    ``only``: those kernels (e.g. :data:`TRACKER`), else every one."""
    if not AVAILABLE:
        return

    def want(*names: str) -> bool:
        return only is None or any(n in only for n in names)

    f8 = np.float64
    src = np.zeros((20, 20, 3), np.uint8)
    dist = np.zeros(5)
    dist.setflags(write=False)  # as Camera.dist: a writable one compiled a type never used
    intr = np.array([100.0, 100.0, 10.0, 10.0])
    if want("la_residuals"):
        la_residuals(np.zeros((20, 20, 3), np.float32), 0.0, 0.0, 1.0, 2.0, np.zeros(1, f8),
                     np.eye(3), np.array([0.0, 0.0, 100.0]), np.zeros((1, 3), f8),
                     np.zeros((1, 3, 1), f8), np.array([100.0, 100.0, 10.0, 10.0]), dist,
                     np.zeros(8, f8), np.zeros((1, 8), f8), np.zeros((0, 0), f8), 1.0,
                     np.ones((1, 8), f8), True, True, src, np.zeros((20, 20), np.uint8),
                     np.zeros((20, 20, 3), np.float32), np.zeros((20, 20), np.uint8),
                     np.full(5, 0.2))
    if want("cauchy"):
        cauchy(np.zeros(8, f8), np.zeros((8, 2), f8), 8, 2.0)
        cauchy(np.zeros(8, f8), np.zeros((0, 0), f8), 8, 2.0)
    if want("point_residuals"):
        for jacobian in (True, False):
            point_residuals(np.zeros((1, 3), f8), np.zeros((1, 3, 1), f8), np.zeros(1, f8),
                            np.eye(3), np.array([0.0, 0.0, 100.0]),
                            np.array([100.0, 100.0, 10.0, 10.0]), np.ones(1), np.zeros((1, 2)),
                            jacobian)
    if want("gn_terms", "lm_step"):  # (fit_terms, lm_system and lm_solve inside them)
        # gn_terms's arguments after the state (alpha, rot, t, gain): one landmark with one
        # shared error mode, a state prior, a pose prior
        rest = (np.zeros((20, 20, 3), np.float32), 0.0, 0.0, 1.0, 2.0, np.zeros((1, 3), f8),
                np.zeros((1, 3, 1), f8), intr, dist, np.zeros(8, f8), np.zeros((1, 8), f8),
                np.zeros((0, 0), f8), np.ones((1, 8), f8), True, src,
                np.zeros((20, 20), np.uint8), np.zeros((20, 20, 3), np.float32),
                np.zeros((20, 20), np.uint8), np.full(5, 0.2), np.zeros((3, 8), f8),
                np.eye(3), 0.05, 1.0, 2.0, np.zeros((1, 3), f8), np.zeros((1, 3, 1), f8),
                intr, np.ones(1), np.zeros((1, 2)), 3.0, np.ones(1), 1.0, 0.25, np.zeros(1),
                np.eye(3), np.zeros(3), np.eye(7), np.eye(3), np.zeros(3), 1.0, 1.0,
                np.ones((2, 1)), np.ones((1, 1)), 0.0, np.zeros(1), 1.0, 1.0)
        state = (np.zeros(1, f8), np.eye(3), np.array([0.0, 0.0, 100.0]), 1.0)
        cost, _, _, _, _, jw, g_p, h_p, g_s, h_s, _ = gn_terms(*state, *rest)
        lm_step(jw.T @ jw, np.zeros(jw.shape[1]), 1e-3, 2, cost, h_p, g_p, h_s, g_s, *state,
                *rest)
    if want("fit_information"):
        fit_information(np.eye(8), np.zeros((7, 7)), 7, 1.0)
    if want("sample_uv"):
        sample_uv(np.zeros((1, 3), f8), np.zeros((1, 3), f8), np.zeros(1, f8), np.eye(3),
                  np.array([0.0, 0.0, 100.0]), intr)
    if want("roi_box"):
        roi_box(np.zeros((1, 2)), 1.0)
    frame = np.zeros((16, 16, 3), np.uint8)
    for writable in (True, False):  # (a frame may come read-only)
        frame.setflags(write=writable)
        if want("pixels_sd3"):
            pixels_sd3(frame[::8, ::8])
        if want("pixels_sd2"):
            pixels_sd2(frame[::4, ::4, 1])
    if only is not None and "facing_cos" in only:  # (Tracker.facing alone: not a frame's)
        facing_cos(np.zeros((2, 3)), np.ones((2, 3)), np.eye(3), np.array([0.0, 0.0, 100.0]))
    if want("occlusion_votes"):
        occlusion_votes(np.ones(2), np.ones(2, np.bool_), np.zeros((2, 3)), np.ones((2, 3)),
                        np.eye(3), np.array([0.0, 0.0, 100.0]), 0.2, 1.0, 10.0, 3.0,
                        np.ones(2), 1.0)
    if want("state_measured"):
        state_measured(np.zeros(1, f8), np.eye(3), np.zeros(3), np.eye(7), np.zeros(1, f8),
                       np.eye(1))
    if want("point_offset"):
        point_offset(np.zeros((1, 3), f8), np.zeros((1, 3, 1), f8), np.zeros(1, f8),
                     np.eye(3), np.array([0.0, 0.0, 100.0]), intr, np.zeros((1, 2)))
    if want("reading_features"):
        reading_features(np.random.default_rng(0).normal(0, 50, (8, 3)), np.eye(3),
                         np.array([0.0, 0.0, 500.0]), intr, np.zeros((8, 2)))
    if want("iris_circle_height", "opening_centres", "dark_height", "brow_half"):
        eye = np.random.default_rng(2).uniform(0, 1, (8, 14)).astype(np.float32)
        iris_circle_height(np.arange(3.0), np.ones(3, np.float32), 2.0, np.arange(0.0, 2.0, 0.5))
        opening_centres(eye, 2)
        dark_height(eye[:, 2:12], 200.0, 40.0)  # (views: the strips are column slices)
        brow_half(eye[1:7, 2:12], 20.0, 2.0)
    if want("lip_ratio"):
        lip_ratio(np.zeros((6, 3), f8), np.zeros((1, 18), f8), np.eye(3),
                  np.array([0.0, 0.0, 100.0]), intr, np.zeros(1, f8))
    if want("lip_gap"):
        lip_gap(np.zeros((6, 3), f8), np.zeros((1, 18), f8), np.eye(3),
                np.array([0.0, 0.0, 100.0]), intr, np.zeros(1, f8), np.zeros(1, f8), 0.1, 0.5,
                1e-3, 3.0, 1e-4)
    if want("iris_chords", "iris_former_rows"):
        eye = np.zeros((8, 12), np.float32)
        mask = np.ones((8, 12), np.uint8)
        iris_chords(eye, mask, mask, 1.0, 0.0, 2.0, 5.0, 0.75)
        iris_former_rows(eye, mask, 0.0, 30.0, 5.0)
    if want("cv_predict", "cv_update"):
        cov, info, *_ = cv_predict(np.eye(14), np.ones(7), 0.04**3, 0.04**2, 0.04,
                                   np.zeros(1), np.zeros(7), np.zeros(3), np.eye(3), 1.0)
        for information in (np.eye(7), np.zeros((0, 0))):
            cv_update(cov, info, np.zeros(1), np.zeros(1), np.eye(3), np.zeros(3), np.zeros(3),
                      np.zeros(7), information)


def compiled_on_disk(only: tuple[str, ...] | None = None) -> bool:
    """Whether numba's on-disk cache already holds the kernels (False: :func:`warm_up` will
    compile them, a few seconds); ``only``: those. Reads numba's cache index; True when it
    cannot tell."""
    if not AVAILABLE:
        return True
    try:
        every: tuple[Any, ...] = (la_residuals, cauchy, point_residuals, gn_terms,
                                  lm_step, fit_information, sample_uv, roi_box, state_measured,
                                  pixels_sd3, pixels_sd2, occlusion_votes,
                                  point_offset, lip_gap,
                                  reading_features, cv_predict, cv_update, iris_chords,
                                  iris_former_rows, iris_circle_height,
                                  opening_centres, dark_height, brow_half)
        kernels = [f for f in every if only is None or f.__name__ in only]
        return all(os.path.exists(f._cache._cache_file._index_path)  # noqa: SLF001
                   for f in kernels)
    except AttributeError:  # another numba's internals
        return True

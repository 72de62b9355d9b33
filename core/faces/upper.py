"""The upper face: eyelids, gaze and brows, per frame, relative to the speaker's own references.

Everything here reads the live reader's 468 landmarks (FaceMesh v1 topology; the first 468 of
FaceLandmarker v2's 478 are the same points) and the frame's pixels:

- **pose removed**: the reading is aligned (similarity Procrustes, MediaPipe's own rigid
  points, none on a lid or a brow) onto the metric canonical face
  (:mod:`articast.core.faces.canonical`), so every measure is in mm of a head frame (x the
  speaker's left, y up, z forward) whatever the head's pose and distance;
- **eyelids**: the lid opening (mean of three upper/lower lid pairs, mm) against the speaker's
  open-eye and closed-eye references from enrolment -> closure 0 (open) .. 1 (closed), so a
  narrow-eyed speaker is not "half closed";
- **blinks between readings**: the reader runs every other frame (``FusionPolicy.read_every``),
  and a blink lasts 3-9 frames. On every frame a photometric eye measure is taken: the
  contrast (grey-level s.d.: sclera, iris, lash line; a closed lid is skin) of an ellipse over
  the open eye relative to the skin of a ring around it, the ellipse placed by the last
  reading's eye corners moved with the tracked head. Enrolment fits it to the reader's
  closure (a straight line per eye, :func:`calibrate`), and frames without a reading take
  their closure from it (or hold the last reading's where that line fits poorly);
- **gaze**: the iris is the darkest blob inside the eye's contour; its centre's offset from
  the corners' midpoint, in mm of the aligned frame, less the speaker's own looking-at-the-
  camera offset, over the eyeball's radius -> yaw (to the speaker's left +) and pitch (up +)
  in degrees;
- **brows**: inner / outer point heights above the eye corners' line, mm, less the speaker's
  neutral (the enrolment's median): raise > 0, lowering = how far the inner brows come down.
  These are the landmark network's brows, which follow its face prior more than the pixels
  (on the synthetic speaker they moved 0.7 mm for a painted 6 mm raise: docs/UPPER_FACE.md).

Nothing here reads a clock or a file; :class:`UpperReference` is what ``enroll`` stores
(speaker.json ``upper``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from articast.core.errors import ModelFileError
from articast.core.faces.canonical import CanonicalFace, canonical_face

SIDES = ("left", "right")
"""The speaker's own left and right (ARKit's and VRM's convention)."""
EYE_CORNERS = {"left": (362, 263), "right": (133, 33)}
"""(inner, outer) corners of each eye."""
LID_PAIRS = {"left": ((386, 374), (385, 380), (387, 373)),
             "right": ((159, 145), (158, 153), (160, 144))}
"""(upper, lower) lid landmark pairs, middle first."""
EYE_CONTOUR = {
    "left": (362, 398, 384, 385, 386, 387, 388, 466, 263, 249, 390, 373, 374, 380, 381, 382),
    "right": (133, 173, 157, 158, 159, 160, 161, 246, 33, 7, 163, 144, 145, 153, 154, 155)}
"""Each eye's contour, in order round the eye."""
BROW_POINTS = {"left": {"inner": (336, 285), "outer": (300, 276)},
               "right": {"inner": (107, 55), "outer": (70, 46)}}
"""Brow landmarks (upper, lower edge) at the inner and outer ends."""
EYE_RADIUS_MM = 11.5
"""Distance of the iris from the eyeball's centre of rotation (adult eyeball ~24 mm)."""
MAX_YAW_DEG = 40.0
"""Head turned further than this from the camera: the far eye is not seen (eyes not ok)."""


@dataclass(frozen=True)
class UpperReference:
    """The speaker's own upper face at enrolment (speaker.json ``upper``).

    open_mm, closed_mm : (left, right) lid opening of the open eye (the clip's median: the
        speaker's usual open eye) and of the closed eye (the clip's deepest blinks, its 1st
        percentile; when the clip has none, a fixed fraction of the open eye and ``blinks`` is
        0). With the 90th percentile as the open eye, a laughing speaker's squint (the
        cheeks push the lower lids up) read 0.52-0.58 on franck, a blink; with the median
        0.4 (docs/UPPER_FACE.md).
    brows_mm : (left inner, left outer, right inner, right outer) neutral brow heights above
        the eye line (the clip's median).
    iris_mm : (left x, left y, right x, right y) the iris's median offset from the eye
        opening's centre over the clip, mm (reported: where the speaker looked while enrolling;
        not the gaze's zero, which is the iris centred in the opening: docs/UPPER_FACE.md).
    iris_radius_mm : (left, right) the speaker's visible iris radius (the clip's median of
        each frame's widest iris chord / 2); 0: not measured (an older speaker.json), each
        frame's own widest chord is used.
    photo : (left a, left b, right a, right b): closure = a + b x the photometric eye measure;
        photo_r : (left, right) its correlation with the reader's closure on the clip (a
        side below 0.5 in magnitude is not used: frames between readings hold the last
        closure).
    blinks : blinks the clip held (closure runs above 0.5); frames : frames measured.
    """

    open_mm: tuple[float, float]
    closed_mm: tuple[float, float]
    brows_mm: tuple[float, float, float, float]
    iris_mm: tuple[float, float, float, float]
    photo: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    photo_r: tuple[float, float] = (0.0, 0.0)
    blinks: int = 0
    frames: int = 0
    iris_radius_mm: tuple[float, float] = (0.0, 0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"open_mm": list(self.open_mm), "closed_mm": list(self.closed_mm),
                "brows_mm": list(self.brows_mm), "iris_mm": list(self.iris_mm),
                "photo": list(self.photo), "photo_r": list(self.photo_r),
                "blinks": int(self.blinks), "frames": int(self.frames),
                "iris_radius_mm": list(self.iris_radius_mm)}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> UpperReference:
        sizes = {"open_mm": 2, "closed_mm": 2, "brows_mm": 4, "iris_mm": 4, "photo": 4,
                 "photo_r": 2}
        if isinstance(d, dict) and "iris_radius_mm" in d:  # (absent before it was measured)
            sizes["iris_radius_mm"] = 2
        try:
            vals = {k: tuple(float(x) for x in d[k]) for k in sizes}
            blinks, frames = int(d["blinks"]), int(d["frames"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{where}: the upper-face block is malformed ({exc})") from None
        bad = [k for k, n in sizes.items()
               if len(vals[k]) != n or not all(math.isfinite(v) and abs(v) < 1e3
                                               for v in vals[k])]
        if bad or not all(o > c > 0 for o, c in zip(vals["open_mm"], vals["closed_mm"],
                                                    strict=True)):
            raise ModelFileError(f"{where}: the upper-face block needs finite numbers and an "
                                 f"open eye wider than the closed one ({', '.join(bad)})")
        return cls(**vals, blinks=blinks, frames=frames)  # type: ignore[arg-type]


@dataclass(frozen=True)
class UpperFace:
    """One frame's upper face. ``eyes_ok`` / ``brows_ok`` False: the values are None and
    the reason (a code word, ``:``, a sentence) says why: ``not_seen`` (a head-mounted camera
    sees the lower face only), ``no_face``, ``turned`` (the head turned too far for both
    eyes), ``left_image``, ``not_calibrated`` (a speaker enrolled before this version).

    closure_* : 0 open .. 1 closed; source ``reader`` (the landmarks this frame) or ``photo``
    (the photometric measure between readings). gaze_* : degrees, yaw to the speaker's left +,
    pitch up +. raise_* : mm above the neutral brow; lowering_mm : inner brows below it."""

    eyes_ok: bool
    eyes_reason: str = ""
    closure_left: float | None = None
    closure_right: float | None = None
    gaze_yaw_deg: float | None = None
    gaze_pitch_deg: float | None = None
    source: str = ""
    brows_ok: bool = False
    brows_reason: str = ""
    raise_inner_left_mm: float | None = None
    raise_outer_left_mm: float | None = None
    raise_inner_right_mm: float | None = None
    raise_outer_right_mm: float | None = None
    lowering_mm: float | None = None

    @classmethod
    def absent(cls, reason: str) -> UpperFace:
        return cls(False, reason, brows_ok=False, brows_reason=reason)

    def eyes_dict(self) -> dict[str, Any]:
        """The ``eyes`` block of a track line / wire frame."""
        return {"ok": self.eyes_ok, "reason": self.eyes_reason,
                "closure_left": _r(self.closure_left), "closure_right": _r(self.closure_right),
                "gaze_yaw_deg": _r(self.gaze_yaw_deg), "gaze_pitch_deg": _r(self.gaze_pitch_deg)}

    def brows_dict(self) -> dict[str, Any]:
        """The ``brows`` block of a track line / wire frame."""
        return {"ok": self.brows_ok, "reason": self.brows_reason,
                "raise_left_mm": _mean(self.raise_inner_left_mm, self.raise_outer_left_mm),
                "raise_right_mm": _mean(self.raise_inner_right_mm, self.raise_outer_right_mm),
                "raise_inner_left_mm": _r(self.raise_inner_left_mm),
                "raise_outer_left_mm": _r(self.raise_outer_left_mm),
                "raise_inner_right_mm": _r(self.raise_inner_right_mm),
                "raise_outer_right_mm": _r(self.raise_outer_right_mm),
                "lowering_mm": _r(self.lowering_mm)}

    @classmethod
    def from_dicts(cls, eyes: Any, brows: Any) -> UpperFace | None:
        """Back from a track line's blocks (None when it has none)."""
        if not isinstance(eyes, dict) or not isinstance(brows, dict):
            return None

        def num(d: dict, k: str, lo: float, hi: float) -> float | None:
            """A plausible number, or None (a hostile or broken file: never a crash
            downstream, e.g. a FAP of 1e308 degrees)."""
            v = d.get(k)
            if not isinstance(v, int | float) or isinstance(v, bool):
                return None
            return float(v) if lo <= v <= hi else None  # (NaN fails the comparison)

        mm = (-100.0, 100.0)
        cl = [num(eyes, k, 0.0, 1.0) for k in ("closure_left", "closure_right")]
        gz = [num(eyes, k, -90.0, 90.0) for k in ("gaze_yaw_deg", "gaze_pitch_deg")]
        br = [num(brows, k, *mm) for k in ("raise_inner_left_mm", "raise_outer_left_mm",
                                           "raise_inner_right_mm", "raise_outer_right_mm")]
        eyes_ok = bool(eyes.get("ok")) and None not in cl
        brows_ok = bool(brows.get("ok")) and None not in br
        return cls(eyes_ok, str(eyes.get("reason", ""))[:200], cl[0], cl[1], gz[0], gz[1], "",
                   brows_ok, str(brows.get("reason", ""))[:200], br[0], br[1], br[2], br[3],
                   num(brows, "lowering_mm", *mm))


def _r(v: float | None, nd: int = 4) -> float | None:
    return None if v is None else round(float(v), nd)


def _mean(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else round((a + b) / 2.0, 4)


# ---------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class Aligned:
    """A reading aligned onto the canonical face: points (468, 3) mm, head frame; scale px per
    mm; yaw_deg the head's turn (from the alignment's rotation)."""

    points: np.ndarray
    scale: float
    yaw_deg: float


def align(landmarks: np.ndarray, canon: CanonicalFace) -> Aligned | None:
    """Similarity Procrustes of a reading (>=468, 3: x, y px, z depth px, image frame) onto
    the canonical face on MediaPipe's rigid points; None for a degenerate reading."""
    lm = np.asarray(landmarks, np.float64)[:468]
    src = np.column_stack([lm[:, 0], -lm[:, 1], -lm[:, 2]])  # -> x right, y up, z forward
    ids, w = canon.procrustes_ids, canon.procrustes_weights
    a, b = src[ids], canon.vertices_mm[ids]
    wn = w / w.sum()
    ma, mb = wn @ a, wn @ b
    ac, bc = a - ma, b - mb
    cov = (bc * wn[:, None]).T @ ac
    if not np.all(np.isfinite(cov)):
        return None
    u, s, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, 1.0, d]) @ vt  # src -> canonical
    var = float((wn * np.sum(ac ** 2, axis=1)).sum())
    if var <= 1e-9:
        return None
    scale = float((s * [1.0, 1.0, d]).sum() / var)  # mm per px
    if not np.isfinite(scale) or scale <= 0:
        return None
    pts = (src - ma) @ rot.T * scale + mb
    # rot maps the face's frame as seen to the canonical: its inverse is the head's rotation
    head = rot.T
    yaw = math.degrees(math.atan2(head[0, 2], head[2, 2]))
    return Aligned(pts, 1.0 / scale, yaw)


def lid_opening_mm(points: np.ndarray) -> tuple[float, float]:
    """(left, right) lid opening, mm: mean upper-minus-lower height of the three lid pairs."""
    return tuple(float(np.mean([points[u, 1] - points[lo, 1] for u, lo in LID_PAIRS[s]]))
                 for s in SIDES)  # type: ignore[return-value]


def brow_heights_mm(points: np.ndarray) -> np.ndarray:
    """(left inner, left outer, right inner, right outer) brow heights above the eye line,
    mm (each brow point pair's mean height minus its eye corners' mean height)."""
    out = []
    for s in SIDES:
        eye_y = float(points[list(EYE_CORNERS[s]), 1].mean())
        for end in ("inner", "outer"):
            out.append(float(points[list(BROW_POINTS[s][end]), 1].mean()) - eye_y)
    return np.array(out)


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


IRIS_MIN_ROWS = 3
"""An iris seen on fewer rows (chords bounded by white on both sides) is not fitted."""
_SUB = (np.arange(4) + 0.5) / 4.0 - 0.5  # sub-rows of a pixel row (a chord is a row's mean)


def fit_iris(grey: np.ndarray, landmarks: np.ndarray, side: str,
             radius_px: float | None = None) -> IrisFit | None:
    """The iris as a circle fitted to its visible edge, and the eye opening it sits in.

    In the eye's crop (the reader's contour grown by 3 px: the contour is a guide, the pixels
    decide), the grey levels give the iris (the median of what is darker than midway between
    the contour's darkest and lightest tenths), the white (the 75th percentile of the rest)
    and the skin (the median round the contour). Each row's **chord** is the run of iris
    round the iris's column, bounded by white on both sides (a row that meets a lid, a lash
    line or the crop's edge is left out), its width the sum of the pixels' iris fractions
    (sub-pixel). The lids cover the iris's top and bottom, so its dark centroid hardly moves
    vertically; the chords' widths do: a circle of radius r whose centre is at height c has
    chords 2 sqrt(r^2 - (y - c)^2), and c is the height that fits the widths best (least
    absolute deviations over a grid of 1/20 px), r the speaker's iris radius (``radius_px``,
    from enrolment) or this frame's widest chord / 2. The iris's x is the chords' centroid.

    The **eye's own centre** replaces the reader's corners (which jitter by ~1 px and move
    with the iris on a rendered eye): the opening is what is whiter than midway between skin
    and white inside the grown contour; its widest row is its height (a parabola through the
    widths round the widest), the middle of its ends on the rows within 2 of it (ends
    sub-pixel from the next pixel's white fraction) its x. None when the eye is too closed,
    too small or outside the image, or no iris/white contrast is found."""
    poly = np.asarray(landmarks, np.float64)[list(EYE_CONTOUR[side]), :2]
    if not np.all(np.isfinite(poly)):
        return None
    x0, y0 = np.floor(poly.min(0)).astype(int) - 3
    x1, y1 = np.ceil(poly.max(0)).astype(int) + 4
    h, w = grey.shape[:2]
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h or x1 - x0 < 12 or y1 - y0 < 8:
        return None
    patch = _grey(grey[y0:y1, x0:x1]).astype(np.float32)
    contour = np.zeros(patch.shape, np.uint8)
    cv2.fillPoly(contour, [np.round(poly - [x0, y0]).astype(np.int32)], 1)
    grown = cv2.dilate(contour, np.ones((5, 5), np.uint8))
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
    if white - iris_l < 20.0 or white - skin < 8.0:
        return None  # no iris/white contrast (a closed or unlit eye)
    # --- the iris's chords
    cov = np.clip((white - patch) / (white - iris_l), 0.0, 1.0) * (grown > 0)
    wgt = np.clip(thr - patch, 0.0, None) * contour
    if float(wgt.sum()) <= 0:
        return None
    cols = np.arange(patch.shape[1], dtype=np.float64)
    cx0 = float((wgt.sum(0) * cols).sum() / wgt.sum())
    brk = cov <= 0.12  # white (or outside): a chord's bound
    run = np.cumsum(brk, axis=1)
    dist = np.where(cov > 0.5, np.abs(cols - cx0)[None, :], np.inf)
    j = np.argmin(dist, axis=1)
    rows_ok = dist[np.arange(len(j)), j] < 0.5 * patch.shape[1] / 2
    mine = (run == run[np.arange(len(j)), j][:, None]) & ~brk
    first = np.argmax(mine, axis=1)
    last = patch.shape[1] - 1 - np.argmax(mine[:, ::-1], axis=1)
    bounded = rows_ok & (first > 0) & (last < patch.shape[1] - 1)
    bounded &= grown[np.arange(len(j)), np.maximum(first - 1, 0)] > 0
    bounded &= grown[np.arange(len(j)), np.minimum(last + 1, patch.shape[1] - 1)] > 0
    widths = (cov * mine).sum(1)
    cxs = (cov * mine * cols).sum(1) / np.maximum(widths, 1e-9)
    half = float(widths[bounded].max()) / 2.0 if bounded.any() else 0.0
    r = float(radius_px) if radius_px else half
    keep = bounded & (widths <= 2.0 * r + 1.0) & (widths > 0.5)
    if keep.sum() < IRIS_MIN_ROWS or r < 1.5:
        return None
    ys = np.flatnonzero(keep).astype(np.float64)
    wk = widths[keep]
    cy = 0.0
    for cys in (np.arange(ys[0] - r, ys[-1] + r, 0.25), None):  # coarse, then fine
        if cys is None:
            cys = cy + np.arange(-0.25, 0.2501, 0.025)
        yy = (ys[:, None] + _SUB[None, :]).ravel()[None, :] - cys[:, None]
        pred = (2.0 * np.sqrt(np.clip(r * r - yy * yy, 0.0, None))).reshape(
            len(cys), len(ys), len(_SUB)).mean(-1)
        cy = float(cys[int(np.argmin(np.abs(pred - wk[None, :]).sum(1)))])
    cx = float(np.average(cxs[keep], weights=wk))
    # --- the eye opening's own centre
    frac = np.clip((patch - skin) / (white - skin), 0.0, 1.0) * (grown > 0)
    bright = frac >= 0.5
    has = bright.any(1)
    if has.sum() < 3:
        return None
    a = np.argmax(bright, axis=1)
    b = patch.shape[1] - 1 - np.argmax(bright[:, ::-1], axis=1)
    ri = np.arange(len(a))
    left = a - 0.5 - np.where(a > 0, frac[ri, np.maximum(a - 1, 0)], 0.0)
    right = b + 0.5 + np.where(b < patch.shape[1] - 1,
                               frac[ri, np.minimum(b + 1, patch.shape[1] - 1)], 0.0)
    width = np.where(has, right - left, 0.0)
    k = int(np.argmax(width))
    near = (np.abs(ri - k) <= 2) & (width > 0.6 * width[k])
    ex = float(np.mean((left[near] + right[near]) / 2.0))
    ey = float(k)
    round_k = (np.abs(ri - k) <= 3) & (width > 0)
    if round_k.sum() >= 3:  # a parabola through the widths round the widest row
        t = (ri[round_k] - k).astype(np.float64)
        v = np.stack([t * t, t, np.ones_like(t)], axis=1)
        a2, b2, _ = np.linalg.solve(v.T @ v + 1e-9 * np.eye(3), v.T @ width[round_k])
        if a2 < 0 and abs(b2 / (2.0 * a2)) <= 1.5:
            ey = k - float(b2 / (2.0 * a2))
    return IrisFit(np.array([cx + x0, cy + y0]), half, np.array([ex + x0, ey + y0]),
                   int(keep.sum()))


def iris_offset_mm(grey: np.ndarray, landmarks: np.ndarray, aligned: Aligned,
                   side: str, radius_mm: float | None = None
                   ) -> tuple[float, float, float] | None:
    """The iris's offset (x to the speaker's left, y up; mm of the aligned frame) from the eye
    opening's own centre (:func:`fit_iris`), and the visible iris's widest half-chord (mm);
    None when the iris is not fitted. ``radius_mm``: the speaker's iris radius (enrolment)."""
    fit = fit_iris(grey, landmarks, side,
                   None if not radius_mm else radius_mm * aligned.scale)
    if fit is None:
        return None
    inner, outer = EYE_CORNERS[side]
    lm = np.asarray(landmarks, np.float64)
    # image px -> the aligned frame's x, y: the in-plane rotation of the corners' axis (its
    # angle: ~1 px of jitter over the eye's width moves a 2 mm offset by < 0.1 mm) and the
    # alignment's scale (all the rigid points: steadier than the corners' distance)
    ax_img = lm[outer, :2] - lm[inner, :2]
    ax_al = aligned.points[outer, :2] - aligned.points[inner, :2]
    ang = math.atan2(ax_al[1], ax_al[0]) - math.atan2(-ax_img[1], ax_img[0])
    d = np.array([fit.centre[0] - fit.eye[0], -(fit.centre[1] - fit.eye[1])]) / aligned.scale
    ca, sa = math.cos(ang), math.sin(ang)
    return (float(ca * d[0] - sa * d[1]), float(sa * d[0] + ca * d[1]),
            fit.half_width / aligned.scale)


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


def _grey(patch: np.ndarray) -> np.ndarray:
    """A crop of a grey or BGR image, grey (only the crop is converted: cheaper than the
    frame)."""
    return patch if patch.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(patch),
                                                       cv2.COLOR_BGR2GRAY)


# ---------------------------------------------------------------------------- per frame
@dataclass(frozen=True)
class Measures:
    """One reading's raw measures (mm, before the speaker's references)."""

    opening: tuple[float, float]
    brows: np.ndarray
    iris: tuple[tuple[float, float, float] | None, tuple[float, float, float] | None]
    photo: tuple[float | None, float | None]
    yaw_deg: float
    scale: float  # px per mm


def measure(grey: np.ndarray, landmarks: np.ndarray, canon: CanonicalFace,
            open_mm: tuple[float, float] | None = None,
            iris_radius_mm: tuple[float, float] | None = None) -> Measures | None:
    """The raw measures of one reading (``open_mm``: the ellipse height of the photometric
    measure; default: this reading's own opening; ``iris_radius_mm``: the speaker's iris
    radius, default each frame's own widest chord)."""
    al = align(landmarks, canon)
    if al is None:
        return None
    opening = lid_opening_mm(al.points)
    lm = np.asarray(landmarks, np.float64)
    iris = tuple(iris_offset_mm(grey, lm, al, s, None if not iris_radius_mm
                                else iris_radius_mm[i]) for i, s in enumerate(SIDES))
    ref = open_mm or opening
    photo = tuple(photo_measure(grey, lm[EYE_CORNERS[s][0], :2], lm[EYE_CORNERS[s][1], :2],
                                max(ref[i], 1.0) * al.scale)
                  for i, s in enumerate(SIDES))
    return Measures(opening, brow_heights_mm(al.points), iris, photo,  # type: ignore[arg-type]
                    al.yaw_deg, al.scale)


def closure(opening: float, open_mm: float, closed_mm: float) -> float:
    """0 (the speaker's open eye) .. 1 (closed), clipped."""
    return float(np.clip((open_mm - opening) / (open_mm - closed_mm), 0.0, 1.0))


CLOSED_FRACTION = 0.25
"""Without a blink in the enrolment clip, the closed eye's opening is taken as this fraction
of the open eye's (FaceMesh v1's lids stay apart by ~20-35 % of the open eye on closed eyes)."""


def calibrate(measures: list[Measures | None]) -> UpperReference | None:
    """The speaker's references from the enrolment clip's readings (in frame order; None
    where no face was read); None when fewer than 10 frames had measurable eyes."""
    ms = [m for m in measures if m is not None and abs(m.yaw_deg) < MAX_YAW_DEG]
    if len(ms) < 10:
        return None
    op = np.array([m.opening for m in ms])  # (F, 2)
    open_mm = np.median(op, axis=0)  # the usual open eye (blinks are < 10 % of the time)
    low = np.percentile(op, 1, axis=0)
    blinked = low < 0.6 * open_mm
    closed = np.where(blinked, np.minimum(low, 0.6 * open_mm), CLOSED_FRACTION * open_mm)
    closed = np.minimum(closed, 0.8 * open_mm)
    brows = np.median(np.array([m.brows for m in ms]), axis=0)
    # closure per frame, then a line from the photometric measure to it
    cl = np.array([[closure(m.opening[i], open_mm[i], closed[i]) for i in range(2)]
                   for m in ms])
    iris, radius = [], []
    for i in range(2):
        pts = np.array([m.iris[i] for m, c in zip(ms, cl[:, i], strict=True)
                        if m.iris[i] is not None and c < 0.3])
        iris += list(np.median(pts[:, :2], axis=0)) if len(pts) else [0.0, 0.0]
        radius.append(float(np.median(pts[:, 2])) if len(pts) >= 5 else 0.0)
    photo, photo_r = [], []
    for i in range(2):
        x = np.array([np.nan if m.photo[i] is None else m.photo[i] for m in ms])
        ok = np.isfinite(x)
        if ok.sum() >= 10 and np.std(x[ok]) > 1e-6 and np.std(cl[ok, i]) > 1e-6:
            b, a = np.polyfit(x[ok], cl[ok, i], 1)
            r = float(np.corrcoef(x[ok], cl[ok, i])[0, 1])
        else:
            a, b, r = 0.0, 0.0, 0.0
        photo += [float(a), float(b)]
        photo_r.append(r)
    runs = _runs(cl.max(axis=1) > 0.5)
    return UpperReference(tuple(open_mm), tuple(closed), tuple(brows),
                          tuple(iris), tuple(photo), tuple(photo_r),  # type: ignore[arg-type]
                          len(runs), len(ms), tuple(radius))  # type: ignore[arg-type]


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of each run of True."""
    f = np.concatenate([[False], np.asarray(flags, bool), [False]])
    d = np.flatnonzero(np.diff(f.astype(int)))
    return list(zip(d[::2].tolist(), d[1::2].tolist(), strict=True))


PHOTO_MIN_R = 0.5
"""A side whose photometric measure correlated less than this (in magnitude: the contrast
falls as the lid closes, r < 0) with the reader's closure at enrolment is not used between
readings (the last reading's closure is held)."""


@dataclass
class UpperTracker:
    """The upper face frame by frame (state: the last reading's measures and placement)."""

    reference: UpperReference | None
    rig: str = "desk"
    fuse: bool = True  # on a reading's frame, the mean of its closure and the photometric one
    clock: Callable[[], float] | None = None  # (given: ``spent_s`` adds up the steps' time)
    spent_s: float = 0.0
    canon: CanonicalFace = field(default_factory=canonical_face)
    _last: Measures | None = None
    _corners: np.ndarray | None = None  # (2 sides, 2 corners, 2) px at the last reading
    _anchor: np.ndarray | None = None  # (2,) px where the head's point was then
    _gaze: tuple[float, float] | None = None
    _closure: tuple[float, float] | None = None

    def reset(self) -> None:
        self._last = self._corners = self._anchor = None
        self._gaze = self._closure = None

    def step(self, image: np.ndarray, landmarks: np.ndarray | None, anchor: np.ndarray | None,
             ok: bool) -> UpperFace:
        """One frame (:meth:`_step`), its time added to ``spent_s`` when there is a clock."""
        if self.clock is None:
            return self._step(image, landmarks, anchor, ok)
        t0 = self.clock()
        out = self._step(image, landmarks, anchor, ok)
        self.spent_s += self.clock() - t0
        return out

    def _step(self, image: np.ndarray, landmarks: np.ndarray | None, anchor: np.ndarray | None,
              ok: bool) -> UpperFace:
        """One frame. landmarks : this frame's reading (None between readings); anchor : (2,)
        px, where a point fixed to the head (tracked) is in this frame, to move the eye
        corners between readings (None: they stay); ok : whether the face is tracked."""
        if self.rig == "head":
            return UpperFace.absent("not_seen: a head-mounted camera sees the lower face only")
        ref = self.reference
        if ref is None:
            return UpperFace.absent("not_calibrated: the speaker was enrolled without the "
                                    "upper face (enrol again with this version)")
        if not ok:
            self.reset()
            return UpperFace.absent("no_face: the face is not tracked in this frame")
        grey = image  # (grey or BGR: only the eyes' crops are converted)
        if landmarks is not None:
            m = measure(grey, landmarks, self.canon, ref.open_mm, ref.iris_radius_mm)
            if m is None:
                self.reset()
                return UpperFace.absent("no_face: the landmarks are degenerate")
            lm = np.asarray(landmarks, np.float64)
            self._last = m
            self._corners = np.array([[lm[EYE_CORNERS[s][0], :2], lm[EYE_CORNERS[s][1], :2]]
                                      for s in SIDES])
            self._anchor = None if anchor is None else np.asarray(anchor, np.float64)
            return self._from(m, "reader")
        if self._last is None or self._corners is None:
            return UpperFace.absent("no_face: no reading of the eyes yet")
        shift = (np.zeros(2) if anchor is None or self._anchor is None
                 else np.asarray(anchor, np.float64) - self._anchor)
        photo = tuple(photo_measure(grey, self._corners[i, 0] + shift,
                                    self._corners[i, 1] + shift,
                                    ref.open_mm[i] * self._last.scale) for i in range(2))
        return self._from(self._last, "photo", photo)  # type: ignore[arg-type]

    def _from(self, m: Measures, source: str,
              photo: tuple[float | None, float | None] | None = None) -> UpperFace:
        ref = self.reference
        assert ref is not None
        if abs(m.yaw_deg) > MAX_YAW_DEG:
            why = f"turned: the head is turned {abs(m.yaw_deg):.0f} deg from the camera"
            return UpperFace.absent(why)
        cl = []
        for i in range(2):
            c = closure(m.opening[i], ref.open_mm[i], ref.closed_mm[i])
            x_now = m.photo[i]
            if (photo is None and self.fuse and x_now is not None
                    and abs(ref.photo_r[i]) >= PHOTO_MIN_R):  # a reading: both measures
                c = 0.5 * (c + float(np.clip(ref.photo[2 * i] + ref.photo[2 * i + 1] * x_now,
                                             0.0, 1.0)))
            if photo is not None:
                x = photo[i]
                if x is not None and abs(ref.photo_r[i]) >= PHOTO_MIN_R:
                    c = float(np.clip(ref.photo[2 * i] + ref.photo[2 * i + 1] * x, 0.0, 1.0))
                elif self._closure is not None:
                    c = self._closure[i]
            cl.append(c)
        self._closure = (cl[0], cl[1])
        gaze = self._gaze
        if source == "reader":
            # the gaze's zero is the iris centred in the eye's opening (not the enrolment's
            # median: a speaker who looked round while enrolling would shift it)
            offs = [iris[:2] for i, iris in enumerate(m.iris) if iris is not None and cl[i] < 0.5]
            if offs:
                dx, dy = np.mean(offs, axis=0)
                gaze = (math.degrees(math.asin(float(np.clip(dx / EYE_RADIUS_MM, -1, 1)))),
                        math.degrees(math.asin(float(np.clip(dy / EYE_RADIUS_MM, -1, 1)))))
                self._gaze = gaze
        d = m.brows - np.asarray(ref.brows_mm)
        lowering = float(max(0.0, -(d[0] + d[2]) / 2.0))
        return UpperFace(True, "", cl[0], cl[1], None if gaze is None else gaze[0],
                         None if gaze is None else gaze[1], source, True, "",
                         float(d[0]), float(d[1]), float(d[2]), float(d[3]), lowering)

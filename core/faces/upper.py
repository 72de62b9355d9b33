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
- **blinks between readings**: the reader runs every few frames (``FusionPolicy``), and a
  blink lasts 3-9 frames. Between readings the closure comes from a photometric eye measure
  placed by the last reading's eye corners moved with the tracked head: the lid gap
  (:func:`lid_gap`, the eye's opening height, linear down to shut), the visible iris's
  height (:func:`iris_height`: a lid as bright as the white is not taken for the eye) or the
  contrast (:func:`photo_measure`), whichever follows the speaker's lids better at enrolment
  (:func:`calibrate`); a poorly fitting side holds the last reading's closure. On a
  reading's frame the closure is the mean of the reader's and the photometric one;
- **gaze**: an iris circle of the speaker's radius fitted to its visible edge
  (:func:`fit_iris`: the chords' widths fix its height under the lids), its offset from the
  eye opening's own centre (not the reader's corners), in mm of the aligned frame, over the
  eyeball's radius -> yaw (to the speaker's left +) and pitch (up +) in degrees;
- **brows**: the brow's dark band above the eye (:func:`brow_band_mm`, inner and outer halves),
  mm above the eye corners' line, less the speaker's neutral (the enrolment's median): raise
  > 0, lowering = how far the inner brows come down; the landmark network's brow points (which
  follow its face prior more than the pixels: docs/UPPER_FACE.md) where no band is found;
- **wide, squint, squeeze**: the eye open beyond its usual, the reader's lower lid's rise, its
  inner brows' move towards the midline.

Nothing here reads a clock or a file; :class:`UpperReference` is what ``enroll`` stores
(speaker.json ``upper``).
"""

from __future__ import annotations

import math
import weakref
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from articast.core.errors import ModelFileError
from articast.core.faces import kernels as faces_kernels
from articast.core.faces.brows import BROW_ABOVE_READER_MM as BROW_ABOVE_READER_MM
from articast.core.faces.brows import BROW_WINDOW_MM as BROW_WINDOW_MM
from articast.core.faces.brows import brow_band_mm as brow_band_mm
from articast.core.faces.canonical import CanonicalFace, canonical_face
from articast.core.faces.eye_landmarks import BROW_POINTS as BROW_POINTS
from articast.core.faces.eye_landmarks import EYE_CONTOUR as EYE_CONTOUR
from articast.core.faces.eye_landmarks import EYE_CORNERS as EYE_CORNERS
from articast.core.faces.eye_landmarks import LID_PAIRS as LID_PAIRS
from articast.core.faces.eye_landmarks import SIDES as SIDES
from articast.core.faces.iris import IRIS_MIN_ROWS as IRIS_MIN_ROWS
from articast.core.faces.iris import ROW_WHITE as ROW_WHITE
from articast.core.faces.iris import IrisFit as IrisFit
from articast.core.faces.iris import _chords as _chords
from articast.core.faces.iris import _chords_numpy as _chords_numpy
from articast.core.faces.iris import _former_rows_numpy as _former_rows_numpy
from articast.core.faces.iris import fit_iris as fit_iris
from articast.core.faces.lids import CHANGE_LAGS as CHANGE_LAGS
from articast.core.faces.lids import CHANGE_QUANTILE as CHANGE_QUANTILE
from articast.core.faces.lids import CHANGE_SEARCH as CHANGE_SEARCH
from articast.core.faces.lids import LEVELS_MIN_CONTRAST as LEVELS_MIN_CONTRAST
from articast.core.faces.lids import eye_change as eye_change
from articast.core.faces.lids import eye_template as eye_template
from articast.core.faces.lids import iris_height as iris_height
from articast.core.faces.lids import lid_gap as lid_gap
from articast.core.faces.lids import photo_measure as photo_measure

PHOTO_KINDS = ("gap", "iris", "contrast")
"""The photometric eye measures between readings (:class:`UpperReference` ``photo_kind``), in
the order of preference (:func:`calibrate`): the lid gap (linear in the lid's travel down to
shut, whatever the gaze), the iris's height (it also falls as the lid follows the gaze down),
the contrast (not linear)."""
EYE_RADIUS_MM = 11.5
"""Distance of the iris from the eyeball's centre of rotation (adult eyeball ~24 mm)."""
MAX_YAW_DEG = 40.0
"""Head turned further than this from the camera: the far eye is not seen (eyes not ok)."""

GAZE_MISSES = 2
"""Readings in a row that see an open eye but fit no iris after which the gaze is absent
(None) rather than held: one miss is the fit's noise (franck's eyes: 16 % of readings), two
are an eye whose iris the pixels do not show (carphone's ~10 px eyes: 86 %), whose gaze was
held unchanged for 43 of its 48 held-out frames before."""


@dataclass(frozen=True)
class UpperReference:
    """The speaker's own upper face at enrolment (speaker.json ``upper``).

    open_mm, closed_mm : (left, right) lid opening of the open eye (the clip's median: the
        speaker's usual open eye) and of the closed eye: with three blinks or more that the
        reader reads deep enough (:func:`blink_dips`, :data:`DIP_MAX_FRACTION`), the median
        of their deepest readings; else the clip's deepest blinks, its 1st percentile; with
        blink frames fewer than 1 % of the clip's, the mean of those whose opening lies
        :data:`BLINK_OUTLIER_SD` robust s.d. below the open eye's; when the clip has none, a
        fixed fraction of the open eye and ``blinks`` is 0. With the 90th
        percentile as the open eye, a laughing speaker's squint (the cheeks push the lower
        lids up) read 0.52-0.58 on franck, a blink; with the median 0.4
        (docs/UPPER_FACE.md).
    brows_mm : (left inner, left outer, right inner, right outer) neutral brow heights above
        the eye line (the clip's median).
    iris_mm : (left x, left y, right x, right y) the iris's median offset from the eye
        opening's centre over the clip, mm (reported: where the speaker looked while enrolling;
        not the gaze's zero, which is the iris centred in the opening: docs/UPPER_FACE.md).
    lower_mm, brow_x_mm : (left, right) the reader's neutral lower lids (:func:`lower_lids_mm`)
        and inner brows (:func:`inner_brows_x_mm`), the clip's median; None in a speaker.json
        from before them (no squint, no squeeze).
    iris_radius_mm : (left, right) the speaker's visible iris radius (the clip's median of
        each frame's widest iris chord / 2); 0: not measured (an older speaker.json), each
        frame's own widest chord is used.
    photo : (left a, left b, right a, right b): closure = a + b x the side's photometric
        measure, ``photo_kind`` (left, right): ``gap`` the lid gap (:func:`lid_gap`: 0 at the
        clip's median gap, the usual open eye, 1 at its 1st percentile, the deepest blinks;
        without blinks, where a line through it against the reader's closure reaches 1),
        ``iris`` the visible iris's height (:func:`iris_height`, calibrated as the gap) or
        ``contrast`` (:func:`photo_measure`: a line fitted to the reader's closure), whichever
        correlates better with the reader's closure on the clip over the two series' fast
        parts, the blinks (:data:`FAST_WINDOW`; by more than the correlation's standard
        error, else the earlier in :data:`PHOTO_KINDS`); photo_r : (left, right) that
        correlation (a side below 0.5 in magnitude is not used: :data:`PHOTO_MIN_R`). A
        speaker.json from before the gap has contrast lines.
    brow_band_mm : (left inner, left outer, right inner, right outer) the neutral brow's
        height above the eye line from the pixels (:func:`brow_band_mm`, the clip's
        median); brow_floor_mm : (left, right) the open eye's top (its photometric opening)
        + 1.5 mm, below which no brow is looked for; all 0: not measured (the reader's brow
        points are used, as in a speaker.json from before).
    levels : (left skin, white, iris, right skin, white, iris) grey levels of the open eyes
        (the clip's median): the lid gap's until the live tracker has fitted an iris; all 0
        in a speaker.json from before the lid gap (its ``photo`` was another measure's, and
        is not used).
    blinks : blinks the clip held (closure runs above 0.5); frames : frames measured.
    change_limit : (left, right) how far the eye's pixels changed (:func:`eye_change`)
        between open-eye frames :data:`CHANGE_LAGS` apart in the clip (its
        :data:`CHANGE_QUANTILE`): between readings, an eye without a usable photometric
        measure that changes further has the frame read (:meth:`UpperTracker.wants_reading`);
        0: not measured (a speaker.json from before it), never read for the eyes.
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
    levels: tuple[float, float, float, float, float, float] = (0.0,) * 6
    brow_band_mm: tuple[float, float, float, float] = (0.0,) * 4
    brow_floor_mm: tuple[float, float] = (0.0, 0.0)
    lower_mm: tuple[float, float] | None = None
    brow_x_mm: tuple[float, float] | None = None
    photo_kind: tuple[str, str] = ("contrast", "contrast")
    change_limit: tuple[float, float] = (0.0, 0.0)

    def brow_window(self, i: int) -> tuple[tuple[float, float] | None, ...] | None:
        """Side ``i``'s live brow search windows (inner, outer: mm above the eye line; None
        for a half whose band was not found at enrolment), None when neither was."""
        return self._brow_windows[i]

    @cached_property
    def _brow_windows(self) -> tuple[tuple[tuple[float, float] | None, ...] | None, ...]:
        """Both sides' :meth:`brow_window`, worked out once (the reference does not change;
        the live frame asks for them up to six times)."""
        return tuple(self._brow_window(i) for i in range(2))

    def _brow_window(self, i: int) -> tuple[tuple[float, float] | None, ...] | None:
        band = self.brow_band_mm[2 * i:2 * i + 2]
        if max(band) <= 0:
            return None
        floor = self.brow_floor_mm[i]
        return tuple(None if b <= 0 else (max(floor, b - BROW_WINDOW_MM), b + BROW_WINDOW_MM)
                     for b in band)

    def eye_levels(self, i: int) -> tuple[float, float, float] | None:
        """Eye ``i``'s (skin, white, iris) levels, None when not measured."""
        lv = tuple(float(v) for v in self.levels[3 * i:3 * i + 3])
        return lv if lv[1] > 0 else None  # type: ignore[return-value]

    def to_dict(self) -> dict[str, Any]:
        return {"open_mm": list(self.open_mm), "closed_mm": list(self.closed_mm),
                "brows_mm": list(self.brows_mm), "iris_mm": list(self.iris_mm),
                "photo": list(self.photo), "photo_r": list(self.photo_r),
                "blinks": int(self.blinks), "frames": int(self.frames),
                "iris_radius_mm": list(self.iris_radius_mm), "levels": list(self.levels),
                "brow_band_mm": list(self.brow_band_mm),
                "brow_floor_mm": list(self.brow_floor_mm),
                **({} if self.lower_mm is None else {"lower_mm": list(self.lower_mm)}),
                **({} if self.brow_x_mm is None else {"brow_x_mm": list(self.brow_x_mm)}),
                "photo_kind": list(self.photo_kind), "change_limit": list(self.change_limit)}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> UpperReference:
        sizes = {"open_mm": 2, "closed_mm": 2, "brows_mm": 4, "iris_mm": 4, "photo": 4,
                 "photo_r": 2}
        if isinstance(d, dict) and "iris_radius_mm" in d:  # (absent before it was measured)
            sizes["iris_radius_mm"] = 2
        if isinstance(d, dict) and "levels" in d:  # (absent before the lid gap)
            sizes["levels"] = 6
        if isinstance(d, dict) and "brow_band_mm" in d:  # (absent before the brow band)
            sizes["brow_band_mm"], sizes["brow_floor_mm"] = 4, 2
        for k in ("lower_mm", "brow_x_mm", "change_limit"):  # (absent before them)
            if isinstance(d, dict) and k in d:
                sizes[k] = 2
        try:
            vals = {k: tuple(float(x) for x in d[k]) for k in sizes}
            blinks, frames = int(d["blinks"]), int(d["frames"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{where}: the upper-face block is malformed ({exc})") from None
        bad = [k for k, n in sizes.items()
               if len(vals[k]) != n or not all(math.isfinite(v) and abs(v) < 1e3
                                               for v in vals[k])]
        if min(vals.get("change_limit", (0.0,))) < 0:
            bad.append("change_limit")
        if bad or not all(o > c > 0 for o, c in zip(vals["open_mm"], vals["closed_mm"],
                                                    strict=True)):
            raise ModelFileError(f"{where}: the upper-face block needs finite numbers and an "
                                 f"open eye wider than the closed one ({', '.join(bad)})")
        kind = d.get("photo_kind", ["contrast", "contrast"])  # (before the gap: contrast)
        if (not isinstance(kind, list | tuple) or len(kind) != 2
                or not all(k in PHOTO_KINDS for k in kind)):
            raise ModelFileError(f"{where}: the upper-face block's photo_kind must be two of "
                                 f"{', '.join(PHOTO_KINDS)}")
        return cls(**vals, blinks=blinks, frames=frames,  # type: ignore[arg-type]
                   photo_kind=(str(kind[0]), str(kind[1])))


@dataclass(frozen=True)
class UpperFace:
    """One frame's upper face. ``eyes_ok`` / ``brows_ok`` False: the values are None and
    the reason (a code word, ``:``, a sentence) says why: ``not_seen`` (a head-mounted camera
    sees the lower face only), ``no_face``, ``turned`` (the head turned too far for both
    eyes), ``left_image``, ``not_calibrated`` (a speaker enrolled before this version).

    closure_* : 0 open .. 1 closed; source ``reader`` (the landmarks this frame, measured in
    full), ``lids`` (this frame's landmarks' lids and the photometric measure; the rest held)
    or ``photo`` (the photometric measure between readings). gaze_* : degrees, yaw to the
    speaker's left +, pitch up +. raise_* : mm above the neutral brow; lowering_mm : inner
    brows below it.
    wide_* : how far the eye is open beyond the speaker's usual open eye (the unclipped
    closure's negative part, in units of the open-to-closed travel; 0 .. 1). lower_lid_* :
    the lower lid's rise above its neutral (the reader's lower lid, a fraction of the open
    eye; + up: a squint, the cheeks pushing it). squeeze_*_mm : the inner brow's move towards
    the face's midline from its neutral (the reader's inner brow points; a frown's corrugator)."""

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
    wide_left: float | None = None
    wide_right: float | None = None
    lower_lid_left: float | None = None
    lower_lid_right: float | None = None
    squeeze_left_mm: float | None = None
    squeeze_right_mm: float | None = None

    @classmethod
    def absent(cls, reason: str) -> UpperFace:
        return cls(False, reason, brows_ok=False, brows_reason=reason)

    def eyes_dict(self) -> dict[str, Any]:
        """The ``eyes`` block of a track line / wire frame."""
        return {"ok": self.eyes_ok, "reason": self.eyes_reason,
                "closure_left": _r(self.closure_left), "closure_right": _r(self.closure_right),
                "gaze_yaw_deg": _r(self.gaze_yaw_deg), "gaze_pitch_deg": _r(self.gaze_pitch_deg),
                "wide_left": _r(self.wide_left), "wide_right": _r(self.wide_right),
                "lower_lid_left": _r(self.lower_lid_left),
                "lower_lid_right": _r(self.lower_lid_right)}

    def brows_dict(self) -> dict[str, Any]:
        """The ``brows`` block of a track line / wire frame."""
        return {"ok": self.brows_ok, "reason": self.brows_reason,
                "raise_left_mm": _mean(self.raise_inner_left_mm, self.raise_outer_left_mm),
                "raise_right_mm": _mean(self.raise_inner_right_mm, self.raise_outer_right_mm),
                "raise_inner_left_mm": _r(self.raise_inner_left_mm),
                "raise_outer_left_mm": _r(self.raise_outer_left_mm),
                "raise_inner_right_mm": _r(self.raise_inner_right_mm),
                "raise_outer_right_mm": _r(self.raise_outer_right_mm),
                "lowering_mm": _r(self.lowering_mm),
                "squeeze_left_mm": _r(self.squeeze_left_mm),
                "squeeze_right_mm": _r(self.squeeze_right_mm)}

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
                   num(brows, "lowering_mm", *mm),
                   num(eyes, "wide_left", 0.0, 1.0), num(eyes, "wide_right", 0.0, 1.0),
                   num(eyes, "lower_lid_left", -1.0, 1.0),
                   num(eyes, "lower_lid_right", -1.0, 1.0),
                   num(brows, "squeeze_left_mm", *mm), num(brows, "squeeze_right_mm", *mm))


def _clip(v: float, lo: float, hi: float) -> float:
    """A scalar clipped (np.clip costs microseconds on a scalar; this step runs per frame)."""
    return lo if v < lo else hi if v > hi else v


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


_FLIP = np.array([1.0, -1.0, -1.0])  # image (x right, y down, z away) -> head frame axes
_RIGID: weakref.WeakKeyDictionary[CanonicalFace, tuple[np.ndarray, ...]] = (
    weakref.WeakKeyDictionary())


def _rigid(canon: CanonicalFace) -> tuple[np.ndarray, ...]:
    """The canonical face's side of :func:`align`'s Procrustes, worked out once per face (the
    same arrays each reading computed before): the rigid points' ids (33,), their weights
    normalised (33,), the points (33, 3) mm, their weighted mean (3,) mm and the weighted,
    centred points transposed (3, 33) mm."""
    got = _RIGID.get(canon)
    if got is None:
        ids, w = canon.procrustes_ids, canon.procrustes_weights
        b = canon.vertices_mm[ids]
        wn = w / w.sum()
        mb = wn @ b
        got = _RIGID[canon] = (ids, wn, b, mb, ((b - mb) * wn[:, None]).T)
    return got


def _det3(m: list[list[float]]) -> float:
    """The determinant of a 3 x 3 matrix (rows of Python floats), by its first row's
    cofactors."""
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def align(landmarks: np.ndarray, canon: CanonicalFace) -> Aligned | None:
    """Similarity Procrustes of a reading (>=468, 3: x, y px, z depth px, image frame) onto
    the canonical face on MediaPipe's rigid points; None for a degenerate reading. In one
    compiled call where numba is (:func:`~articast.core.faces.kernels.aligned`: the numpy
    code's numbers to rounding, ~0.06 ms a frame less in the live loop), else
    :func:`align_numpy`."""
    if not faces_kernels.AVAILABLE:
        return align_numpy(landmarks, canon)
    ids, wn, b, mb, _ = _rigid(canon)
    ok, pts, scale, yaw = faces_kernels.aligned(  # (a copy: a read-only array, as a
        # reading's landmarks are, is another type to numba, compiled again)
        np.array(np.asarray(landmarks)[:468], np.float64), ids, wn, b, mb)
    return Aligned(pts, float(scale), float(yaw)) if ok else None


def align_numpy(landmarks: np.ndarray, canon: CanonicalFace) -> Aligned | None:
    """:func:`align` in numpy (the reference of the compiled call)."""
    lm = np.asarray(landmarks, np.float64)[:468]
    src = lm * _FLIP  # -> x right, y up, z forward
    ids, wn, _, mb, bcw = _rigid(canon)
    a = src[ids]
    ma = wn @ a
    ac = a - ma
    cov = bcw @ ac
    if not all(map(math.isfinite, cov.ravel().tolist())):
        return None
    u, s, vt = np.linalg.svd(cov)
    # (the sign of det(u @ vt), +-1: the product of u's and vt's, both orthogonal, by their
    # cofactors in Python floats; and the scale's sum of three in floats, from 0.0 as numpy's)
    d = 1.0 if _det3(u.tolist()) * _det3(vt.tolist()) > 0 else -1.0
    rot = u @ np.diag([1.0, 1.0, d]) @ vt  # src -> canonical
    var = float((wn * np.sum(ac ** 2, axis=1)).sum())
    if var <= 1e-9:
        return None
    s0, s1, s2 = s.tolist()
    scale = (0.0 + s0 + s1 + s2 * d) / var  # mm per px
    if not math.isfinite(scale) or scale <= 0:
        return None
    pts = (src - ma) @ rot.T * scale + mb
    # rot maps the face's frame as seen to the canonical: its inverse is the head's rotation
    head = rot.T
    yaw = math.degrees(math.atan2(head[0, 2], head[2, 2]))
    return Aligned(pts, 1.0 / scale, yaw)


_LID_UPPER = np.array([[u for u, _ in LID_PAIRS[s]] for s in SIDES])
_LID_LOWER = np.array([[lo for _, lo in LID_PAIRS[s]] for s in SIDES])


def lids_only(landmarks: np.ndarray, canon: CanonicalFace
              ) -> tuple[tuple[float, float], float] | None:
    """A reading's lid opening (:func:`lid_opening_mm` of :func:`align`'s points) and yaw,
    without aligning the other 460 points: (opening (left, right) mm, yaw deg), or None for
    a degenerate reading. For the frames whose reading is read for the lids alone
    (:meth:`UpperTracker.step`'s ``lids``): compiled, :func:`align`'s own call (aligning the
    other points costs it ~1 us); in numpy, ~0.1 of ``align``'s cost."""
    if faces_kernels.AVAILABLE:
        al = align(landmarks, canon)
        return None if al is None else (lid_opening_mm(al.points), al.yaw_deg)
    return lids_only_numpy(np.asarray(landmarks, np.float64), canon)


def lids_only_numpy(lm: np.ndarray, canon: CanonicalFace
                    ) -> tuple[tuple[float, float], float] | None:
    """:func:`lids_only` in numpy, where numba is not (the reference its test compares the
    compiled :func:`align` path with)."""
    ids, w = canon.procrustes_ids, canon.procrustes_weights
    a = lm[ids] * (1.0, -1.0, -1.0)  # -> x right, y up, z forward
    b = canon.vertices_mm[ids]
    wn = w / w.sum()
    ac, bc = a - wn @ a, b - wn @ b
    cov = (bc * wn[:, None]).T @ ac
    if not np.all(np.isfinite(cov)):
        return None
    u, sv, vt = np.linalg.svd(cov)
    d = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    var = float((wn * np.sum(ac ** 2, axis=1)).sum())
    if var <= 1e-9:
        return None
    scale = float((sv[0] + sv[1] + d * sv[2]) / var)
    if not np.isfinite(scale) or scale <= 0:
        return None
    # a pair's height difference is the canonical y of the difference of its two points
    diff = (lm[_LID_UPPER] - lm[_LID_LOWER]) * (1.0, -1.0, -1.0)  # (2 sides, 3 pairs, 3)
    up = (diff @ rot[1]).mean(axis=1) * scale
    yaw = math.degrees(math.atan2(rot[2, 0], rot[2, 2]))
    return (float(up[0]), float(up[1])), yaw


# (the points these read, both sides', in one take each: a few Python float operations on
# the values instead of ~10 small numpy calls per measure; the same sums in the same order
# as numpy's mean of 2 or 3 values, from 0.0 as numpy's, so the same numbers. A column's
# take of an index array: ~1.4 us, against ~5 us for a list's fancy index per side, ~15 us
# a call cold in the live loop, where the lids are read on every frame)
_LIDS_Y = np.array([i for s in SIDES for pair in LID_PAIRS[s] for i in pair])
# (per side: u0 l0 u1 l1 u2 l2)
_LOWER_Y = np.array([i for s in SIDES for i in (*(lo for _, lo in LID_PAIRS[s]),
                                                  *EYE_CORNERS[s])])  # (l0 l1 l2 c0 c1)
_BROWS_Y = np.array([i for s in SIDES for i in (*EYE_CORNERS[s], *BROW_POINTS[s]["inner"],
                                                 *BROW_POINTS[s]["outer"])])
_INNER_X = np.array([*BROW_POINTS["left"]["inner"], *BROW_POINTS["right"]["inner"]])


def lid_opening_mm(points: np.ndarray) -> tuple[float, float]:
    """(left, right) lid opening, mm: mean upper-minus-lower height of the three lid pairs."""
    v = points[:, 1].take(_LIDS_Y).tolist()
    out = []
    for k in (0, 6):
        u0, l0, u1, l1, u2, l2 = v[k:k + 6]
        out.append((0.0 + (u0 - l0) + (u1 - l1) + (u2 - l2)) / 3)
    return out[0], out[1]


def lower_lids_mm(points: np.ndarray) -> tuple[float, float]:
    """(left, right) the lower lid's height above its eye's corners' line, mm (the mean of
    the three lid pairs' lower points)."""
    v = points[:, 1].take(_LOWER_Y).tolist()
    out = []
    for k in (0, 5):
        l0, l1, l2, c0, c1 = v[k:k + 5]
        out.append((0.0 + l0 + l1 + l2) / 3 - (0.0 + c0 + c1) / 2)
    return out[0], out[1]


def inner_brows_x_mm(points: np.ndarray) -> tuple[float, float]:
    """(left, right) the inner brow's distance from the face's midline, mm (x of the
    inner brow points' mean: + to the speaker's left for the left brow, mirrored for the
    right)."""
    l0, l1, r0, r1 = points[:, 0].take(_INNER_X).tolist()
    return (0.0 + l0 + l1) / 2, -((0.0 + r0 + r1) / 2)


def brow_heights_mm(points: np.ndarray) -> np.ndarray:
    """(left inner, left outer, right inner, right outer) brow heights above the eye line,
    mm (each brow point pair's mean height minus its eye corners' mean height)."""
    v = points[:, 1].take(_BROWS_Y).tolist()
    out = []
    for k in (0, 6):
        c0, c1, i0, i1, o0, o1 = v[k:k + 6]
        eye_y = (0.0 + c0 + c1) / 2
        out += [(0.0 + i0 + i1) / 2 - eye_y, (0.0 + o0 + o1) / 2 - eye_y]
    return np.array(out)




def iris_offset_mm(grey: np.ndarray, landmarks: np.ndarray, aligned: Aligned,
                   side: str, radius_mm: float | None = None, fit: IrisFit | None = None
                   ) -> tuple[float, float, float] | None:
    """The iris's offset (x to the speaker's left, y up; mm of the aligned frame) from the eye
    opening's own centre (:func:`fit_iris`, or ``fit`` when given), and the visible iris's
    widest half-chord (mm); None when the iris is not fitted. ``radius_mm``: the speaker's
    iris radius (enrolment)."""
    if fit is None:
        fit = fit_iris(grey, landmarks, side,
                       None if not radius_mm else radius_mm * aligned.scale)
    if fit is None:
        return None
    inner, outer = EYE_CORNERS[side]
    lm = np.asarray(landmarks, np.float64)
    # image px -> the aligned frame's x, y: the in-plane rotation of the corners' axis (its
    # angle: ~1 px of jitter over the eye's width moves a 2 mm offset by < 0.1 mm) and the
    # alignment's scale (all the rigid points: steadier than the corners' distance). (In
    # Python floats: numpy's float64 operations on these 2-vectors one at a time, the same
    # numbers without ~8 small array calls.)
    (ix, iy), (ox, oy) = lm[inner, :2].tolist(), lm[outer, :2].tolist()
    (ai, bi), (ao, bo) = aligned.points[inner, :2].tolist(), aligned.points[outer, :2].tolist()
    ang = math.atan2(bo - bi, ao - ai) - math.atan2(-(oy - iy), ox - ix)
    (cx, cy), (ex, ey) = fit.centre.tolist(), fit.eye.tolist()
    scale = float(aligned.scale)
    d0, d1 = (cx - ex) / scale, -(cy - ey) / scale
    ca, sa = math.cos(ang), math.sin(ang)
    return (ca * d0 - sa * d1, sa * d0 + ca * d1, fit.half_width / aligned.scale)



def change_limits(greys: Sequence[np.ndarray], readings: Sequence[np.ndarray | None],
                  measures: Sequence[Measures | None], ref: UpperReference
                  ) -> tuple[float, float]:
    """Each eye's :data:`CHANGE_QUANTILE` of :func:`eye_change` between enrolment frames
    :data:`CHANGE_LAGS` apart, both open (closure < 0.3 in both), the template from the
    earlier frame and looked for where the face's points moved it (as live, where the head's
    motion moves it); 0 with fewer than 20 such pairs. ``greys``, ``readings`` (468+, 2+)
    px and ``measures`` per frame in clip order (None where no face was read)."""
    n = len(measures)
    ok = np.zeros(n, bool)
    for t, m in enumerate(measures):
        ok[t] = m is not None and abs(m.yaw_deg) < MAX_YAW_DEG and readings[t] is not None \
            and max(closure(m.opening[i], ref.open_mm[i], ref.closed_mm[i])
                    for i in range(2)) < 0.3
    marks = [None if not ok[t] else np.asarray(readings[t], np.float64)[:, :2]
             for t in range(n)]
    centres = [None if lm is None else lm[:468].mean(axis=0) for lm in marks]
    out = []
    for i, side in enumerate(SIDES):
        a, b = EYE_CORNERS[side]
        opens = [0.0 if m is None else ref.open_mm[i] * m.scale for m in measures]
        tpls = [None if lm is None else eye_template(greys[t], lm[a], lm[b], opens[t])
                for t, lm in enumerate(marks)]  # (each frame's once, for every lag)
        ch = []
        for k in CHANGE_LAGS:
            for t in range(k, n):
                lm0, tpl, c0, c1 = marks[t - k], tpls[t - k], centres[t - k], centres[t]
                if lm0 is None or tpl is None or c0 is None or c1 is None:
                    continue
                shift = c1 - c0
                x = eye_change(tpl, greys[t], lm0[a] + shift, lm0[b] + shift, opens[t - k])
                if x is not None:
                    ch.append(x)
        out.append(float(np.quantile(ch, CHANGE_QUANTILE)) if len(ch) >= 20 else 0.0)
    return out[0], out[1]



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
    levels: tuple[tuple[float, float, float] | None, tuple[float, float, float] | None] = (
        None, None)  # each eye's (skin, white, iris) when its iris was fitted
    band: tuple[tuple[float | None, float | None] | None, ...] = (None, None)
    # each side's brow band (inner, outer mm above the eye line), None where not found
    floor: tuple[float | None, float | None] = (None, None)  # each open eye's top + 1.5 mm
    contrast: tuple[float | None, float | None] = (None, None)  # photo_measure, per eye
    lower: tuple[float, float] = (0.0, 0.0)  # the reader's lower lids (lower_lids_mm)
    brow_x: tuple[float, float] = (0.0, 0.0)  # the reader's inner brows (inner_brows_x_mm)
    iris_h: tuple[float | None, float | None] = (None, None)  # iris_height, per eye

    def photometric(self, kind: str, i: int) -> float | None:
        """Eye i's photometric measure of ``kind`` (:data:`PHOTO_KINDS`) on this reading."""
        return (self.photo if kind == "gap" else self.contrast if kind == "contrast"
                else self.iris_h)[i]


def measure(grey: np.ndarray, landmarks: np.ndarray, canon: CanonicalFace,
            open_mm: tuple[float, float] | None = None,
            iris_radius_mm: tuple[float, float] | None = None,
            levels: tuple[tuple[float, float, float] | None, ...] | None = None,
            brow_windows: tuple[Any, ...] | None = None,
            kinds: tuple[str, ...] = PHOTO_KINDS,
            photo_eyes: tuple[bool, bool] = (True, True)) -> Measures | None:
    """The raw measures of one reading (``open_mm``: the strip height of the photometric lid
    gap; default: this reading's own opening; ``iris_radius_mm``: the speaker's iris
    radius, default each frame's own widest chord; ``levels``: each eye's grey levels for
    the lid gap, e.g. the last open eye's (a half-closed eye's own put its lid among the
    iris); where None, this frame's own when its iris is fitted, else no gap);
    ``brow_windows``: each side's brow search window (:meth:`UpperReference.brow_window`),
    default from just above this frame's open eye to ``BROW_ABOVE_READER_MM`` above the
    reader's brow points; given with a side's None, that side's band is not looked for);
    ``kinds``: the photometric measures wanted, default all; ``photo_eyes``: the eyes they
    are wanted for, default both (the others' are None))."""
    al = align(landmarks, canon)
    if al is None:
        return None
    opening = lid_opening_mm(al.points)
    lm = np.asarray(landmarks, np.float64)
    fits = [fit_iris(grey, lm, s, None if not iris_radius_mm or not iris_radius_mm[i]
                     else iris_radius_mm[i] * al.scale) for i, s in enumerate(SIDES)]
    iris = tuple(iris_offset_mm(grey, lm, al, s, fit=f) if f is not None else None
                 for s, f in zip(SIDES, fits, strict=True))
    lv = [levels[i] if levels is not None and levels[i] is not None
          else (None if f is None else f.levels) for i, f in enumerate(fits)]
    ref = open_mm or opening
    gap = "gap" in kinds or brow_windows is None  # (the enrolment's brow floor needs it)
    photo = tuple(None if lv[i] is None or not gap or not photo_eyes[i] else lid_gap(
        grey, lm[EYE_CORNERS[s][0], :2], lm[EYE_CORNERS[s][1], :2],
        max(ref[i], 1.0) * al.scale, lv[i]) for i, s in enumerate(SIDES))  # type: ignore[arg-type]
    floor: list[float | None] = []
    for i, s in enumerate(SIDES):  # the open eye's top: its centre + half its lid gap, mm
        f, x = fits[i], photo[i]
        if f is None or x is None:
            floor.append(None)
            continue
        mid = (lm[EYE_CORNERS[s][0], :2] + lm[EYE_CORNERS[s][1], :2]) / 2.0
        above = float(mid[1] - f.eye[1]) / al.scale  # (image y down; roll ignored)
        floor.append(above + 0.5 * x * max(ref[i], 1.0) + 1.5)
    band: list[tuple[float | None, float | None] | None] = []
    brows = brow_heights_mm(al.points)
    for i, s in enumerate(SIDES):
        if brow_windows is not None and brow_windows[i] is None:
            band.append(None)  # (a side whose band the enrolment did not find)
            continue
        win = None if brow_windows is None else brow_windows[i]
        if win is None and (fl := floor[i]) is not None:  # (enrolment: see BROW_ABOVE_READER_MM)
            win = tuple((fl, max(fl + 3.0, float(brows[2 * i + j]) + BROW_ABOVE_READER_MM))
                        for j in range(2))
        band.append(None if win is None else brow_band_mm(grey, lm, al, s, win))
    return Measures(opening, brows, iris, photo,  # type: ignore[arg-type]
                    al.yaw_deg, al.scale,
                    tuple(None if f is None else f.levels for f in fits),  # type: ignore[arg-type]
                    tuple(band), tuple(floor),  # type: ignore[arg-type]
                    tuple(photo_measure(grey, lm[EYE_CORNERS[s][0], :2],  # type: ignore[arg-type]
                                        lm[EYE_CORNERS[s][1], :2], max(ref[i], 1.0) * al.scale)
                          if "contrast" in kinds and photo_eyes[i] else None
                          for i, s in enumerate(SIDES)),
                    lower_lids_mm(al.points), inner_brows_x_mm(al.points),
                    tuple(None if (v := lv[i]) is None or "iris" not in kinds
                          or not photo_eyes[i] else iris_height(grey, lm[EYE_CORNERS[s][0], :2],
                                           lm[EYE_CORNERS[s][1], :2],
                                           max(ref[i], 1.0) * al.scale, v)
                          for i, s in enumerate(SIDES)))  # type: ignore[arg-type]


def closure(opening: float, open_mm: float, closed_mm: float) -> float:
    """0 (the speaker's open eye) .. 1 (closed), clipped."""
    return _clip(float((open_mm - opening) / (open_mm - closed_mm)), 0.0, 1.0)


CLOSED_FRACTION = 0.5
"""Without a blink in the enrolment clip, the closed eye's opening is taken as this fraction
of the open eye's. FaceMesh v1 never reads a shut eye's lids together: on the real clips of
issue 38 whose enrolment had blinks, the shut reference it gave was 0.38-0.65 of the open eye
(median 0.55 on either half of the people); the former 0.25 (the synthetic speaker's
20-35 %) left every blink of a speaker enrolled without one under a closure of 0.4 (lia_obama:
0 of 10 found, peaks 0.24-0.39). Chosen on one half of the people (edtalk_mouth_source,
lia_vox_driving3, liveportrait_d10: 0.5 found 3 of 6 blinks with no false one, 0.55 one false
more), checked on the other (lia_obama 7 of 10 found, 0 before; facerealtime_driving's one
blink, at ~100 px, still missed): docs/UPPER_FACE.md."""

BLINK_OUTLIER_SD = 5.0
"""An enrolment frame whose lid opening (both eyes' mean) lies this many robust standard
deviations (1.4826 x the median absolute deviation) below the clip's median is a blink, however
shallow the reader reads it (on a 176 x 144 face its lids stop at 0.62 of the open eye): no
open eye's spread reaches that far (4 s.d. did, twice: cap12 and cap13's gaze dips to 0.78-0.8
of the open eye, dlib's eyes open)."""


DIP_MIN_FRACTION = 0.15
"""A blink dip (:func:`blink_dips`) goes at least this fraction of the open eye below the
opening round it."""

DIP_MAX_FRACTION = 0.75
"""The enrolment's blink dips give the shut eye (:func:`calibrate`) when the median of their
deepest readings is at most this fraction of the open eye (a blink the reader reads at
least a quarter shut). FaceMesh v1 reads a blink on a small face shallow: lia_obama's shut
eyes (256 px broadcast crop, 14 blinks in its enrolment) read 0.51-0.83 of the open eye,
median 0.72, and against the former references (the 1st percentile, or half the open eye)
its held-out blinks peaked at a closure of 0.45-0.61, 6 of 10 found; with the dips' median,
0.80-0.98, 10 of 10. Dips shallower than that (0.77-0.8: facerealtime_driving's ~100 px
face, lia_vox_driving3, liveportrait_d10) are not told from the open eye's own flutter
(taken for the shut eye, they read 1-5 false blinks each). Chosen on half B of the people
(lia_obama, facerealtime_driving), checked on half A (lia_vox_driving3 and
liveportrait_d10 keep their references): docs/UPPER_FACE.md. (Enrolled afresh in session 10,
lia_vox_driving3's two dips read 0.66 and 0.8, median 0.73: :data:`DIP_MIN_COUNT`.)"""

DIP_MIN_COUNT = 3
"""Blink dips (:func:`blink_dips`) the enrolment needs before the median of their deepest
readings is its shut eye: the fewest of which a median rejects one odd dip (a half blink, a
narrowing that passed for one). With two, the median is their mean: lia_vox_driving3's
enrolment holds one blink (read at 0.66 of the open eye) and a half-closed eye with the iris
seen (0.80), and their mean, 0.73, taken for the shut eye read its narrowed eyes (0.75-0.79,
the iris seen) as 4 false blinks. Fewer dips leave the former reference (:func:`calibrate`).
Not chosen on the clips: the median's own breakdown; docs/UPPER_FACE.md (session 10)."""

DIP_MAX_SAMPLES = 8
"""A blink dip lasts at most this many readings (~0.3 s at 25 fps): a longer one is a look
down or a squint, not a blink."""


def blink_dips(op: np.ndarray, window: int = 15, noise_sd: float = 3.0
               ) -> list[tuple[int, int]]:
    """(start, end) of each blink dip in the enrolment's lid openings ``op`` (F, 2) mm, in
    frame order: a run of at most :data:`DIP_MAX_SAMPLES` readings whose mean opening lies
    below the median of the ``window`` readings either side by more than ``noise_sd`` x
    the robust s.d. of the openings about that median and more than
    :data:`DIP_MIN_FRACTION` of the clip's median opening. A dip is judged against the
    opening round it, not against the clip's: a speaker whose eyes roam (looks down,
    squints while laughing) has a wide spread but short, sharp blinks."""
    o = np.asarray(op, np.float64).mean(axis=1)
    n = len(o)
    if n < 10:
        return []
    d = fast_part(o, window)  # (the opening less the median round it)
    noise = 1.4826 * float(np.median(np.abs(d)))
    below = d < -max(noise_sd * noise, DIP_MIN_FRACTION * float(np.median(o)))
    return [(a, b) for a, b in _runs(below) if b - a <= DIP_MAX_SAMPLES]


FAST_WINDOW = 15
"""The photometric measure is chosen (and trusted) by its correlation with the reader's
closure over their fast parts: each series less its running median over this many readings
either side (:func:`fast_part`; :func:`blink_dips`' own window, ~0.6 s at 25 fps), so that
the blinks, short, weigh and the slow changes do not. The reader reads a narrowed eye (a look
down, a frown, a laugh's squint) as deep as a shut one: on the whole series a measure that
follows those lowerings but not the lid over the eye was chosen (pexels_woman's left lid gap:
r -0.86 over the whole enrolment, -0.25 over its fast part; it reads her shut eyes open)."""


def fast_part(v: np.ndarray, window: int = FAST_WINDOW) -> np.ndarray:
    """A series (in frame order; NaN where none) less its running median over ``window``
    samples either side (NaN where the window holds none)."""
    v = np.asarray(v, np.float64)
    n = len(v)
    out = np.full(n, np.nan)
    for k in range(n):
        w = v[max(0, k - window):k + window + 1]
        w = w[np.isfinite(w)]
        if len(w) and np.isfinite(v[k]):
            out[k] = v[k] - float(np.median(w))
    return out


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
    # fewer blink frames than 1 % of the clip leave the 1st percentile among the open eyes:
    # then the blinks found as outliers of the open eye's spread give the shut reference
    sd = 1.4826 * np.median(np.abs(op - open_mm), axis=0)
    dips = ((op - open_mm) / np.maximum(sd, 1e-6)).mean(axis=1) < -BLINK_OUTLIER_SD
    shut = op[dips].mean(axis=0) if dips.any() else CLOSED_FRACTION * open_mm
    closed = np.where(blinked, np.minimum(low, 0.6 * open_mm), shut)
    # the blinks as the reader reads them, where it reads them deep enough to be told
    # (:func:`blink_dips`): the shut eye is the median of their deepest readings
    runs = blink_dips(op)
    if len(runs) >= DIP_MIN_COUNT:
        deepest = np.median([op[a:b].min(axis=0) for a, b in runs], axis=0)
        closed = np.where(deepest <= DIP_MAX_FRACTION * open_mm, deepest, closed)
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
    photo, photo_r, levels, kinds = [], [], [], []
    for i in range(2):
        lv = np.array([m.levels[i] for m, c in zip(ms, cl[:, i], strict=True)
                       if m.levels[i] is not None and c < 0.3]).reshape(-1, 3)
        levels += list(np.median(lv, axis=0)) if len(lv) >= 5 else [0.0, 0.0, 0.0]
        best, n_best = (0.0, 0.0, 0.0, "gap"), 0
        fast_cl = fast_part(cl[:, i])
        for kind in PHOTO_KINDS:  # (in the order of preference)
            x = np.array([np.nan if v is None else v for v in
                          (m.photometric(kind, i) for m in ms)])
            ok = np.isfinite(x)
            if ok.sum() < 10 or np.std(x[ok]) <= 1e-6 or np.std(cl[ok, i]) <= 1e-6:
                continue
            # how well it follows the reader's fast lid movements, the blinks (FAST_WINDOW):
            # not its slow ones, a look down or a laugh's squint, which the reader itself
            # reads as deep as a shut eye and so teaches wrong (docs/UPPER_FACE.md)
            fx = fast_part(x)
            both = np.isfinite(fx)
            if both.sum() < 10 or np.std(fx[both]) <= 1e-9 or np.std(fast_cl[both]) <= 1e-9:
                continue
            r = float(np.corrcoef(fx[both], fast_cl[both])[0, 1])
            k, c0 = np.polyfit(x[ok], cl[ok, i], 1)
            a, b = float(c0), float(k)
            if kind != "contrast":  # its own open (median) and shut (deepest blinks) refs
                x_open = float(np.median(x[ok]))
                x_shut = (float(np.percentile(x[ok], 1)) if blinked[i]
                          else (1.0 - c0) / k if abs(k) > 1e-9 else x_open)
                if x_open - x_shut <= 1e-6:
                    continue
                a, b = x_open / (x_open - x_shut), -1.0 / (x_open - x_shut)
            # a measure later in the order replaces the one kept only when it follows the
            # reader better by more than the kept one's correlation's standard error,
            # (1 - r^2) / sqrt(n - 1): a tie on the synthetic eye (0.766 / 0.764) keeps the gap
            if not n_best or abs(r) > abs(best[2]) + (1.0 - best[2] ** 2) / math.sqrt(
                    n_best - 1):
                best, n_best = (a, b, r, kind), int(both.sum())
        photo += [best[0], best[1]]
        photo_r.append(best[2])
        kinds.append(best[3])
    bands, floors = [], []
    for i in range(2):
        for j in range(2):  # each half on its own: the other may be hidden (docstring)
            hb = [float(v) for m, c in zip(ms, cl[:, i], strict=True)
                  if (bd := m.band[i]) is not None and (v := bd[j]) is not None and c < 0.3]
            ok = len(hb) >= 10 and len(hb) >= 0.3 * len(ms)
            bands.append(float(np.median(hb)) if ok else 0.0)
        fl = [float(f) for m, c in zip(ms, cl[:, i], strict=True)
              if (f := m.floor[i]) is not None and c < 0.3]
        floors.append(float(np.median(fl)) if fl and max(bands[-2:]) > 0 else 0.0)
    runs = _runs(cl.max(axis=1) > 0.5)
    return UpperReference(tuple(open_mm), tuple(closed), tuple(brows),
                          tuple(iris), tuple(photo), tuple(photo_r),  # type: ignore[arg-type]
                          len(runs), len(ms), tuple(radius),  # type: ignore[arg-type]
                          tuple(levels), tuple(bands), tuple(floors),  # type: ignore[arg-type]
                          _pair(np.median([m.lower for m in ms], axis=0)),
                          _pair(np.median([m.brow_x for m in ms], axis=0)), (kinds[0], kinds[1]))


def _pair(v: np.ndarray) -> tuple[float, float]:
    return float(v[0]), float(v[1])


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of each run of True."""
    f = np.concatenate([[False], np.asarray(flags, bool), [False]])
    d = np.flatnonzero(np.diff(f.astype(int)))
    return list(zip(d[::2].tolist(), d[1::2].tolist(), strict=True))


OFFSET_WEIGHT = 0.5
"""Between readings each eye's closure is its photometric closure moved by the readings'
disagreement with it (:meth:`UpperTracker._from`): a running mean over the readings in which
the last one weighs this much. A disagreement that lasts (a measure blind to a lid, an
expression held) is carried whole, one reading's alone (the reader's lids saturating at a
blink's deepest) by half. The ablation (1: the last reading's alone; 0.5; 0.3) over every
clip with blinks and the synthetic speaker is in docs/UPPER_FACE.md."""

PHOTO_MIN_R = 0.5
"""A side whose photometric measure correlated less than this (in magnitude: the contrast
falls as the lid closes, r < 0) with the reader's closure at enrolment (over their fast
parts, :data:`FAST_WINDOW`) is not used: its closure is the reader's lids alone where the
frame is read, the last reading's held between readings."""


LEVEL_KNOT = 0.5
"""The closure at which an eye is half shut, a blink frame (``BLINK_CLOSURE`` of
core/evaluation/upper.py): the speaker's levels (:func:`levelled`) move every closure but
this one, so no blink is found or lost by them."""

OPEN_LEVEL_FRAMES = 25
"""The open eye's level (:class:`ClosureLevels`) is the median closure of the last this many
frames that were not a blink's (~1 s): a pose or a light that leaves the open eye reading
0.2-0.3 for a second reads open after it."""

OPEN_LEVEL_MAX = 0.3
"""The open eye's level is at most this closure: a long look down or squint is not taken for
the open eye beyond it (a blink from it still reads > 0.5: :data:`LEVEL_KNOT` is fixed)."""

OPEN_CURVE = 2.0
"""Below :data:`LEVEL_KNOT` the closure over its open level is raised to this power (a
half-lowered lid reads less than half of it; 0 and the knot stay): FaceMesh v1 reads a shut
eye at ~half the open eye's opening, so the enrolment's shut reference is shallow and a lid
lowered by a sixth (a look down, a smile) read 0.3 on open eyes (issue 38, docs/UPPER_FACE.md)."""

SHUT_LEVEL_PRIOR = 0.8
"""The closure at which an eye reads shut (1) before the session has shown its own blinks,
and the deepest the learned shut level may be (:class:`ClosureLevels`): the reader seldom
reads a shut eye as deep as the enrolment's shut reference (issue 38's first blinks peaked at
0.58-0.8)."""

SHUT_LEVEL_MIN = 0.65
"""The learned shut level is at least this closure: a session whose events are shallow (a
squint that crossed :data:`LEVEL_KNOT`) cannot stretch the closure further."""

SHUT_LEVEL_BLINKS = 2
"""Events (runs of closure above :data:`LEVEL_KNOT`) seen before the shut level is the median
of their deepest closures (the last :data:`SHUT_LEVEL_MEMORY`) rather than the prior."""

SHUT_LEVEL_MEMORY = 9


def levelled(c: float, open_level: float, shut_level: float, curve: float | None = None
             ) -> float:
    """Closure ``c`` (0..1 from the enrolment's references) against the session's levels:
    ``open_level`` reads 0, ``shut_level`` 1 and above, :data:`LEVEL_KNOT` stays (the
    lower part raised to ``curve``, default :data:`OPEN_CURVE`; the upper one linear). Never
    above ``c`` below the knot nor below it above the knot (``open_level`` >= 0,
    ``shut_level`` <= 1, ``curve`` >= 1)."""
    k = LEVEL_KNOT
    if c <= k:
        return k * (max(c - open_level, 0.0) / (k - open_level)) ** (
            OPEN_CURVE if curve is None else curve)
    return min(1.0, k + (1.0 - k) * (c - k) / max(shut_level - k, 1e-6))


def _median(v: Sequence[float]) -> float:
    s = sorted(v)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


@dataclass
class ClosureLevels:
    """One eye's open and shut levels through the session (causal: a frame is read by the
    levels of the frames before it). The open level: the median closure of the last
    :data:`OPEN_LEVEL_FRAMES` frames at most :data:`LEVEL_KNOT` (0 before 5 of them), at most
    :data:`OPEN_LEVEL_MAX`. The shut level: each event (closure above the knot, then back)
    gives its deepest closure; with :data:`SHUT_LEVEL_BLINKS` of them their median, within
    [:data:`SHUT_LEVEL_MIN`, :data:`SHUT_LEVEL_PRIOR`], else the prior: the first blink of a
    session reads by the prior (enrolment may have seen none)."""

    recent: deque = field(default_factory=lambda: deque(maxlen=OPEN_LEVEL_FRAMES))
    peaks: deque = field(default_factory=lambda: deque(maxlen=SHUT_LEVEL_MEMORY))
    peak: float = 0.0  # the deepest closure of the event under way (0: none)

    def levels(self) -> tuple[float, float]:
        """(open level, shut level) now."""
        op = min(OPEN_LEVEL_MAX, _median(self.recent)) if len(self.recent) >= 5 else 0.0
        shut = (SHUT_LEVEL_PRIOR if len(self.peaks) < SHUT_LEVEL_BLINKS
                else _clip(_median(self.peaks), SHUT_LEVEL_MIN, SHUT_LEVEL_PRIOR))
        return op, shut

    def read(self, c: float) -> float:
        """This frame's closure levelled (:func:`levelled`), then the levels updated by it."""
        out = levelled(c, *self.levels())
        if c > LEVEL_KNOT:
            self.peak = max(self.peak, c)
        else:
            if self.peak > 0.0:
                self.peaks.append(self.peak)
                self.peak = 0.0
            self.recent.append(c)
        return out


@dataclass
class UpperTracker:
    """The upper face frame by frame (state: the last reading's measures and placement)."""

    reference: UpperReference | None
    rig: str = "desk"
    photometric: bool = False  # the closure from the photometric measure alone on every
    # frame when usable (else, the default, on a reading's frame the mean of the reader's and
    # the photometric closure, the photometric alone between readings: docs/UPPER_FACE.md)
    clock: Callable[[], float] | None = None  # (given: ``spent_s`` adds up the steps' time)
    spent_s: float = 0.0
    levels: bool = True  # the closure against the session's own levels (:class:`ClosureLevels`;
    # False: against the enrolment's references alone, as before issue 38's levels)
    canon: CanonicalFace = field(default_factory=canonical_face)
    _last: Measures | None = None
    _corners: np.ndarray | None = None  # (2 sides, 2 corners, 2) px at the last reading
    _anchor: np.ndarray | None = None  # (2,) px where the head's point was then
    _gaze: tuple[float, float] | None = None
    _gaze_misses: int = 0  # readings in a row that saw an open eye but fitted no iris
    _closure: tuple[float, float] | None = None
    _wide: tuple[float, float] | None = None
    _offset: list[float | None] = field(default_factory=lambda: [None, None])
    # each eye's running disagreement of the readings with its photometric closure (:meth:`_from`)
    _levels: list[tuple[float, float, float] | None] = field(
        default_factory=lambda: [None, None])  # each eye's grey levels at its last fit
    _templates: list[np.ndarray | None] = field(
        default_factory=lambda: [None, None])  # each watched eye's pixels at the last reading
    _levels_of: list[ClosureLevels] = field(
        default_factory=lambda: [ClosureLevels(), ClosureLevels()])  # each eye's (the
    # session's: kept when the face is lost)

    def reset(self) -> None:
        self._last = self._corners = self._anchor = None
        self._gaze = self._closure = None
        self._gaze_misses = 0
        self._offset = [None, None]
        self._templates = [None, None]

    def _photo(self, grey: np.ndarray, i: int, inner: np.ndarray, outer: np.ndarray
               ) -> float | None:
        """Eye i's photometric measure of the speaker's kind, placed at ``inner``, ``outer``."""
        ref = self.reference
        assert ref is not None and self._last is not None
        open_px = ref.open_mm[i] * self._last.scale
        if ref.photo_kind[i] == "contrast":
            return photo_measure(grey, inner, outer, open_px)
        lv = self._eye_levels(i)
        fn = lid_gap if ref.photo_kind[i] == "gap" else iris_height
        return None if lv is None else fn(grey, inner, outer, open_px, lv)

    def _eye_levels(self, i: int) -> tuple[float, float, float] | None:
        """Eye i's grey levels: the last fitted open eye's, else the enrolment's."""
        lv = self._levels[i]
        return lv if lv is not None or self.reference is None else \
            self.reference.eye_levels(i)

    def step(self, image: np.ndarray, landmarks: np.ndarray | None, anchor: np.ndarray | None,
             ok: bool, lids: np.ndarray | None = None) -> UpperFace:
        """One frame (:meth:`_step`), its time added to ``spent_s`` when there is a clock."""
        if self.clock is None:
            return self._step(image, landmarks, anchor, ok, lids)
        t0 = self.clock()
        out = self._step(image, landmarks, anchor, ok, lids)
        self.spent_s += self.clock() - t0
        return out

    def _step(self, image: np.ndarray, landmarks: np.ndarray | None, anchor: np.ndarray | None,
              ok: bool, lids: np.ndarray | None = None) -> UpperFace:
        """One frame. landmarks : this frame's reading, measured in full (None between
        readings); anchor : (2,) px, where a point fixed to the head (tracked) is in this
        frame, to move the eye corners between readings (None: they stay); ok : whether the
        face is tracked; lids : between readings, this frame's reading where there is one
        (the live reader reads every frame for the lips): only its lids' opening is taken
        (no iris fit, no brow band: cheap), and the closure is that of a reading, the mean of
        the reader's and the photometric one (source ``lids``; the gaze and brows held from
        the last reading). Without it an eye the photometric measure cannot follow held the
        last reading's closure up to three frames: half of the shut frames of the issue-38
        clips' blinks read under 0.8 (docs/UPPER_FACE.md)."""
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
            m = measure(grey, landmarks, self.canon, ref.open_mm, ref.iris_radius_mm,
                        (self._eye_levels(0), self._eye_levels(1)),
                        (ref.brow_window(0), ref.brow_window(1)), ref.photo_kind,
                        self._followed())
            if m is None:
                self.reset()
                return UpperFace.absent("no_face: the landmarks are degenerate")
            lm = np.asarray(landmarks, np.float64)
            for i in range(2):  # the grey levels of an open eye (reader's closure < 0.3)
                if m.levels[i] is not None and closure(m.opening[i], ref.open_mm[i],
                                                       ref.closed_mm[i]) < 0.3:
                    self._levels[i] = m.levels[i]
            self._last = m
            self._corners = np.array([[lm[EYE_CORNERS[s][0], :2], lm[EYE_CORNERS[s][1], :2]]
                                      for s in SIDES])
            self._anchor = None if anchor is None else np.asarray(anchor, np.float64)
            self._templates = [None, None]
            for i in self.watched():  # (an eye read shut: its reopening waits for the cadence)
                if closure(m.opening[i], ref.open_mm[i], ref.closed_mm[i]) < 0.5:
                    self._templates[i] = eye_template(
                        grey, self._corners[i, 0], self._corners[i, 1], ref.open_mm[i] * m.scale)
            return self._from(m, "reader")
        if self._last is None or self._corners is None:
            return UpperFace.absent("no_face: no reading of the eyes yet")
        shift = self._shift(anchor)
        photo = tuple(self._photo(grey, i, self._corners[i, 0] + shift,
                                  self._corners[i, 1] + shift)
                      if used else None for i, used in enumerate(self._followed()))
        if lids is not None and (read := lids_only(lids, self.canon)) is not None:
            return self._from(self._last, "lids", photo, read)  # type: ignore[arg-type]
        return self._from(self._last, "photo", photo)  # type: ignore[arg-type]

    def _shift(self, anchor: np.ndarray | None) -> np.ndarray:
        """How far the head's point moved since the last reading (px; 0 without anchors)."""
        return (np.zeros(2) if anchor is None or self._anchor is None
                else np.asarray(anchor, np.float64) - self._anchor)

    def _followed(self) -> tuple[bool, bool]:
        """Whether each eye's photometric measure is used (:data:`PHOTO_MIN_R`): the
        others' are not measured."""
        ref = self.reference
        assert ref is not None
        return (abs(ref.photo_r[0]) >= PHOTO_MIN_R, abs(ref.photo_r[1]) >= PHOTO_MIN_R)

    def watched(self) -> list[int]:
        """The eyes without a usable photometric measure whose pixels are watched
        between readings (:meth:`wants_reading`)."""
        ref = self.reference
        if ref is None or self.rig == "head":
            return []
        return [i for i in range(2)
                if ref.change_limit[i] > 0 and abs(ref.photo_r[i]) < PHOTO_MIN_R]

    def wants_reading(self, image: np.ndarray, anchor: np.ndarray | None) -> bool:
        """Whether a frame between readings should be read for the eyes: an eye whose
        closure cannot be followed from its pixels (a photometric measure under
        :data:`PHOTO_MIN_R` at enrolment: carphone's ~10 px eyes) but whose pixels changed
        since the last reading (:func:`eye_change`) further than the speaker's open eye does
        between frames (:attr:`UpperReference.change_limit`): a lid closing, or the face
        turning, either worth a reading; where both eyes are watched, both must have changed.
        A blink of two frames falls between readings one time in three otherwise
        (docs/UPPER_FACE.md). ``anchor`` as in :meth:`step`; the
        time is added to ``spent_s`` when there is a clock."""
        t0 = self.clock() if self.clock is not None else 0.0
        try:
            return self._wants_reading(image, anchor)
        finally:
            if self.clock is not None:
                self.spent_s += self.clock() - t0

    def _wants_reading(self, image: np.ndarray, anchor: np.ndarray | None) -> bool:
        ref, m = self.reference, self._last
        if ref is None or m is None or self._corners is None:
            return False
        shift = self._shift(anchor)
        measured = False
        for i in self.watched():
            tpl = self._templates[i]
            if tpl is None:
                continue
            x = eye_change(tpl, image, self._corners[i, 0] + shift, self._corners[i, 1] + shift,
                           ref.open_mm[i] * m.scale)
            if x is None:
                continue
            # both eyes, where both are watched: a blink shuts both; one eye's change alone
            # was the head rolling on carphone (a template is moved with the head, not
            # turned); an eye that did not change ends it (most frames: one eye looked at)
            if x <= ref.change_limit[i]:
                return False
            measured = True
        return measured

    def _from(self, m: Measures, source: str,
              photo: tuple[float | None, float | None] | None = None,
              lids: tuple[tuple[float, float], float] | None = None) -> UpperFace:
        """The upper face of measures ``m`` (``source`` "reader", "lids" or "photo"; ``photo``
        each eye's photometric measure between readings; ``lids``: this frame's lid opening
        and yaw, :func:`lids_only`, in place of ``m``'s)."""
        ref = self.reference
        assert ref is not None
        opening, yaw_deg = (m.opening, m.yaw_deg) if lids is None else lids
        if abs(yaw_deg) > MAX_YAW_DEG:
            why = f"turned: the head is turned {abs(yaw_deg):.0f} deg from the camera"
            return UpperFace.absent(why)
        cl, wide = [], []
        for i in range(2):
            c = closure(opening[i], ref.open_mm[i], ref.closed_mm[i])
            w = (opening[i] - ref.open_mm[i]) / (ref.open_mm[i] - ref.closed_mm[i])
            x = m.photometric(ref.photo_kind[i], i) if photo is None else photo[i]
            usable = x is not None and abs(ref.photo_r[i]) >= PHOTO_MIN_R
            # on a reading's frame (unless ``photometric``) both measures are averaged: two
            # estimates of the closure with their own errors (the reader's saturates near
            # closed; the average keeps a laugh's squint, which the reader reads 0.5-0.7, under
            # 0.5 on franck and pexels_woman: docs/UPPER_FACE.md)
            reading = (photo is None or source == "lids") and not self.photometric
            if usable:
                raw = ref.photo[2 * i] + ref.photo[2 * i + 1] * float(x)  # type: ignore[arg-type]
                if reading:
                    # the mean is the photometric closure moved by half the two measures'
                    # disagreement (closures, 0..1); that move, a running mean over the
                    # full readings (:data:`OFFSET_WEIGHT`), is carried to the frames between
                    # that have no reading at all
                    if source == "reader":
                        d = 0.5 * (c - _clip(raw, 0.0, 1.0))
                        off = self._offset[i]
                        self._offset[i] = d if off is None else (
                            OFFSET_WEIGHT * d + (1.0 - OFFSET_WEIGHT) * off)
                    raw = 0.5 * (raw - w)
                elif (off := self._offset[i]) is not None and not self.photometric:
                    # between readings the photometric measure gives the change, the readings
                    # the level: where the two measures disagree for longer than a reading
                    # (pexels_woman's left lid as bright as her white, read open while shut;
                    # her right eye's iris height, read half closed while open) the closure
                    # does not jump at the reader's cadence (docs/UPPER_FACE.md)
                    cl.append(_clip(_clip(raw, 0.0, 1.0) + off, 0.0, 1.0))
                    wide.append(_clip(-raw, 0.0, 1.0))
                    continue
                c, w = _clip(raw, 0.0, 1.0), -raw
            elif source == "lids":
                pass  # the reader's lids this frame, as read
            elif photo is None:
                self._offset[i] = None  # a reading without the photometric measure
            elif self._closure is not None:
                c = self._closure[i]  # between readings without a usable gap: held
                w = 0.0 if self._wide is None else self._wide[i]
            cl.append(c)
            wide.append(_clip(float(w), 0.0, 1.0))
        self._wide = (wide[0], wide[1])
        self._closure = (cl[0], cl[1])  # (held between readings as measured, not levelled)
        if self.levels:
            cl = [self._levels_of[i].read(cl[i]) for i in range(2)]
        gaze = self._gaze
        if source == "reader":
            # the gaze's zero is the iris centred in the eye's opening (not the enrolment's
            # median: a speaker who looked round while enrolling would shift it)
            offs = [iris[:2] for i, iris in enumerate(m.iris) if iris is not None and cl[i] < 0.5]
            if offs:
                dx = sum(o[0] for o in offs) / len(offs)  # (numpy's mean of the 1-2 eyes)
                dy = sum(o[1] for o in offs) / len(offs)
                gaze = (math.degrees(math.asin(_clip(float(dx) / EYE_RADIUS_MM, -1.0, 1.0))),
                        math.degrees(math.asin(_clip(float(dy) / EYE_RADIUS_MM, -1.0, 1.0))))
                self._gaze, self._gaze_misses = gaze, 0
            elif min(cl) < 0.5:
                # an open eye read without an iris fitted: the gaze held from an older reading
                # is no longer what the eye shows once the misses run on (GAZE_MISSES); a shut
                # eye hides the iris and keeps it held
                self._gaze_misses += 1
                if self._gaze_misses >= GAZE_MISSES:
                    gaze = self._gaze = None
        lower = [None, None] if ref.lower_mm is None else [
            _clip(float((m.lower[i] - ref.lower_mm[i]) / ref.open_mm[i]), -1.0, 1.0)
            for i in range(2)]
        squeeze = [None, None] if ref.brow_x_mm is None else [
            ref.brow_x_mm[i] - m.brow_x[i] for i in range(2)]
        # (in Python floats: the same float64 differences as numpy's on these 4-vectors)
        rise = [b - float(r) for b, r in zip(m.brows.tolist(), ref.brows_mm, strict=True)]
        for i in range(2):  # the brow band from the pixels where measured (module docstring)
            band = m.band[i]
            if band is None or ref.brow_window(i) is None or band == (None, None):
                continue
            up = [None if h is None or ref.brow_band_mm[2 * i + j] <= 0
                  else h - ref.brow_band_mm[2 * i + j] for j, h in enumerate(band)]
            if up == [None, None]:
                continue
            # a half not seen (under hair, off the face) rises with the other
            rise[2 * i:2 * i + 2] = [up[j] if up[j] is not None else up[1 - j] for j in range(2)]
        lowering = float(max(0.0, -(rise[0] + rise[2]) / 2.0))
        return UpperFace(True, "", cl[0], cl[1], None if gaze is None else gaze[0],
                         None if gaze is None else gaze[1], source, True, "",
                         float(rise[0]), float(rise[1]), float(rise[2]), float(rise[3]), lowering,
                         wide[0], wide[1], lower[0], lower[1], squeeze[0], squeeze[1])

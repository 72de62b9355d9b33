"""The synthetic speaker's upper face: eyes that blink and look, brows that rise, with truth.

A simple eye model painted on the face's skin (the texture at the neutral head-frame x, y, so
it moves and turns with the head): per eye a sclera (an ellipse 24 x 9 mm), an iris (10 mm)
and pupil that move inside it with the gaze (``EYE_RADIUS_MM`` x sin(angle)), an upper lid that
comes down over it with the closure (0 open .. 1 closed: its edge from the top of the sclera
to the bottom) and a lower lid line; per side a brow that rises by its raise in mm. The skin
under them is the speaker's own (its atlas, inpainted where the static eyes were painted).

:func:`upper_sequence` draws a person-like timeline: blinks 10-20 a minute at random
intervals (some double: a second blink 250-400 ms after the first), each closing in ~80 ms,
closed ~40 ms and opening in ~150 ms; gaze fixations of 0.4-2 s joined by fast saccades
(within +-15 deg yaw, +-10 deg pitch); brow raises of 2-5 mm held 0.3-1.2 s, now and then.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from articast.core.errors import InputError
from articast.core.synthetic.texture import SKIN_PPM, SKIN_X0, SKIN_Y1, make_atlas

EYE_RADIUS_MM = 11.5
EYE_Y, EYE_X = 52.0, 32.0
"""The eyes' centres in the neutral head frame (mm), as the static texture paints them."""
SCLERA = (12.0, 4.5)
"""Half-axes of the sclera, mm."""
BROW_Y = 61.0
"""The animated brows' rest height (3 mm below the static texture's: raised, those went under
the hair)."""
REGION = (-55.0, 55.0, 36.0, 78.0)
"""The part of the skin repainted (x0, x1, y0, y1 mm, head frame)."""


@dataclass(frozen=True)
class UpperTruth:
    """A sequence's upper face. closure (F, 2) left, right 0..1; gaze (F, 2) yaw (to the
    speaker's left +), pitch (up +), deg; brows (F, 2) left, right raise, mm; blinks: the
    (onset, end) frames of each blink (closure > 0.5)."""

    closure: np.ndarray
    gaze: np.ndarray
    brows: np.ndarray
    blinks: tuple[tuple[int, int], ...]

    def frame(self, i: int) -> dict[str, float]:
        """Frame ``i``'s truth as the track lines name it."""
        return {"closure_left": float(self.closure[i, 0]),
                "closure_right": float(self.closure[i, 1]),
                "gaze_yaw_deg": float(self.gaze[i, 0]), "gaze_pitch_deg": float(self.gaze[i, 1]),
                "raise_left_mm": float(self.brows[i, 0]),
                "raise_right_mm": float(self.brows[i, 1])}


def _blink_profile(t: np.ndarray) -> np.ndarray:
    """Closure (0..1) of one blink at times t (s) from its onset."""
    close, hold, reopen = 0.08, 0.04, 0.15
    out = np.zeros_like(t)
    a = (t >= 0) & (t < close)
    out[a] = np.sin(0.5 * np.pi * t[a] / close) ** 2
    out[(t >= close) & (t < close + hold)] = 1.0
    b = (t >= close + hold) & (t < close + hold + reopen)
    out[b] = np.cos(0.5 * np.pi * (t[b] - close - hold) / reopen) ** 2
    return out


def upper_sequence(seed: int, n_frames: int, fps: float) -> UpperTruth:
    """A person-like upper-face timeline of ``n_frames`` at ``fps`` (module docstring)."""
    if n_frames < 1 or not fps > 0:
        raise InputError(f"need n_frames >= 1 and fps > 0, got {n_frames}, {fps}")
    rng = np.random.default_rng([int(seed), 0xE7E5])
    t = np.arange(n_frames) / fps
    dur = n_frames / fps
    closure = np.zeros(n_frames)
    onsets: list[float] = []
    at = rng.uniform(0.3, 2.0)
    while at < dur:
        onsets.append(at)
        if rng.random() < 0.2:  # a double blink
            onsets.append(at + rng.uniform(0.25, 0.4))
        at = onsets[-1] + rng.uniform(3.0, 6.0)  # 10-20 a minute
    for o in onsets:
        closure = np.maximum(closure, _blink_profile(t - o))
    gaze = np.zeros((n_frames, 2))
    at, cur = 0.0, np.zeros(2)
    while at < dur:
        nxt = np.array([rng.uniform(-15, 15), rng.uniform(-10, 10)])
        sacc = 0.04
        m = (t >= at) & (t < at + sacc)
        gaze[m] = cur + (nxt - cur) * ((t[m] - at) / sacc)[:, None]
        hold = rng.uniform(0.4, 2.0)
        gaze[(t >= at + sacc) & (t < at + sacc + hold)] = nxt
        at, cur = at + sacc + hold, nxt
    brows = np.zeros((n_frames, 2))
    at = rng.uniform(0.5, 2.0)
    while at < dur:
        h = rng.uniform(2.0, 5.0)
        length = rng.uniform(0.3, 1.2)
        ramp = 0.15
        shape = np.clip(np.minimum((t - at) / ramp, (at + length + ramp - t) / ramp), 0, 1)
        side = rng.uniform(0.8, 1.2, 2)
        brows = np.maximum(brows, shape[:, None] * h * side[None])
        at += length + 2 * ramp + rng.uniform(1.0, 4.0)
    cl2 = np.column_stack([closure, closure])
    flags = np.concatenate([[False], closure > 0.5, [False]])
    d = np.flatnonzero(np.diff(flags.astype(int)))
    blinks = tuple(zip(d[::2].tolist(), d[1::2].tolist(), strict=True))
    return UpperTruth(cl2, gaze, brows, blinks)


def _grid() -> tuple[np.ndarray, np.ndarray, tuple[slice, slice]]:
    """The repainted region's head-frame x, y (mm) per atlas pixel, and its atlas slices."""
    x0, x1, y0, y1 = REGION
    c0, c1 = int((x0 - SKIN_X0) * SKIN_PPM), int((x1 - SKIN_X0) * SKIN_PPM)
    r0, r1 = int((SKIN_Y1 - y1) * SKIN_PPM), int((SKIN_Y1 - y0) * SKIN_PPM)
    xs = SKIN_X0 + np.arange(c0, c1) / SKIN_PPM
    ys = SKIN_Y1 - np.arange(r0, r1) / SKIN_PPM
    x, y = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    return x, y, (slice(r0, r1), slice(c0, c1))


@lru_cache(maxsize=4)
def _bare(seed: int) -> np.ndarray:
    """The region's skin without the static eyes and brows (inpainted), uint8."""
    x, y, sl = _grid()
    patch = np.ascontiguousarray(make_atlas(seed).image[sl])
    painted = np.zeros(x.shape, bool)
    for side in (-1.0, 1.0):
        ex = side * EYE_X
        painted |= ((x - ex) / 13.8) ** 2 + ((y - EYE_Y) / 6.6) ** 2 < 1.0
        brow = np.abs(y - (64.0 - 0.006 * (x - ex) ** 2 + 1.5 * side * (x - ex) / 15)) < 3.2
        painted |= brow & (np.abs(x - ex) < 18.5)
    mask = cv2.dilate(painted.astype(np.uint8), np.ones((5, 5), np.uint8))
    out = cv2.inpaint(patch, mask, 5, cv2.INPAINT_TELEA)
    out.setflags(write=False)
    return out


def paint_upper(seed: int, closure: tuple[float, float], gaze: tuple[float, float],
                brows: tuple[float, float]) -> np.ndarray:
    """Speaker ``seed``'s atlas image (a copy) with the eyes at ``closure`` (left, right),
    looking at ``gaze`` (yaw, pitch deg) and the brows raised by ``brows`` (left, right mm)."""
    x, y, sl = _grid()
    img = make_atlas(seed).image.copy()
    patch = _bare(seed).astype(np.float32)
    skin = patch.copy()
    yaw, pitch = np.radians(gaze[0]), np.radians(gaze[1])
    for k, side in enumerate((1.0, -1.0)):  # left (+x), right
        ex, ey = side * EYE_X, EYE_Y
        c = float(np.clip(closure[k], 0.0, 1.0))
        sclera = ((x - ex) / SCLERA[0]) ** 2 + ((y - ey) / SCLERA[1]) ** 2 < 1.0
        # the upper lid's edge: an arc from corner to corner, the sclera's top arc when
        # open, its bottom arc when closed
        arc = SCLERA[1] * np.sqrt(np.clip(1.0 - ((x - ex) / SCLERA[0]) ** 2, 0.0, 1.0))
        top = ey + (1.0 - 2.0 * c) * arc
        visible = sclera & (y < top)
        ix, iy = ex + EYE_RADIUS_MM * np.sin(yaw), ey + EYE_RADIUS_MM * np.sin(pitch)
        patch[visible] = (218.0, 222.0, 228.0)
        iris = visible & (np.hypot(x - ix, y - iy) < 5.0)
        patch[iris] = (50.0, 70.0, 95.0)
        patch[visible & (np.hypot(x - ix, y - iy) < 2.0)] = (15.0, 15.0, 18.0)
        lid = sclera & (y >= top)
        patch[lid] = skin[lid] * 0.88  # the lid's skin, a little shaded
        edge = (np.abs(y - top) < 0.7) & (np.abs(x - ex) < SCLERA[0])
        patch[edge] = (40.0, 45.0, 60.0)  # the lash line
        low = np.abs(((x - ex) / 12.6) ** 2 + ((y - ey) / 5.0) ** 2 - 1.0) < 0.15
        patch[low & (y < ey - 1)] = patch[low & (y < ey - 1)] * 0.8
        r = float(brows[k])
        brow = np.abs(y - (BROW_Y + r - 0.006 * (x - ex) ** 2 + 1.5 * side * (x - ex) / 15)) < 2.2
        brow &= np.abs(x - ex) < 17.0
        patch[brow] = patch[brow] * 0.35 + np.array([30.0, 40.0, 55.0]) * 0.65
    img[sl] = np.clip(patch, 0, 255).astype(np.uint8)
    return img

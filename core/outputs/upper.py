"""The upper face (:class:`~articast.core.faces.upper.UpperFace`) in the standard outputs:
ARKit blendshapes, MPEG-4 FAPs and the eye bones' rotations of VMC.

Only what was seen is produced: the eye values when ``eyes_ok``, the brow values when
``brows_ok`` (an absent eye is left out, never sent as an open eye at 0).

ARKit (values 0..1; "Left" is the speaker's own left):

==========================  =================================================================
eyeBlinkLeft/Right          the eyelid closure (0 the speaker's open eye, 1 closed)
eyeLookOutLeft, InRight     gaze yaw to the speaker's left / :data:`GAZE_FULL_DEG`
eyeLookInLeft, OutRight     gaze yaw to the speaker's right / :data:`GAZE_FULL_DEG`
eyeLookUp/Down Left/Right   gaze pitch up / down / :data:`GAZE_FULL_DEG`
browInnerUp                 the inner brows' mean raise / :data:`BROW_FULL_MM`
browOuterUpLeft/Right       that outer brow's raise / :data:`BROW_FULL_MM`
browDownLeft/Right          that inner brow's lowering / :data:`BROW_DOWN_FULL_MM`
eyeWideLeft/Right           the eye open beyond the speaker's usual open eye (``wide_*``, in
                            units of its open-to-closed travel), less :data:`WIDE_DEAD` (the
                            open eye's own noise), over :data:`WIDE_FULL`
eyeSquintLeft/Right         the lower lid's rise (``lower_lid_*``, a fraction of the open eye)
                            over :data:`SQUINT_FULL`
==========================  =================================================================

FAPs (FAP.md; units FAPU/1024): ``close_t_l/r_eyelid`` (19, 20) the top lid's travel down,
closure x IRISD0 (the open eye's lid opening is IRISD0 by the FAPU's definition, 3.1.y - 3.3.y:
a closed eye is 1024); ``close_b_*`` (21, 22) the lower lid's rise (up +) in the same units
(``lower_lid_*`` x 1024; 0 when not measured); eyeball yaw (23, 24, to the left +) and pitch
(25, 26, down +) in AU (1e-5 rad), both eyes the gaze; ``raise_l/r_i/m/o_eyebrow`` (31-36)
the raise in ENS0 units (the middle: the mean of the inner and outer);
``squeeze_l/r_eyebrow`` (37, 38) the inner brow's move towards the midline (FAP.md: the left
brow's "right", the right brow's "left") in ES0 units, when measured.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

GAZE_FULL_DEG = 30.0
"""Gaze angle of a full eyeLook* weight (eyes rotate ~30-40 deg before the head follows)."""
BROW_FULL_MM = 8.0
"""Brow raise of a full browInnerUp / browOuterUp weight (a full raise is ~8-12 mm)."""
BROW_DOWN_FULL_MM = 4.0
"""Inner-brow lowering of a full browDown weight."""
WIDE_DEAD, WIDE_FULL = 0.1, 0.4
"""eyeWide = (wide - WIDE_DEAD) / WIDE_FULL, clipped: an open eye reads within ~0.1 of its
usual opening (the measure's noise on the synthetic speaker: docs/UPPER_FACE.md); a full
eyeWide is an eye opened by half its open-to-closed travel beyond the usual."""
SQUINT_FULL = 0.25
"""Lower-lid rise (a fraction of the open eye) of a full eyeSquint."""

EYE_SHAPES = ("eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight",
              "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight",
              "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight",
              "eyeWideLeft", "eyeWideRight")
BROW_SHAPES = ("browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft",
               "browOuterUpRight")
EYE_FAPS = (19, 20, 21, 22, 23, 24, 25, 26)
BROW_FAPS = (31, 32, 33, 34, 35, 36, 37, 38)


def _unit(x: float) -> float:
    return float(np.clip(x, 0.0, 1.0))


def arkit_upper(u: Any) -> dict[str, float]:
    """ARKit weights of the upper face (the eye shapes if its eyes are ok, the brow shapes if
    its brows are; ``{}`` for None)."""
    out: dict[str, float] = {}
    if u is None:
        return out
    if u.eyes_ok and u.closure_left is not None and u.closure_right is not None:
        out["eyeBlinkLeft"] = _unit(u.closure_left)
        out["eyeBlinkRight"] = _unit(u.closure_right)
        yaw = u.gaze_yaw_deg or 0.0
        pitch = u.gaze_pitch_deg or 0.0
        to_left, to_right = _unit(yaw / GAZE_FULL_DEG), _unit(-yaw / GAZE_FULL_DEG)
        up, down = _unit(pitch / GAZE_FULL_DEG), _unit(-pitch / GAZE_FULL_DEG)
        out.update({"eyeLookOutLeft": to_left, "eyeLookInRight": to_left,
                    "eyeLookInLeft": to_right, "eyeLookOutRight": to_right,
                    "eyeLookUpLeft": up, "eyeLookUpRight": up,
                    "eyeLookDownLeft": down, "eyeLookDownRight": down})
        for side in ("Left", "Right"):
            wide = getattr(u, f"wide_{side.lower()}", None)
            if wide is not None:
                out[f"eyeWide{side}"] = _unit((wide - WIDE_DEAD) / WIDE_FULL)
            lower = getattr(u, f"lower_lid_{side.lower()}", None)
            if lower is not None:
                out[f"eyeSquint{side}"] = _unit(lower / SQUINT_FULL)
    if u.brows_ok and u.raise_inner_left_mm is not None:
        inner = (u.raise_inner_left_mm + u.raise_inner_right_mm) / 2.0
        out["browInnerUp"] = _unit(inner / BROW_FULL_MM)
        out["browOuterUpLeft"] = _unit(u.raise_outer_left_mm / BROW_FULL_MM)
        out["browOuterUpRight"] = _unit(u.raise_outer_right_mm / BROW_FULL_MM)
        out["browDownLeft"] = _unit(-u.raise_inner_left_mm / BROW_DOWN_FULL_MM)
        out["browDownRight"] = _unit(-u.raise_inner_right_mm / BROW_DOWN_FULL_MM)
    return out


def fap_upper(u: Any, fapu: Any) -> dict[int, int]:
    """FAP number -> integer value of the upper face (what was seen; ``{}`` for None).
    fapu : :class:`~articast.core.outputs.fap.Fapu` of the speaker's model."""
    out: dict[int, int] = {}
    if u is None:
        return out
    if u.eyes_ok and u.closure_left is not None and u.closure_right is not None:
        out[19] = int(round(_unit(u.closure_left) * 1024))
        out[20] = int(round(_unit(u.closure_right) * 1024))
        for n, lower in ((21, getattr(u, "lower_lid_left", None)),
                         (22, getattr(u, "lower_lid_right", None))):
            out[n] = 0 if lower is None else int(round(float(np.clip(lower, -1, 1)) * 1024))
        if u.gaze_yaw_deg is not None and u.gaze_pitch_deg is not None:
            yaw = int(round(math.radians(u.gaze_yaw_deg) / 1e-5))
            pitch = int(round(-math.radians(u.gaze_pitch_deg) / 1e-5))
            out.update({23: yaw, 24: yaw, 25: pitch, 26: pitch})
    if u.brows_ok and u.raise_inner_left_mm is not None:
        ens = float(fapu.ENS0) / 1024.0
        li, lo = u.raise_inner_left_mm, u.raise_outer_left_mm
        ri, ro = u.raise_inner_right_mm, u.raise_outer_right_mm
        for n, mm in ((31, li), (32, ri), (33, (li + lo) / 2), (34, (ri + ro) / 2), (35, lo),
                      (36, ro)):
            out[n] = int(round(mm / ens))
        es = float(fapu.ES0) / 1024.0
        for n, sq in ((37, getattr(u, "squeeze_left_mm", None)),
                      (38, getattr(u, "squeeze_right_mm", None))):
            if sq is not None:
                out[n] = int(round(sq / es))
    return out


def upper_from_faps(values: dict[int, int], fapu: Any) -> dict[str, float]:
    """The inverse of :func:`fap_upper` for what it encodes: closures, gaze (deg) and brow
    raises (mm) of one frame's FAP values (for reading ``.fap`` files back)."""
    out: dict[str, float] = {}
    if 19 in values:
        out["closure_left"] = values[19] / 1024.0
        out["closure_right"] = values[20] / 1024.0
    if 21 in values:
        out["lower_lid_left"] = values[21] / 1024.0
        out["lower_lid_right"] = values[22] / 1024.0
    if 23 in values:
        out["gaze_yaw_deg"] = math.degrees(values[23] * 1e-5)
        out["gaze_pitch_deg"] = -math.degrees(values[25] * 1e-5)
    if 31 in values:
        ens = float(fapu.ENS0) / 1024.0
        out.update({"raise_inner_left_mm": values[31] * ens, "raise_inner_right_mm":
                    values[32] * ens, "raise_outer_left_mm": values[35] * ens,
                    "raise_outer_right_mm": values[36] * ens})
    if 37 in values:
        es = float(fapu.ES0) / 1024.0
        out["squeeze_left_mm"] = values[37] * es
        out["squeeze_right_mm"] = values[38] * es
    return out


def eye_rotation(u: Any) -> np.ndarray | None:
    """(3, 3) rotation of both eyes in the head frame (x the speaker's left, y up, z forward):
    yaw about +y (to the speaker's left +), then pitch (up +: about -x); None unless the eyes
    are ok and the gaze is known."""
    if u is None or not u.eyes_ok or u.gaze_yaw_deg is None or u.gaze_pitch_deg is None:
        return None
    y, p = math.radians(u.gaze_yaw_deg), math.radians(u.gaze_pitch_deg)
    ry = np.array([[math.cos(y), 0.0, math.sin(y)], [0.0, 1.0, 0.0],
                   [-math.sin(y), 0.0, math.cos(y)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), math.sin(p)],
                   [0.0, -math.sin(p), math.cos(p)]])
    return ry @ rx


def with_upper_faps(values: np.ndarray, mask: np.ndarray, uppers: list[Any],
                    fapu: Any) -> tuple[np.ndarray, np.ndarray]:
    """The lower face's FAP values (F, 68) and mask ((68,) or (F, 68)) with each frame's
    upper-face FAPs added (``uppers``: F UpperFace or None): a per-frame mask (F, 68), the
    eye and brow FAPs flagged only on the frames where they were seen."""
    vals = np.array(values, np.int64)
    m = np.array(np.broadcast_to(np.asarray(mask, bool), vals.shape))
    for i, u in enumerate(uppers):
        for n, v in fap_upper(u, fapu).items():
            vals[i, n - 1] = v
            m[i, n - 1] = True
    return vals, m

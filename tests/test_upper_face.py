"""The upper face (core/faces/upper.py): eyelids, gaze and brows from a reading, pose removed,
against readings made from the canonical face with known lids, brows, iris and head pose."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from articast.core.errors import ModelFileError
from articast.core.faces import upper as U
from articast.core.faces.canonical import canonical_face
from articast.core.model.camera import Pose, rotation_matrix
from articast.core.tracking.result import TrackResult

CANON = canonical_face()
SCALE = 3.0  # px per mm
CENTRE = np.array([320.0, 200.0])


def reading(points_mm: np.ndarray, yaw_deg: float = 0.0, roll_deg: float = 0.0,
            scale: float = SCALE) -> np.ndarray:
    """A reading (468, 3) in image px of head-frame points, the head turned by yaw and roll
    (orthographic, as the landmark network's x, y, z)."""
    r = rotation_matrix(np.array([0.0, math.radians(yaw_deg), 0.0])) @ rotation_matrix(
        np.array([0.0, 0.0, math.radians(roll_deg)]))
    p = (points_mm - points_mm.mean(0)) @ r.T * scale
    return np.column_stack([p[:, 0] + CENTRE[0], -p[:, 1] + CENTRE[1], -p[:, 2]])


def with_lids(closing_mm: float) -> np.ndarray:
    """The canonical face with both upper lids lowered by ``closing_mm``."""
    v = CANON.vertices_mm.copy()
    for side in U.SIDES:
        for up, _ in U.LID_PAIRS[side]:
            v[up, 1] -= closing_mm
    return v


OPEN = U.lid_opening_mm(CANON.vertices_mm)[0]  # the canonical eye's lid opening, mm
REF = U.UpperReference(open_mm=(OPEN, OPEN), closed_mm=(1.0, 1.0),
                       brows_mm=tuple(U.brow_heights_mm(CANON.vertices_mm)),
                       iris_mm=(0.0, 0.0, 0.0, 0.0))


def test_alignment_removes_pose_and_scale():
    for yaw, roll in ((0.0, 0.0), (25.0, 0.0), (-20.0, 12.0)):
        al = U.align(reading(CANON.vertices_mm, yaw, roll), CANON)
        assert al is not None
        assert al.scale == pytest.approx(SCALE, rel=1e-6)
        assert abs(abs(al.yaw_deg) - abs(yaw)) < 1e-6
        ids = CANON.procrustes_ids
        assert np.abs(al.points[ids] - CANON.vertices_mm[ids]).max() < 1e-6


def test_the_compiled_3x3_svd_is_numpys_to_rounding():
    """faces.kernels._svd3 (the alignment's SVD, one-sided Jacobi) gives np.linalg.svd's
    singular values, orthogonal factors that rebuild the matrix, and the same Procrustes
    rotation and scale (u diag(1, 1, det) vt), on well and badly conditioned matrices, of
    rank 2 and 1, diagonal, symmetric, and zero."""
    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(12)
    for k in range(3000):
        m = rng.normal(size=(3, 3)) * rng.uniform(1e-3, 1e3, 3)[None, :] * 10.0 ** rng.uniform(-3, 3)
        if k % 7 == 1:
            m[:, 2] = 0.0  # rank 2: the third u from the first two
        elif k % 7 == 2:
            m[:, 1] = 2.0 * m[:, 0]
        elif k % 7 == 3:
            m = np.diag(rng.uniform(0.0, 5.0, 3))
        elif k % 7 == 4:
            m = m @ m.T
        elif k % 7 == 5:
            m = np.outer(rng.normal(size=3), rng.normal(size=3))  # rank 1
        u, s, vt = FK._svd3(m)
        u0, s0, vt0 = np.linalg.svd(m)
        top = s0[0]
        np.testing.assert_allclose(s, s0, rtol=0, atol=1e-14 * top)
        np.testing.assert_allclose(u @ np.diag(s) @ vt, m, rtol=0, atol=1e-14 * top)
        np.testing.assert_allclose(vt @ vt.T, np.eye(3), atol=1e-14)
        if s0[1] > 1e-6 * top:  # (rank 1 leaves u's last two columns free)
            np.testing.assert_allclose(u.T @ u, np.eye(3), atol=1e-14)
        if min(s0[0] - s0[1], s0[1] - s0[2], s0[1]) > 1e-3 * top:  # a well-defined rotation
            rots = []
            for uu, ss, vv in ((u, s, vt), (u0, s0, vt0)):
                d = 1.0 if np.linalg.det(uu) * np.linalg.det(vv) > 0 else -1.0
                rots.append((uu @ np.diag([1.0, 1.0, d]) @ vv, ss[0] + ss[1] + d * ss[2]))
            np.testing.assert_allclose(rots[0][0], rots[1][0], rtol=0, atol=1e-12)
            assert rots[0][1] == pytest.approx(rots[1][1], rel=1e-13, abs=1e-14 * top)
    u, s, vt = FK._svd3(np.zeros((3, 3)))
    assert np.all(s == 0.0) and np.all(np.isfinite(u)) and np.all(np.isfinite(vt))


def test_compiled_alignment_is_the_numpy_alignment_to_rounding():
    """align's compiled call (faces.kernels.aligned) gives align_numpy's points, scale and
    yaw to rounding (its sums in another order), at any pose and scale, with noise on the
    points, mirrored (a reflection) and with the non-rigid points not finite; and None where
    the numpy code gives None."""
    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(11)
    compared = 0
    for k in range(60):
        lm = reading(CANON.vertices_mm, rng.uniform(-40, 40), rng.uniform(-20, 20)) \
            * rng.uniform(0.3, 2.5) + rng.normal(0.0, (0.0, 0.5, 3.0)[k % 3], (468, 3))
        if k % 5 == 1:
            lm[:, 0] *= -1.0  # mirrored: the rotation's reflection is taken out
        if k % 7 == 2:
            lm[np.setdiff1d(np.arange(468), CANON.procrustes_ids)[:5]] = np.nan
        lm.setflags(write=False)  # (a reading's landmarks are read-only)
        got, ref = U.align(lm, CANON), U.align_numpy(lm, CANON)
        assert ref is not None and got is not None
        np.testing.assert_allclose(got.points, ref.points, rtol=1e-12, atol=1e-12)
        assert got.scale == pytest.approx(ref.scale, rel=1e-12)
        assert got.yaw_deg == pytest.approx(ref.yaw_deg, rel=1e-12, abs=1e-12)
        compared += 1
    for bad in (np.full((468, 3), np.nan), np.zeros((468, 3))):
        assert U.align(bad, CANON) is None and U.align_numpy(bad, CANON) is None
    assert compared == 60


def test_closure_is_relative_to_the_speakers_open_eye_whatever_the_pose():
    tracker = U.UpperTracker(REF)
    img = np.full((400, 640, 3), 128, np.uint8)
    seen = []
    for closing in (0.0, (OPEN - 1.0) / 2, OPEN - 1.0):
        for yaw in (0.0, 25.0):
            f = tracker.step(img, reading(with_lids(closing), yaw), None, True)
            assert f.eyes_ok and f.source == "reader"
            seen.append((closing, f.closure_left, f.closure_right))
    for closing, left, right in seen:
        want = min(1.0, closing / (OPEN - 1.0))
        assert left == pytest.approx(want, abs=0.02) and right == pytest.approx(want, abs=0.02)


def test_brow_raise_in_mm_whatever_the_pose():
    v = CANON.vertices_mm.copy()
    for p in U.BROW_POINTS["left"]["inner"]:
        v[p, 1] += 3.0
    for p in (*U.BROW_POINTS["right"]["inner"], *U.BROW_POINTS["right"]["outer"]):
        v[p, 1] -= 2.0
    tracker = U.UpperTracker(REF)
    f = tracker.step(np.full((400, 640, 3), 128, np.uint8), reading(v, 20.0, 8.0), None, True)
    assert f.brows_ok
    assert f.raise_inner_left_mm == pytest.approx(3.0, abs=0.05)
    assert f.raise_outer_left_mm == pytest.approx(0.0, abs=0.05)
    assert f.raise_inner_right_mm == pytest.approx(-2.0, abs=0.05)
    assert f.lowering_mm == pytest.approx(max(0.0, -(3.0 - 2.0) / 2), abs=0.05)
    assert f.brows_dict()["raise_left_mm"] == pytest.approx(1.5, abs=0.05)


def eye_image(lm: np.ndarray, iris_mm: tuple[float, float], scale: float = SCALE) -> np.ndarray:
    """Skin, white eyes inside their contours, a dark iris at ``iris_mm`` (x left, y up) from
    each eye's corners' midpoint (a frontal face)."""
    img = np.full((400, 640), 150, np.uint8)
    for side in U.SIDES:
        poly = np.round(lm[list(U.EYE_CONTOUR[side]), :2]).astype(np.int32)
        cv2.fillPoly(img, [poly], 235)
        inner, outer = U.EYE_CORNERS[side]
        mid = (lm[inner, :2] + lm[outer, :2]) / 2.0
        c = mid + np.array([iris_mm[0], -iris_mm[1]]) * scale
        mask = np.zeros_like(img)
        cv2.fillPoly(mask, [poly], 1)
        disc = np.zeros_like(img)
        cv2.circle(disc, (int(round(c[0])), int(round(c[1]))), int(5.5 * scale), 1, -1)
        img[(mask > 0) & (disc > 0)] = 30
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def test_gaze_from_the_iris_between_the_corners():
    lm = reading(CANON.vertices_mm)
    tracker = U.UpperTracker(REF)
    centred = tracker.step(eye_image(lm, (0.0, 0.0)), lm, None, True)
    assert abs(centred.gaze_yaw_deg) < 3.0 and abs(centred.gaze_pitch_deg) < 4.0
    left = tracker.step(eye_image(lm, (3.0, 0.0)), lm, None, True)
    want = math.degrees(math.asin(3.0 / U.EYE_RADIUS_MM))
    assert left.gaze_yaw_deg - centred.gaze_yaw_deg == pytest.approx(want, abs=4.0)
    assert left.gaze_yaw_deg > centred.gaze_yaw_deg + 8.0
    right = tracker.step(eye_image(lm, (-3.0, 0.0)), lm, None, True)
    assert right.gaze_yaw_deg < centred.gaze_yaw_deg - 8.0


def test_a_gaze_no_reading_sees_is_absent_not_held():
    """The gaze is held between readings and through one reading that fits no iris (the
    fit's noise); an open eye read twice in a row without an iris makes it absent (None),
    where it was held for good (carphone's ~10 px eyes: one value for 43 of 48 frames); a
    shut eye, which hides the iris, keeps it held however long; a fitted iris brings it
    back."""
    lm = reading(CANON.vertices_mm)
    shut = reading(with_lids(OPEN - 1.0))
    blank = np.full((400, 640, 3), 128, np.uint8)  # no iris, no white: nothing to fit
    tracker = U.UpperTracker(REF)
    seen = tracker.step(eye_image(lm, (3.0, 0.0)), lm, None, True)
    assert seen.gaze_yaw_deg is not None and seen.gaze_yaw_deg > 8.0
    for _ in range(3):  # shut: held
        f = tracker.step(blank, shut, None, True)
        assert f.eyes_ok and (f.gaze_yaw_deg, f.gaze_pitch_deg) == (
            seen.gaze_yaw_deg, seen.gaze_pitch_deg)
    once = tracker.step(blank, lm, None, True)  # open, one miss: held
    assert once.eyes_ok and once.gaze_yaw_deg == seen.gaze_yaw_deg
    twice = tracker.step(blank, lm, None, True)  # open, a second miss in a row: absent
    assert twice.eyes_ok and twice.gaze_yaw_deg is None and twice.gaze_pitch_deg is None
    assert twice.closure_left is not None  # (the lids are still measured)
    back = tracker.step(eye_image(lm, (-3.0, 0.0)), lm, None, True)
    assert back.gaze_yaw_deg is not None and back.gaze_yaw_deg < -8.0


def lidded_eye_image(lm: np.ndarray, iris_mm: tuple[float, float], scale: float = SCALE,
                     iris_radius_mm: float = 5.5, roll_deg: float = 0.0,
                     closure: float = 0.0, lash_mm: float = 0.0, lid: int = 130,
                     skin: int = 150, white: int = 235, nasal_white: int | None = None
                     ) -> np.ndarray:
    """Skin, per eye an opening (an ellipse between the corners, a quarter as high as wide:
    the lids cover the iris's top and bottom) and a dark iris at ``iris_mm`` (x left, y up,
    head frame; the head rolled by ``roll_deg`` as :func:`reading`) from the opening's
    centre; an upper lid (skin, shaded) down to ``closure`` of the opening's height at every
    column (1: on the lower lid), grey ``lid``; a dark lash line ``lash_mm`` thick straddling the opening's
    upper arc; drawn 8x larger and averaged down (edges fall between pixels). ``skin``,
    ``white``: their greys; ``nasal_white``: the white's grey on the nose's side of the
    opening's middle (a shaded sclera), default ``white``."""
    ca, sa = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    off = np.array([ca * iris_mm[0] - sa * iris_mm[1], -(sa * iris_mm[0] + ca * iris_mm[1])])
    k = 8
    img = np.full((400, 640), skin, np.uint8)
    for side in U.SIDES:
        inner, outer = U.EYE_CORNERS[side]
        a = float(np.linalg.norm(lm[outer, :2] - lm[inner, :2])) / 2.0
        ang = math.degrees(math.atan2(*(lm[outer, :2] - lm[inner, :2])[::-1]))
        x0, y0 = np.floor((lm[inner, :2] + lm[outer, :2]) / 2.0 - a - 2).astype(int)
        side_px = int(2 * a + 4)
        mid = (lm[inner, :2] + lm[outer, :2]) / 2.0 - [x0, y0]  # in the eye's tile
        big = np.full((side_px * k, side_px * k), skin, np.uint8)
        o = (k - 1) / 2.0  # small pixel j's centre is big pixel k j + (k - 1) / 2's
        opening = np.zeros_like(big)
        cv2.ellipse(opening, ((mid[0] * k + o, mid[1] * k + o),
                              (2 * a * k, 2 * 0.25 * a * k), ang), 1, -1)
        c = (mid + off * scale) * k + o
        disc = np.zeros_like(big)
        cv2.circle(disc, (int(round(c[0])), int(round(c[1]))),
                   int(round(iris_radius_mm * scale * k)), 1, -1)
        big[opening > 0] = white
        if nasal_white is not None:  # the inner corner's half of the opening
            ys, xs = np.mgrid[0:big.shape[0], 0:big.shape[1]]
            nose = (lm[inner, :2] - lm[outer, :2]) @ np.array(
                [xs.ravel() - mid[0] * k - o, ys.ravel() - mid[1] * k - o]) > 0
            big[(opening > 0) & nose.reshape(big.shape)] = nasal_white
        big[(opening > 0) & (disc > 0)] = 40
        if closure > 0:  # the lid: each point of the opening whose height above the lower
            # lid (in the opening's own frame) is above (1 - closure) x the column's height
            ys, xs = np.nonzero(opening)
            th = math.radians(ang if math.cos(math.radians(ang)) > 0 else ang + 180.0)
            px, py = xs - mid[0] * k - o, ys - mid[1] * k - o
            pu = px * math.cos(th) + py * math.sin(th)
            pv = -px * math.sin(th) + py * math.cos(th)
            half_h = 0.25 * a * k * np.sqrt(np.clip(1 - (pu / (a * k)) ** 2, 0, 1))
            up = (half_h - pv) / np.maximum(2 * half_h, 1e-9)  # 0 lower lid .. 1 top
            shut = up > 1.0 - closure
            big[ys[shut], xs[shut]] = lid
        if lash_mm > 0:  # every point within lash_mm / 2 (across the eye's axis) of the
            # opening's upper arc, between the corners
            ys, xs = np.mgrid[0:big.shape[0], 0:big.shape[1]]
            th = math.radians(ang if math.cos(math.radians(ang)) > 0 else ang + 180.0)
            px, py = xs - mid[0] * k - o, ys - mid[1] * k - o
            pu = px * math.cos(th) + py * math.sin(th)
            pv = -px * math.sin(th) + py * math.cos(th)
            arc = 0.25 * a * k * np.sqrt(np.clip(1 - (pu / (a * k)) ** 2, 0, 1))
            big[(np.abs(pv + arc) < lash_mm * scale * k / 2.0) & (np.abs(pu) < a * k)] = 15
        img[y0:y0 + side_px, x0:x0 + side_px] = cv2.resize(big, (side_px, side_px),
                                                          interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def test_gaze_pitch_although_the_lids_cover_the_iris_top_and_bottom():
    """The iris circle is fitted to its visible edge: moved up by 2 mm inside an opening
    lower than itself (its dark centroid then moves ~0.5 mm), it reads ~10 deg up; the zero is
    the iris centred in the eye's opening, whatever the enrolment's median (``iris_mm``)."""
    ref = U.UpperReference(REF.open_mm, REF.closed_mm, REF.brows_mm, (2.0, -1.0, 2.0, -1.0),
                           iris_radius_mm=(5.5, 5.5))
    for roll in (0.0, 8.0):
        lm = reading(CANON.vertices_mm, 0.0, roll)
        for dx, dy in ((0.0, 0.0), (0.0, 2.0), (0.0, -2.0), (3.0, 1.0), (-2.5, -1.5)):
            f = U.UpperTracker(ref).step(lidded_eye_image(lm, (dx, dy), roll_deg=roll), lm,
                                         None, True)
            assert f.eyes_ok and f.gaze_yaw_deg is not None
            want = [math.degrees(math.asin(v / U.EYE_RADIUS_MM)) for v in (dx, dy)]
            assert f.gaze_yaw_deg == pytest.approx(want[0], abs=1.0), (roll, dx, dy)
            assert f.gaze_pitch_deg == pytest.approx(want[1], abs=1.0), (roll, dx, dy)


def test_gaze_pitch_is_not_pulled_down_by_the_lash_line():
    """A dark lash line 1.6 mm thick straddling the upper lid's margin covers the opening's
    top 0.8 mm: the white alone puts the opening's centre ~0.5 mm low (the pitch 2.4 deg high);
    the opening is taken between the white's and the white-and-lash line's (both
    openings' centres averaged), and the pitch stays within 1 deg of the truth."""
    ref = U.UpperReference(REF.open_mm, REF.closed_mm, REF.brows_mm, (0.0,) * 4,
                           iris_radius_mm=(5.5, 5.5))
    lm = reading(CANON.vertices_mm)
    for dx, dy in ((0.0, 0.0), (0.0, 1.5), (2.0, -1.0)):
        f = U.UpperTracker(ref).step(lidded_eye_image(lm, (dx, dy), lash_mm=1.6), lm, None,
                                     True)
        want = [math.degrees(math.asin(v / U.EYE_RADIUS_MM)) for v in (dx, dy)]
        assert f.gaze_yaw_deg == pytest.approx(want[0], abs=1.0), (dx, dy)
        assert f.gaze_pitch_deg == pytest.approx(want[1], abs=1.0), (dx, dy)


@pytest.mark.parametrize("skin, white, nasal", [
    (150, 156, None),  # a sclera as grey as the skin round it (cap12, cap13's desk light)
    (150, 235, 200),   # a sclera shaded on the nose's side (franck, single_face)
])
def test_gaze_on_a_shaded_sclera(skin, white, nasal):
    """Real scleras are not the rendered eye's uniform white: under a brow, lit from one
    side, the white can be no brighter than the skin round the eye, or darker on one side of
    the iris than on the other. The iris is still fitted (each row's chord bounded by its
    own side's white; the opening from the reader's corners where the pixels cannot tell it
    from the skin) and the gaze read within 1.5 deg (on main: no iris, no gaze, on either
    eye for the grey sclera). An eye fitted only since gives the closure's measures no grey
    levels: the closure stays as calibrated before."""
    ref = U.UpperReference(REF.open_mm, REF.closed_mm, REF.brows_mm, (0.0,) * 4,
                           iris_radius_mm=(5.5, 5.5))
    lm = reading(CANON.vertices_mm)
    for dx, dy in ((0.0, 0.0), (2.5, 0.0), (-2.0, 1.5), (1.0, -2.0)):
        img = lidded_eye_image(lm, (dx, dy), skin=skin, white=white, nasal_white=nasal)
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        fits = [U.fit_iris(grey, lm, s, 5.5 * SCALE) for s in U.SIDES]
        assert all(fit is not None for fit in fits)
        if nasal is None:
            assert all(fit.levels is None for fit in fits)  # type: ignore[union-attr]
        f = U.UpperTracker(ref).step(img, lm, None, True)
        want = [math.degrees(math.asin(v / U.EYE_RADIUS_MM)) for v in (dx, dy)]
        assert f.gaze_yaw_deg == pytest.approx(want[0], abs=1.5), (dx, dy)
        assert f.gaze_pitch_deg == pytest.approx(want[1], abs=1.5), (dx, dy)


def test_iris_chords_end_at_each_sides_own_white():
    """A row's chord ends where the row reaches its own side's white (sub-pixel, by the
    pixels' iris fractions): with the nasal white darker, the chord is as wide as the
    iris (2 r at its equator) and centred on it; a row whose side is only a lid's skin (no
    sclera) is not bounded; a one-pixel glint inside the iris does not end the chord."""
    row = np.array([120, 200, 200, 200, 40, 40, 40, 40, 40, 40, 235, 235, 235, 120],
                   np.float32)
    lid = np.array([120, 130, 130, 130, 40, 40, 40, 40, 40, 40, 235, 235, 235, 120],
                   np.float32)
    glint = row.copy()
    glint[7] = 250
    patch = np.stack([row, glint, lid])
    inside = np.zeros(patch.shape, np.uint8)
    inside[:, 1:-1] = 1
    widths, centres, bounded = U._chords(patch, inside, np.ones_like(inside), 120.0, 40.0,
                                         235.0, 6.5)
    assert list(bounded) == [True, True, False]
    assert widths[:2] == pytest.approx([6.0, 6.0]) and centres[:2] == pytest.approx([6.5, 6.5])


def test_iris_fit_finds_the_radius_and_the_opening():
    lm = reading(CANON.vertices_mm)
    grey = cv2.cvtColor(lidded_eye_image(lm, (1.0, 0.5)), cv2.COLOR_BGR2GRAY)
    for side in U.SIDES:
        fit = U.fit_iris(grey, lm, side)
        assert fit is not None and fit.rows >= U.IRIS_MIN_ROWS
        assert fit.half_width == pytest.approx(5.5 * SCALE, abs=0.5)  # the equator is seen
        inner, outer = U.EYE_CORNERS[side]
        mid = (lm[inner, :2] + lm[outer, :2]) / 2.0
        assert np.abs(fit.eye - mid).max() < 0.3
        assert np.abs(fit.centre - (mid + [1.0 * SCALE, -0.5 * SCALE])).max() < 0.3
    assert U.fit_iris(np.full_like(grey, 150), lm, "left") is None  # no eye: no iris


def test_lid_gap_is_linear_in_the_lids_travel_down_to_shut():
    """The photometric lid gap against an upper lid painted down to 0 .. 1 of the opening:
    a straight line (the reader's lids saturate near closed: docs/UPPER_FACE.md), near 0
    shut, whatever the gaze."""
    lm = reading(CANON.vertices_mm, 0.0, 6.0)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    grey = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), roll_deg=6.0), cv2.COLOR_BGR2GRAY)
    fit = U.fit_iris(grey, lm, "left")
    assert fit is not None
    skin, white, iris = fit.levels
    assert skin == pytest.approx(150, abs=3) and white == pytest.approx(235, abs=3)
    assert iris == pytest.approx(40, abs=3)
    open_px = OPEN * SCALE
    cs = np.linspace(0.0, 1.0, 9)
    for gaze in ((0.0, 0.0), (2.5, -1.5)):
        gaps = np.array([U.lid_gap(cv2.cvtColor(lidded_eye_image(
            lm, gaze, roll_deg=6.0, closure=c), cv2.COLOR_BGR2GRAY), inner, outer, open_px,
            fit.levels) for c in cs])
        slope, icpt = np.polyfit(cs, gaps, 1)
        assert np.abs(gaps - (icpt + slope * cs)).max() < 0.03 * icpt, gaps
        assert gaps[-1] < 0.05 * gaps[0]
    assert U.lid_gap(grey, inner, outer, open_px, (150.0, 152.0, 40.0)) is None  # no white
    assert U.lid_gap(grey, inner - 1000, outer - 1000, open_px, fit.levels) is None


def test_iris_height_sees_a_shut_eye_under_a_lid_as_bright_as_the_white():
    """The visible iris's height against an upper lid painted down to 0 .. 1: a line to 0
    shut, whatever the lid's grey; a lid as bright as the white (a lit lid, a pale face:
    pexels_woman) makes the lid gap read the shut eye open, not the iris's height."""
    lm = reading(CANON.vertices_mm, 0.0, 6.0)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    fit = U.fit_iris(cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), roll_deg=6.0),
                                  cv2.COLOR_BGR2GRAY), lm, "left")
    assert fit is not None
    open_px = OPEN * SCALE
    cs = np.linspace(0.0, 1.0, 9)
    for lid in (130, 225):
        greys = [cv2.cvtColor(lidded_eye_image(lm, (2.5, -1.5), roll_deg=6.0, closure=c,
                                               lid=lid), cv2.COLOR_BGR2GRAY) for c in cs]
        hs = np.array([U.iris_height(g, inner, outer, open_px, fit.levels) for g in greys])
        slope, icpt = np.polyfit(cs, hs, 1)
        assert np.abs(hs - (icpt + slope * cs)).max() < 0.05 * icpt, hs
        assert hs[-1] < 0.05 * hs[0]
        gap = U.lid_gap(greys[-1], inner, outer, open_px, fit.levels)
        assert gap is not None and (gap < 0.1 if lid == 130 else gap > 0.8)
    assert U.iris_height(greys[0], inner, outer, open_px, (150.0, 235.0, 145.0)) is None


def test_calibration_picks_the_iris_height_where_the_lid_gap_fails():
    """Under a lid as bright as the white the lid gap does not follow the reader's lids; the
    iris's height does, is picked at enrolment, and sees the blinks between readings."""
    lm = reading(CANON.vertices_mm)
    cs = np.zeros(60)
    cs[[10, 11, 12, 40, 41]] = [0.5, 1.0, 0.5, 0.8, 1.0]
    lids = (OPEN - 0.8) * cs
    greys = [cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), closure=c, lid=225),
                          cv2.COLOR_BGR2GRAY) for c in cs]
    first = U.calibrate([U.measure(g, reading(with_lids(d)), CANON)
                         for g, d in zip(greys, lids, strict=True)])
    assert first is not None
    ref = U.calibrate([U.measure(g, reading(with_lids(d)), CANON, first.open_mm,
                                 first.iris_radius_mm, (first.eye_levels(0),
                                                        first.eye_levels(1)))
                       for g, d in zip(greys, lids, strict=True)])
    assert ref is not None and ref.photo_kind == ("iris", "iris")
    assert U.UpperReference.from_dict(ref.to_dict(), "x").photo_kind == ("iris", "iris")
    # (the measure against the enrolment's references, not the session's levels:
    # test_closure_levels_learned_through_the_session_keep_the_blink_frames)
    tracker = U.UpperTracker(ref, photometric=True, levels=False)
    got = [tracker.step(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), reading(with_lids(d)), None,
                        True).closure_left for g, d in zip(greys, lids, strict=True)]
    assert np.abs(np.array(got) - cs).max() < 0.1, np.round(got, 2)


def test_calibration_maps_the_usual_open_eye_to_0_and_the_deepest_blinks_to_1():
    lm = reading(CANON.vertices_mm)
    cs = np.zeros(60)
    cs[[10, 11, 12, 40, 41]] = [0.5, 1.0, 0.5, 0.8, 1.0]
    lids = (OPEN - 0.8) * cs  # the reader's lids come down with them
    ms = []
    for c, d in zip(cs, lids, strict=True):
        grey = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), closure=c), cv2.COLOR_BGR2GRAY)
        ms.append(U.measure(grey, reading(with_lids(d)), CANON))
    first = U.calibrate(ms)
    assert first is not None and first.eye_levels(0) is not None
    ms = [U.measure(cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), closure=c),
                                 cv2.COLOR_BGR2GRAY), reading(with_lids(d)), CANON,
                    first.open_mm, first.iris_radius_mm, (first.eye_levels(0),
                                                          first.eye_levels(1)))
          for c, d in zip(cs, lids, strict=True)]
    ref = U.calibrate(ms)
    assert ref is not None and ref.blinks == 2 and min(abs(r) for r in ref.photo_r) > 0.9
    back = U.UpperReference.from_dict(ref.to_dict(), "x")
    assert back.photo == pytest.approx(ref.photo) and back.levels == pytest.approx(ref.levels)
    # (the measure against the enrolment's references, not the session's levels:
    # test_closure_levels_learned_through_the_session_keep_the_blink_frames)
    tracker = U.UpperTracker(ref, levels=False)
    got = [tracker.step(lidded_eye_image(lm, (0.0, 0.0), closure=c), reading(with_lids(d)),
                        None, True).closure_left for c, d in zip(cs, lids, strict=True)]
    assert np.abs(np.array(got) - cs).max() < 0.08, np.round(got, 2)
    assert ref.photo_kind == ("gap", "gap")  # (it follows these lids better than contrast)
    tracker = U.UpperTracker(ref, photometric=True, levels=False)  # the lid gap on every frame
    got = [tracker.step(lidded_eye_image(lm, (0.0, 0.0), closure=c), reading(with_lids(d)),
                        None, True).closure_left for c, d in zip(cs, lids, strict=True)]
    assert np.abs(np.array(got) - cs).max() < 0.08, np.round(got, 2)
    # an older speaker.json (no levels, no kind: its photometric line is the contrast's)
    old = {k: v for k, v in ref.to_dict().items() if k not in ("levels", "photo_kind")}
    assert U.UpperReference.from_dict(old, "x").photo_kind == ("contrast", "contrast")
    with pytest.raises(ModelFileError, match="photo_kind"):
        U.UpperReference.from_dict({**ref.to_dict(), "photo_kind": ["gap", "x"]}, "x")


def brow_image(lm: np.ndarray, height_mm: float, scale: float = SCALE) -> np.ndarray:
    """Skin, the eyes (:func:`lidded_eye_image`), and per eye a brow: a dark band 4 mm thick
    centred ``height_mm`` above the eye's corners' line, 1.3 eye widths long (a frontal,
    upright face)."""
    img = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0)), cv2.COLOR_BGR2GRAY)
    for side in U.SIDES:
        inner, outer = lm[U.EYE_CORNERS[side][0], :2], lm[U.EYE_CORNERS[side][1], :2]
        mid, half = (inner + outer) / 2.0, abs(outer[0] - inner[0]) * 0.65
        y = mid[1] - height_mm * scale
        img[int(round(y)) - int(2 * scale):int(round(y)) + int(2 * scale) + 1,
            int(round(mid[0] - half)):int(round(mid[0] + half))] = 70
    return img


def test_brow_band_from_the_pixels_above_the_eye():
    """The brow is the dark band above the eye, found in the pixels (the landmark network's
    brow points follow its face prior: docs/UPPER_FACE.md); the enrolment window starts above
    the open eye (its lashes and iris are darker than a brow), live one is round the neutral."""
    lm = reading(CANON.vertices_mm)
    al = U.align(lm, CANON)
    assert al is not None
    wide = ((6.0, 20.0),) * 2
    for h in (10.0, 13.0, 16.0):
        for side in U.SIDES:
            band = U.brow_band_mm(brow_image(lm, h), lm, al, side, wide)
            assert band is not None and None not in band
            assert band[0] == pytest.approx(h, abs=0.3) and band[1] == pytest.approx(h, abs=0.3)
    # no brow in the window (e.g. under a fringe): no height, not the window's edge
    flat = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0)), cv2.COLOR_BGR2GRAY)
    assert U.brow_band_mm(flat, lm, al, "left", wide) in (None, (None, None))
    # the tracker: the raise from the enrolment's neutral band, inner and outer
    ref = U.UpperReference(REF.open_mm, REF.closed_mm, REF.brows_mm, REF.iris_mm,
                           brow_band_mm=(12.0, 12.0, 12.0, 12.0), brow_floor_mm=(6.0, 6.0))
    f = U.UpperTracker(ref).step(cv2.cvtColor(brow_image(lm, 15.0), cv2.COLOR_GRAY2BGR), lm,
                                 None, True)
    assert f.brows_ok
    for v in (f.raise_inner_left_mm, f.raise_outer_left_mm, f.raise_inner_right_mm,
              f.raise_outer_right_mm):
        assert v == pytest.approx(3.0, abs=0.3)
    # an outer half not found at enrolment (the synthetic brow's end off the face's mesh):
    # not looked for, and it rises with the inner half
    half = U.UpperReference(REF.open_mm, REF.closed_mm, REF.brows_mm, REF.iris_mm,
                            brow_band_mm=(12.0, 0.0, 12.0, 0.0), brow_floor_mm=(6.0, 6.0))
    assert half.brow_window(0) == ((6.0, 20.0), None)
    g = U.UpperTracker(half).step(cv2.cvtColor(brow_image(lm, 15.0), cv2.COLOR_GRAY2BGR), lm,
                                  None, True)
    assert g.raise_outer_left_mm == pytest.approx(3.0, abs=0.3)
    assert g.raise_outer_right_mm == pytest.approx(g.raise_inner_right_mm)


def test_enrolment_looks_for_the_brow_up_to_above_the_readers_own_brow_points():
    """The enrolment's brow search ends BROW_ABOVE_READER_MM above the reader's brow points
    (the canonical face's: inner 19.5 mm above the eye line), not at a fixed height: a brow
    22 mm up is found (a fixed 20 mm cap missed it), and a darker band further up (hair,
    9 mm above the reader's points) does not take the brow's place."""
    lm = reading(CANON.vertices_mm)
    inner = float(U.brow_heights_mm(CANON.vertices_mm)[0])
    m = U.measure(brow_image(lm, 22.0), lm, CANON)
    assert m is not None
    for band in m.band:
        assert band is not None and band[0] == pytest.approx(22.0, abs=0.4)
    hair = brow_image(lm, 16.0)
    for side in U.SIDES:
        a, b = lm[U.EYE_CORNERS[side][0], :2], lm[U.EYE_CORNERS[side][1], :2]
        y = int(round((a[1] + b[1]) / 2.0 - (inner + 9.0) * SCALE))
        hair[y - 6:y + 7, int(min(a[0], b[0])) - 20:int(max(a[0], b[0])) + 20] = 30
    m = U.measure(hair, lm, CANON)
    assert m is not None
    for band in m.band:
        assert band is not None and band[0] == pytest.approx(16.0, abs=0.4)


def test_photometric_measure_tells_an_open_eye_from_a_closed_one():
    lm = reading(CANON.vertices_mm)
    open_img = cv2.cvtColor(eye_image(lm, (0.0, 0.0)), cv2.COLOR_BGR2GRAY)
    closed_img = np.full_like(open_img, 150)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    m_open = U.photo_measure(open_img, inner, outer, OPEN * SCALE)
    m_closed = U.photo_measure(closed_img, inner, outer, OPEN * SCALE)
    assert m_closed == pytest.approx(0.0, abs=1e-6)
    assert m_open is not None and m_open > 0.05
    assert U.photo_measure(open_img, inner - 1000, outer - 1000, 20.0) is None  # off the image


def test_between_readings_the_calibrated_photometric_measure_sees_a_blink():
    lm = reading(CANON.vertices_mm)
    grey_open = cv2.cvtColor(eye_image(lm, (0.0, 0.0)), cv2.COLOR_BGR2GRAY)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    fit = U.fit_iris(grey_open, lm, "left")
    assert fit is not None
    m_open = U.lid_gap(grey_open, inner, outer, OPEN * SCALE, fit.levels)
    assert m_open is not None
    b = -1.0 / m_open  # closure 0 at the open eye's gap, 1 at none
    ref = U.UpperReference((OPEN, OPEN), (1.0, 1.0), REF.brows_mm, REF.iris_mm,
                           photo=(1.0, b, 1.0, b), photo_r=(-0.9, -0.9),
                           photo_kind=("gap", "gap"))
    tracker = U.UpperTracker(ref)
    first = tracker.step(eye_image(lm, (0.0, 0.0)), lm, np.zeros(2), True)
    assert first.closure_left == pytest.approx(0.0, abs=0.02)
    shut = tracker.step(np.full((400, 640, 3), 150, np.uint8), None, np.zeros(2), True)
    assert shut.source == "photo" and shut.closure_left > 0.9 and shut.closure_right > 0.9
    # a weak calibration is not used: the last reading's closure is held
    weak = U.UpperTracker(U.UpperReference((OPEN, OPEN), (1.0, 1.0), REF.brows_mm, REF.iris_mm,
                                           photo=(1.0, b, 1.0, b), photo_r=(-0.2, -0.2),
                                           photo_kind=("gap", "gap")))
    weak.step(eye_image(lm, (0.0, 0.0)), lm, np.zeros(2), True)
    held = weak.step(np.full((400, 640, 3), 150, np.uint8), None, np.zeros(2), True)
    assert held.closure_left == pytest.approx(0.0, abs=0.02)


def test_between_full_readings_the_readers_lids_of_the_frame_give_its_closure():
    """The live reader reads every frame for the lips; the eyes are measured in full on every
    third. Between, an eye the photometric measure cannot follow (a weak calibration) read
    the last full reading's closure, held: a blink shut on the frames between read open.
    Given the frame's reading as ``lids``, its lids give the closure that frame (cheap: no
    iris fit), the rest (gaze, brows) held; with a usable photometric measure the two are
    averaged as on a full reading."""
    lm = reading(CANON.vertices_mm)
    shut_lm = reading(with_lids(OPEN - 1.0))  # the reader's lids: closure 1
    img = eye_image(lm, (0.0, 0.0))
    weak = U.UpperReference((OPEN, OPEN), (1.0, 1.0), REF.brows_mm, REF.iris_mm,
                            photo=(1.0, -0.1, 1.0, -0.1), photo_r=(-0.2, -0.2),
                            photo_kind=("gap", "gap"))
    tracker = U.UpperTracker(weak)
    first = tracker.step(img, lm, np.zeros(2), True)
    assert first.source == "reader" and first.closure_left == pytest.approx(0.0, abs=0.02)
    held = tracker.step(img, None, np.zeros(2), True)  # no reading at all: held
    assert held.source == "photo" and held.closure_left == pytest.approx(0.0, abs=0.02)
    shut = tracker.step(img, None, np.zeros(2), True, lids=shut_lm)
    assert shut.source == "lids"
    assert shut.closure_left > 0.95 and shut.closure_right > 0.95
    assert shut.gaze_yaw_deg == first.gaze_yaw_deg  # the gaze held from the full reading
    assert shut.raise_inner_left_mm == first.raise_inner_left_mm  # the brows too
    again = tracker.step(img, None, np.zeros(2), True, lids=lm)
    assert again.closure_left == pytest.approx(0.0, abs=0.02)


def test_the_lids_alone_are_read_as_the_full_alignment_reads_them():
    """:func:`lids_only` (compiled where numba is) gives the opening and yaw of
    :func:`align` + :func:`lid_opening_mm`, at any pose and with noise on the points."""
    rng = np.random.default_rng(3)
    for k in range(6):
        lm = reading(with_lids(0.7 * k), yaw_deg=10.0 * k - 25.0, roll_deg=4.0 * k) \
            + rng.normal(0.0, 1.5, (468, 3))
        al = U.align(lm, CANON)
        assert al is not None
        fast, ref = U.lids_only(lm, CANON), U.lids_only_numpy(lm, CANON)
        assert fast is not None and ref is not None
        np.testing.assert_allclose(fast[0], U.lid_opening_mm(al.points), atol=1e-9)
        np.testing.assert_allclose(ref[0], U.lid_opening_mm(al.points), atol=1e-9)
        assert fast[1] == pytest.approx(al.yaw_deg, abs=1e-9)
    assert U.lids_only(np.full((468, 3), np.nan), CANON) is None
    assert U.lids_only(np.zeros((468, 3)), CANON) is None


def test_between_readings_a_lasting_disagreement_with_the_reader_is_carried():
    """A photometric measure blind to a shut lid (pexels_woman's lid as bright as her white)
    reads the eye open while the reader's lids read it shut: on a reading's frame the closure
    is the two's mean; between readings it is not the photometric one alone (a closure that
    jumps at the reader's cadence, a shut eye read as several blinks) but moved by the
    readings' disagreement, the lasting part of it whole, one reading's by half."""
    lm = reading(CANON.vertices_mm)
    shut_lm = reading(with_lids(OPEN - 1.0))  # the reader's lids: closure 1
    img = eye_image(lm, (0.0, 0.0))  # the pixels: an open eye
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    fit = U.fit_iris(grey, lm, "left")
    assert fit is not None
    m_open = U.lid_gap(grey, inner, outer, OPEN * SCALE, fit.levels)
    assert m_open is not None
    b = -1.0 / m_open
    ref = U.UpperReference((OPEN, OPEN), (1.0, 1.0), REF.brows_mm, REF.iris_mm,
                           photo=(1.0, b, 1.0, b), photo_r=(-0.9, -0.9),
                           photo_kind=("gap", "gap"))
    # (the measure against the enrolment's references, not the session's levels:
    # test_closure_levels_learned_through_the_session_keep_the_blink_frames)
    tracker = U.UpperTracker(ref, levels=False)
    tracker.step(img, lm, np.zeros(2), True)  # an open eye: both measures agree
    got = []
    for _ in range(8):  # the reader every other frame, reading the lids shut
        got.append(tracker.step(img, shut_lm, np.zeros(2), True))
        got.append(tracker.step(img, None, np.zeros(2), True))
    assert [f.source for f in got[:2]] == ["reader", "photo"]
    cl = np.array([f.closure_left for f in got])
    assert cl[0] == pytest.approx(0.5, abs=0.05)  # the reading: the two measures' mean
    assert cl[1] == pytest.approx(0.25, abs=0.05)  # after one reading: half its disagreement
    assert np.abs(cl[-6:] - 0.5).max() < 0.05, np.round(cl, 2)  # lasting: no jump
    # the photometric measure alone (``photometric``) keeps its own reading between
    alone = U.UpperTracker(ref, photometric=True, levels=False)
    alone.step(img, shut_lm, np.zeros(2), True)
    assert alone.step(img, None, np.zeros(2), True).closure_left == pytest.approx(0.0, abs=0.05)


def _open_eyes_moving(n: int = 30) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Frames of open eyes as the head moves them by a pixel or so and they look about
    (greys, readings): the changes an open eye shows from frame to frame."""
    lm = reading(CANON.vertices_mm)
    greys, lms = [], []
    for t in range(n):
        shift = np.array([1.5 * math.sin(0.7 * t), 1.0 * math.cos(0.5 * t), 0.0])
        at = lm + shift
        img = lidded_eye_image(at, (0.6 * math.sin(0.3 * t), 0.3 * math.cos(0.4 * t)))
        greys.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        lms.append(at)
    return greys, lms


def test_between_readings_an_eye_it_cannot_follow_is_read_when_it_changes():
    """An eye whose photometric measure did not follow the reader at enrolment (carphone's
    ~10 px eyes: its closure is held between readings) is watched: when its pixels change
    more than the enrolment's open eyes changed between frames (a lid closing), the frame is
    asked to be read; the open eye moved a pixel or two with the head is not."""
    greys, lms = _open_eyes_moving()
    ms = [U.measure(g, lm, CANON) for g, lm in zip(greys, lms, strict=True)]
    limits = U.change_limits(greys, lms, ms, REF)
    assert all(0.0 < x < 0.3 for x in limits), limits
    lm = lms[0]
    shut = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), closure=1.0), cv2.COLOR_BGR2GRAY)
    half_shut = cv2.cvtColor(lidded_eye_image(lm, (0.0, 0.0), closure=0.6),
                             cv2.COLOR_BGR2GRAY)
    inner, outer = lm[U.EYE_CORNERS["left"][0], :2], lm[U.EYE_CORNERS["left"][1], :2]
    tpl = U.eye_template(greys[0], inner, outer, OPEN * SCALE)
    assert tpl is not None
    assert U.eye_change(tpl, shut, inner, outer, OPEN * SCALE) > 3 * limits[0]
    assert U.eye_change(tpl, half_shut, inner, outer, OPEN * SCALE) > limits[0]

    weak = dataclasses.replace(REF, photo_r=(-0.2, -0.2), change_limit=limits)
    tracker = U.UpperTracker(weak)
    assert tracker.watched() == [0, 1]
    tracker.step(cv2.cvtColor(greys[0], cv2.COLOR_GRAY2BGR), lm, np.zeros(2), True)
    moved = lms[1][0, :2] - lm[0, :2]  # where the head's motion puts the eyes next frame
    assert not tracker.wants_reading(greys[1], moved)
    assert tracker.wants_reading(shut, np.zeros(2))
    # one eye changed alone (the head rolling moved one template more): a blink shuts both
    one = greys[0].copy()
    x, y, w, h = cv2.boundingRect(np.round(lm[list(U.EYE_CONTOUR["left"]), :2]).astype(
        np.int32))
    one[y - 5:y + h + 5, x - 5:x + w + 5] = shut[y - 5:y + h + 5, x - 5:x + w + 5]
    assert not tracker.wants_reading(one, np.zeros(2))
    assert dataclasses.replace(tracker, reference=dataclasses.replace(
        weak, photo_r=(-0.2, -0.9))).wants_reading(one, np.zeros(2))  # the left eye alone
    # the eyes a calibrated measure follows, and a speaker.json from before: not watched
    for ref in (dataclasses.replace(weak, photo_r=(-0.9, -0.9)), REF):
        other = U.UpperTracker(ref)
        other.step(cv2.cvtColor(greys[0], cv2.COLOR_GRAY2BGR), lm, np.zeros(2), True)
        assert other.watched() == [] and not other.wants_reading(shut, np.zeros(2))


def test_absent_not_zero():
    img = np.full((400, 640, 3), 128, np.uint8)
    lm = reading(CANON.vertices_mm)
    head = U.UpperTracker(REF, rig="head").step(img, lm, None, True)
    assert not head.eyes_ok and head.eyes_reason.startswith("not_seen")
    assert head.closure_left is None and head.eyes_dict()["closure_left"] is None
    assert not head.brows_ok and head.brows_dict()["raise_left_mm"] is None
    old = U.UpperTracker(None).step(img, lm, None, True)
    assert old.eyes_reason.startswith("not_calibrated")
    lost = U.UpperTracker(REF).step(img, lm, None, False)
    assert lost.eyes_reason.startswith("no_face")
    turned = U.UpperTracker(REF).step(img, reading(CANON.vertices_mm, 60.0), None, True)
    assert turned.eyes_reason.startswith("turned")


def test_calibration_finds_the_open_and_closed_eye_and_counts_blinks():
    img = cv2.cvtColor(np.full((400, 640, 3), 128, np.uint8), cv2.COLOR_BGR2GRAY)
    closing = np.zeros(60)
    closing[[10, 11, 12, 40, 41]] = [3.0, 5.7, 3.0, 5.0, 5.7]
    ms = [U.measure(img, reading(with_lids(c), 10.0), CANON) for c in closing]
    ref = U.calibrate(ms)
    assert ref is not None
    open_canon = U.lid_opening_mm(CANON.vertices_mm)[0]
    assert ref.open_mm[0] == pytest.approx(open_canon, abs=0.01)
    assert ref.closed_mm[0] == pytest.approx(open_canon - 5.7, abs=0.2)
    assert ref.blinks == 2 and ref.frames == 60
    none = U.calibrate([U.measure(img, reading(CANON.vertices_mm), CANON)] * 20)
    assert none is not None and none.blinks == 0
    assert none.closed_mm[0] == pytest.approx(U.CLOSED_FRACTION * open_canon, abs=0.01)
    assert U.calibrate([None] * 30) is None


def test_a_blink_the_reader_reads_shallow_is_the_closed_eye_when_it_lies_far_outside_the_open():
    """A small face (carphone: its reader's lids stop at 0.62 of the open eye at a blink) with
    one blink frame in 72: the 1st percentile lies among the open eyes, and the fixed fraction
    would put the shut eye so deep that its blinks read 0.4; the blink, an outlier of the open
    eye's spread, is the shut reference. A dip the open eye's spread explains is not."""
    img = cv2.cvtColor(np.full((400, 640, 3), 128, np.uint8), cv2.COLOR_BGR2GRAY)
    rng = np.random.default_rng(3)
    open_canon = U.lid_opening_mm(CANON.vertices_mm)[0]
    closing = np.abs(rng.normal(0.0, 0.04 * open_canon, 72))  # the open eye's spread
    closing[40] = 0.38 * open_canon  # the blink, read at 0.62 of the open eye
    ms = [U.measure(img, reading(with_lids(c), 10.0), CANON) for c in closing]
    ref = U.calibrate(ms)
    assert ref is not None and ref.blinks == 1
    opened = ref.open_mm[0]
    assert ref.closed_mm[0] == pytest.approx(U.lid_opening_mm(with_lids(closing[40]))[0],
                                             abs=0.05)
    assert U.closure(ms[40].opening[0], opened, ref.closed_mm[0]) > 0.9  # it reads shut
    # the same dip where the open eye's own spread is wide (a speaker whose eyes roam): held
    # to the fixed fraction, not taken for the shut eye
    wide = np.abs(rng.normal(0.0, 0.12 * open_canon, 72))
    wide[40] = 0.38 * open_canon
    ref_w = U.calibrate([U.measure(img, reading(with_lids(c), 10.0), CANON) for c in wide])
    assert ref_w is not None
    assert ref_w.closed_mm[0] == pytest.approx(U.CLOSED_FRACTION * ref_w.open_mm[0], abs=0.01)


def test_blinks_the_reader_reads_shallow_give_the_shut_eye_from_their_dips():
    """A small face's blinks (lia_obama: the reader's shut eyes at ~0.72 of the open eye)
    among an open eye that roams: the median of the dips' deepest readings is the shut
    eye, so each of its blinks reads nearly shut; dips too shallow to be told from the open
    eye's flutter (0.82) leave the former reference; a long dip (a look down) is not a blink."""
    img = cv2.cvtColor(np.full((400, 640, 3), 128, np.uint8), cv2.COLOR_BGR2GRAY)
    rng = np.random.default_rng(5)
    open_canon = U.lid_opening_mm(CANON.vertices_mm)[0]
    at = [20, 60, 100, 140, 180]

    def ref_for(depth, extra=None):
        closing = np.abs(rng.normal(0.0, 0.06 * open_canon, 220))
        for i in at:
            closing[i:i + 2] = depth * open_canon
        if extra is not None:
            closing[extra] = 0.45 * open_canon
        ms = [U.measure(img, reading(with_lids(c), 10.0), CANON) for c in closing]
        return U.calibrate(ms), ms

    ref, ms = ref_for(0.28)
    assert ref is not None
    shut = U.lid_opening_mm(with_lids(0.28 * open_canon))[0]
    assert ref.closed_mm[0] == pytest.approx(shut, abs=0.1)
    assert min(U.closure(ms[i].opening[0], ref.open_mm[0], ref.closed_mm[0]) for i in at) > 0.9
    assert {a for a, _ in U.blink_dips(np.array([m.opening for m in ms]))} >= set(at)
    shallow, _ = ref_for(0.18)
    assert shallow is not None
    assert shallow.closed_mm[0] < U.DIP_MAX_FRACTION * shallow.open_mm[0] - 0.1
    # a look down of 0.6 s among the blinks is no dip
    _, ms_down = ref_for(0.28, extra=slice(195, 210))
    runs = U.blink_dips(np.array([m.opening for m in ms_down]))
    assert {a for a, _ in runs} >= set(at)
    assert not [(a, b) for a, b in runs if b > 195 and a < 210]


def test_two_dips_are_not_a_median_a_half_blink_does_not_set_the_shut_eye():
    """lia_vox_driving3's enrolment: one blink (the reader's lids at 0.66 of the open eye) and
    one half-closed eye (0.8, the iris seen), both dips. The median of two is their mean, a
    shut eye the open eye's narrowings reach: with fewer than DIP_MIN_COUNT dips the shut eye
    is as without the half blink. With a second blink the median of the three rejects it."""
    img = cv2.cvtColor(np.full((400, 640, 3), 128, np.uint8), cv2.COLOR_BGR2GRAY)
    open_canon = U.lid_opening_mm(CANON.vertices_mm)[0]
    base = np.abs(np.random.default_rng(7).normal(0.0, 0.06 * open_canon, 220))

    def calibrated(dips):
        closing = base.copy()
        for i, depth in dips:
            closing[i:i + 2] = depth * open_canon
        ms = [U.measure(img, reading(with_lids(c), 10.0), CANON) for c in closing]
        return U.calibrate(ms), ms

    blink, half = (150, 0.34), (60, 0.22)
    one, _ = calibrated([blink])
    two, ms = calibrated([blink, half])
    assert one is not None and two is not None
    assert [a for a, _ in U.blink_dips(np.array([m.opening for m in ms]))] == [60, 150]
    mean = (U.lid_opening_mm(with_lids(blink[1] * open_canon))[0]
            + U.lid_opening_mm(with_lids(half[1] * open_canon))[0]) / 2.0
    assert two.closed_mm[0] == pytest.approx(one.closed_mm[0], abs=0.02)
    assert abs(two.closed_mm[0] - mean) > 0.3  # (the former rule's shut eye)
    three, _ = calibrated([blink, half, (100, 0.34)])
    assert three is not None
    assert three.closed_mm[0] == pytest.approx(
        U.lid_opening_mm(with_lids(blink[1] * open_canon))[0], abs=0.1)


def test_reference_round_trip_and_malformed():
    d = REF.to_dict()
    back = U.UpperReference.from_dict(d, "x")
    assert back == REF
    with pytest.raises(ModelFileError, match="upper-face"):
        U.UpperReference.from_dict({**d, "open_mm": [1.0, 1.0]}, "x")  # not above closed
    with pytest.raises(ModelFileError, match="upper-face"):
        U.UpperReference.from_dict({**d, "brows_mm": [1.0]}, "x")
    watched = dataclasses.replace(REF, change_limit=(0.12, 0.2))
    assert U.UpperReference.from_dict(watched.to_dict(), "x") == watched
    with pytest.raises(ModelFileError, match="change_limit"):
        U.UpperReference.from_dict({**d, "change_limit": [-0.1, 0.2]}, "x")
    old = {k: v for k, v in d.items() if k != "change_limit"}  # (before it): never watched
    assert U.UpperReference.from_dict(old, "x").change_limit == (0.0, 0.0)


def test_track_line_carries_eyes_and_brows():
    f = U.UpperTracker(REF).step(np.full((400, 640, 3), 128, np.uint8),
                                 reading(with_lids((OPEN - 1.0) / 2)), None, True)
    r = TrackResult(3, 0.1, np.zeros(2), Pose(), upper=f)
    d = r.to_dict(("a", "b"))
    assert d["eyes"]["ok"] and d["eyes"]["closure_left"] == pytest.approx(0.5, abs=0.02)
    assert set(d["brows"]) >= {"ok", "raise_left_mm", "raise_right_mm", "lowering_mm"}
    back = TrackResult.from_dict(d, ("a", "b"))
    assert back.upper.closure_right == pytest.approx(f.closure_right, abs=1e-3)
    assert "eyes" not in TrackResult(0, 0.0, np.zeros(2), Pose()).to_dict(("a", "b"))


def test_compiled_iris_chords_are_numpys_to_the_bit():
    """kernels.iris_chords and iris_former_rows (the iris fit's chords in one compiled call
    each) give numpy's reference (_chords_numpy, _former_rows_numpy) to the bit: its float32
    arithmetic with the Python floats cast to float32 first, its pairwise sums, the same
    dtypes; on rendered eyes with noise (gazes, rolls, lids half down, a shaded nasal white)
    cropped as fit_iris crops them."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(7)
    n_bounded = 0
    for k, (gaze, roll, closure, nasal) in enumerate(
            [((0.0, 0.0), 0.0, 0.0, None), ((2.5, -1.5), 6.0, 0.3, 200),
             ((-2.0, 1.0), -4.0, 0.5, None), ((1.0, 0.5), 2.0, 0.1, 180)]):
        lm = reading(CANON.vertices_mm, 0.0, roll)
        img = lidded_eye_image(lm, gaze, roll_deg=roll, closure=closure, nasal_white=nasal)
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
        grey = np.clip(grey + rng.normal(0.0, 4.0, grey.shape), 0, 255).astype(np.uint8)
        for side in U.SIDES:
            poly = lm[list(U.EYE_CONTOUR[side]), :2]
            x0, y0 = np.floor(poly.min(0)).astype(int) - 3
            x1, y1 = np.ceil(poly.max(0)).astype(int) + 4
            patch = grey[y0:y1, x0:x1].astype(np.float32)
            contour = np.zeros(patch.shape, np.uint8)
            cv2.fillPoly(contour, [np.round(poly - [x0, y0]).astype(np.int32)], 1)
            grown = cv2.dilate(contour, np.ones((5, 5), np.uint8))
            srt = np.sort(patch[contour > 0])
            thr = float(srt[srt.size // 10] + srt[(9 * srt.size) // 10]) / 2.0
            nd = int(np.searchsorted(srt, thr))
            iris, white = float(srt[nd // 2]), float(srt[nd + (3 * (srt.size - nd)) // 4])
            cx0 = float(patch.shape[1]) / 2.0 + 0.37 * k
            p = cv2.morphologyEx(patch, cv2.MORPH_OPEN, np.ones((1, 3), np.uint8))
            got = kernels.iris_chords(p, contour, grown, thr, iris, white, cx0, U.ROW_WHITE)
            want = U._chords_numpy(p, contour, grown, thr, iris, white, cx0)
            for g, w in zip(got, want, strict=True):
                assert g.dtype == w.dtype
                np.testing.assert_array_equal(g, w)
            n_bounded += int(want[2].sum())
            got2 = kernels.iris_former_rows(patch, grown, iris, white, cx0)
            want2 = U._former_rows_numpy(patch, grown, iris, white, cx0)
            for g, w in zip(got2, want2, strict=True):
                assert g.dtype == w.dtype
                np.testing.assert_array_equal(g, w)
    assert n_bounded >= 20  # chords were measured, not only empty rows


def test_compiled_pairwise_sum_is_numpys_up_to_the_widest_eye_crop():
    """kernels._pairwise_sum adds as numpy's sum does (eight running sums, halves of long
    runs), float32 in float32: the same bits for every length up to IRIS_MAX_WIDTH."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(11)
    lengths = [*range(1, 300), 511, 1000, 1537, 2900, kernels.IRIS_MAX_WIDTH]
    for dtype in (np.float32, np.float64):
        for n in lengths:
            a = (rng.random(n) * rng.choice([1e-3, 1.0, 1e3], n)).astype(dtype)
            assert kernels._pairwise_sum(a, 0, n) == a.sum(), (dtype, n)
    a = rng.random(200).astype(np.float32)
    assert kernels._pairwise_sum(a, 0, 200) != np.float32(sum(a.tolist()))  # not in order


def test_compiled_eye_measures_are_numpys_to_the_bit():
    """kernels.iris_circle_height, opening_centres, dark_height and brow_half (the iris
    circle's height search, the eye opening's centres, the iris height of a lid strip and a
    brow half's darkest band, each in one compiled call) give their numpy references to the
    bit: on noisy smoothed strips (column slices, as the callers pass them), openings of one
    and two stacked fractions, chords of circles with noise; their None cases alike."""
    from articast.core.faces import brows as B
    from articast.core.faces import iris as I
    from articast.core.faces import lids as L
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(5)
    n_found = n_none = 0
    for trial in range(300):
        h, w = int(rng.integers(3, 30)), int(rng.integers(6, 90))
        img = rng.uniform(0, 255, (h, w + 4)).astype(np.float32)
        if trial % 3:
            img = cv2.GaussianBlur(img, (1, 0), sigmaX=0.1, sigmaY=float(rng.uniform(0.5, 3)))
        if trial % 7 == 0:
            img[:] = img[0]  # flat columns: the minimum on the edge
        strip = img[:, 2:2 + w]  # a view, as the callers' slices
        skin, iris = float(rng.uniform(100, 200)), float(rng.uniform(10, 90))
        assert float(kernels.dark_height(strip, skin, iris)) == L._dark_height_numpy(
            strip, skin, iris)
        top, scale = float(rng.uniform(5, 30)), float(rng.uniform(1, 6))
        found, at = kernels.brow_half(strip, top, scale)
        want = B._brow_half_numpy(strip, np.float64(top), scale)
        assert (float(at) if found else None) == want
        n_found += want is not None
        n_none += want is None
        # the eye opening: an ellipse of white with soft edges, one or two stacked
        yy, xx = np.mgrid[0:h, 0:w]
        fr = [np.clip(1.5 - ((xx - rng.uniform(0, w)) / rng.uniform(2, w)) ** 2
                      - ((yy - rng.uniform(0, h)) / rng.uniform(1, h)) ** 2
                      + rng.normal(0, 0.2, (h, w)), 0.0, 1.0).astype(np.float32)
              for _ in range(1 + trial % 2)]
        frac = np.concatenate(fr, axis=0) if len(fr) > 1 else fr[0]
        got = [(float(x), float(y)) if f else None
               for x, y, f in kernels.opening_centres(np.ascontiguousarray(frac), len(fr))]
        assert got == I._opening_centres_numpy(fr[0].shape, frac, len(fr))
        # the iris circle's height: chords of a circle with noise
        r = float(rng.uniform(1.5, 12))
        ys = np.flatnonzero(rng.random(h + 10) < 0.7).astype(np.float64)
        if ys.size < 3:
            continue
        c0 = float(rng.uniform(ys[0], ys[-1]))
        wk = (2 * np.sqrt(np.clip(r * r - (ys - c0) ** 2, 0, None))
              + rng.normal(0, 0.5, ys.size)).astype(np.float32)
        for cys in (np.arange(ys[0] - r, ys[-1] + r, 0.5), c0 + I._FINE):
            assert float(kernels.iris_circle_height(ys, wk, r, cys)) == I._circle_height(
                ys, wk, r, cys)
    assert n_found > 50 and n_none > 20  # both outcomes were compared


def test_closure_levels_learned_through_the_session_keep_the_blink_frames():
    """Issue 38: the reader reads a shut eye shallow (closure 0.6-0.8 from the enrolment's
    references) and a lowered lid on an open eye at 0.2-0.3. Against the session's own
    levels (:class:`ClosureLevels`) the first blink reads shut by the prior, later ones by the
    median of the session's blinks, an open eye held lowered reads open after a second; no
    frame crosses 0.5 that did not before (the blinks found are the same)."""
    img = np.full((400, 640, 3), 128, np.uint8)  # no pixels to follow: the reader's lids alone
    travel = OPEN - 1.0

    def frames(c: float, n: int = 1) -> list[np.ndarray]:
        return [reading(with_lids(c * travel))] * n

    seq = (frames(0.0, 30) + frames(0.4) + frames(0.75, 2) + frames(0.4)  # a first blink
           + frames(0.0, 20) + frames(0.7, 2) + frames(0.0, 20) + frames(0.7, 2)
           + frames(0.0, 20) + frames(0.68, 2) + frames(0.0, 5)
           + frames(0.25, 40)  # lids lowered on an open eye (a look down)
           + frames(0.9, 2) + frames(0.25, 5))  # a blink from it
    levelled, measured = U.UpperTracker(REF), U.UpperTracker(REF, levels=False)
    got = np.array([levelled.step(img, lm, None, True).closure_left for lm in seq])
    raw = np.array([measured.step(img, lm, None, True).closure_left for lm in seq])
    assert raw[31:33].max() == pytest.approx(0.75, abs=0.02)  # as the enrolment reads it
    assert got[31:33].max() >= 0.9  # the first blink, by the prior
    assert raw[98:100].max() < 0.7 and got[98:100].max() >= 0.85  # by the session's blinks
    assert raw[140] == pytest.approx(0.25, abs=0.02) and got[140] <= 0.15  # open, lowered
    assert got[145:147].max() >= 0.9  # a blink from the lowered lid still reads shut
    assert got[:30].max() == pytest.approx(0.0, abs=0.01)
    np.testing.assert_array_equal(got > 0.5, raw > 0.5)  # the same blink frames
    # the shut level is bounded: shallow events (a squint over 0.5) do not stretch it
    lv = U.ClosureLevels()
    for _ in range(5):
        for c in (0.0,) * 10 + (0.55,) * 3:
            lv.read(c)
    assert lv.levels()[1] == pytest.approx(U.SHUT_LEVEL_MIN)
    assert lv.read(0.55) < 0.7
    # the open level too: a long look down at 0.45 is not the open eye beyond OPEN_LEVEL_MAX
    for _ in range(100):
        lv.read(0.45)
    assert lv.levels()[0] == pytest.approx(U.OPEN_LEVEL_MAX)


def test_the_photometric_measure_is_chosen_by_the_blinks_not_by_the_slow_lowerings():
    """The reader reads a narrowed eye (a look down, a laugh's squint) as it reads a closing
    one. A measure that follows those slow lowerings but not the lid over the eye (a lit lid
    as bright as the white: pexels_woman's left lid gap) correlates with the reader's closure
    over the whole clip better than one that sees the blinks; over the series' fast parts
    (:func:`fast_part`), the blinks, it does not, and the measure that sees them is kept."""
    img = cv2.cvtColor(np.full((400, 640, 3), 128, np.uint8), cv2.COLOR_BGR2GRAY)
    rng = np.random.default_rng(11)
    open_canon = U.lid_opening_mm(CANON.vertices_mm)[0]
    n = 300
    blink = np.zeros(n)
    for i in (20, 60, 140, 180, 220, 270):
        blink[i:i + 2] = 1.0
    slow = np.zeros(n)
    slow[80:125] = 1.0  # a long look down (~1.8 s at 25 fps)
    slow[230:260] = 0.7  # a laugh's squint
    closing = (0.4 * blink + 0.3 * slow + np.abs(rng.normal(0.0, 0.01, n))) * open_canon
    gap = 1.2 - 0.5 * slow + rng.normal(0.0, 0.02, n)  # blind to the lid, sees the slow
    iris = 1.0 - 0.6 * blink + rng.normal(0.0, 0.02, n)  # sees the lid, not the slow
    ms = [dataclasses.replace(U.measure(img, reading(with_lids(c), 10.0), CANON),
                              photo=(g, g), iris_h=(h, h), contrast=(None, None))
          for c, g, h in zip(closing, gap, iris, strict=True)]
    cl = np.array([m.opening[0] for m in ms])
    # over the whole series the gap follows the reader's opening better (the former choice)
    assert abs(np.corrcoef(gap, cl)[0, 1]) > abs(np.corrcoef(iris, cl)[0, 1]) + 0.05
    ref = U.calibrate(ms)
    assert ref is not None and ref.photo_kind == ("iris", "iris")
    assert abs(ref.photo_r[0]) >= U.PHOTO_MIN_R
    # and it reads the blinks shut: 1 at the deepest
    a, b = ref.photo[0], ref.photo[1]
    assert a + b * (1.0 - 0.6) > 0.8
    # fast_part: the series less its running median (NaN kept)
    x = np.array([1.0, 1.0, np.nan, 1.0, 0.0, 1.0, 1.0])
    fx = U.fast_part(x, 2)
    assert np.isnan(fx[2]) and fx[4] == pytest.approx(-1.0) and fx[0] == pytest.approx(0.0)


def test_the_eye_strips_length_is_numpys_norm_to_the_bit():
    """lids.norm2 (the eye strip's and the brow band's axis length in Python floats) is
    np.linalg.norm's number, not x * x + y * y's (which rounds otherwise on ~8 % of vectors)."""
    from articast.core.faces import lids as L

    rng = np.random.default_rng(3)
    vs = rng.normal(size=(20000, 2)) * rng.choice([0.1, 1.0, 30.0, 700.0], size=(20000, 1))
    got = [L.norm2(float(x), float(y)) for x, y in vs]
    assert got == [float(np.linalg.norm(v)) for v in vs]


def test_compiled_iris_fit_is_the_step_by_step_fit_to_the_bit():
    """faces.kernels.iris_fit (fit_iris after its crop in one compiled call) gives the step
    by step fit (iris._fit_steps: numpy's sort, partition and pairwise sums, the compiled
    chords) to the bit: the circle's centre, the half width, the opening's centre, the rows,
    the grey levels or their absence; on rendered eyes with noise (gazes, rolls, lids down
    to shut, a shaded nasal white, a sclera as grey as the skin), with and without the
    speaker's radius; and None where it is None."""
    from articast.core.faces import iris as I
    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")

    def steps(grey, lm, side, radius):
        FK.AVAILABLE = False
        try:
            return I.fit_iris(grey, lm, side, radius)
        finally:
            FK.AVAILABLE = True

    def bits(f):
        return None if f is None else (
            f.centre.tobytes(), float(f.half_width).hex(), f.eye.tobytes(), f.rows,
            None if f.levels is None else tuple(float(v).hex() for v in f.levels))

    rng = np.random.default_rng(5)
    fitted = levels = nones = 0
    for k, (gaze, roll, closure, skin, white, nasal) in enumerate(
            [((0.0, 0.0), 0.0, 0.0, 150, 235, None), ((2.5, -1.5), 6.0, 0.3, 150, 235, 200),
             ((-2.0, 1.0), -4.0, 0.5, 150, 235, None), ((1.0, 0.5), 2.0, 0.1, 150, 235, 180),
             ((0.5, -1.0), 0.0, 0.0, 150, 156, None), ((0.0, 0.0), 0.0, 1.0, 150, 235, None)]):
        lm = reading(CANON.vertices_mm, 0.0, roll)
        img = lidded_eye_image(lm, gaze, roll_deg=roll, closure=closure, skin=skin,
                               white=white, nasal_white=nasal)
        for noise in (0.0, 4.0, 12.0):
            grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
            grey = np.clip(grey + rng.normal(0.0, noise, grey.shape), 0, 255).astype(np.uint8)
            for side in U.SIDES:
                for radius in (None, 5.5 * SCALE, 4.0 * SCALE):
                    got = U.fit_iris(grey, lm, side, radius)
                    assert bits(got) == bits(steps(grey, lm, side, radius)), (k, noise, side)
                    fitted += got is not None
                    levels += got is not None and got.levels is not None
                    nones += got is None
    assert fitted >= 40 and levels >= 20 and nones >= 3  # every branch was compared


def test_the_iris_kernels_contour_mask_is_opencvs_fill_poly():
    """faces.kernels._contour (the reader's eye contour's mask made in the compiled iris
    fit) is cv2.fillPoly of the contour less the crop's corner, rounded as numpy rounds, to
    the bit: eye-like rings with jittered points and random polygons of 3-20 points (self-
    crossing, with flat and vertical edges, repeated points), every point inside the mask."""
    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(12)
    for k in range(3000):
        h, w = (int(v) for v in rng.integers(8, 40, 2))
        n = int(rng.integers(3, 21))
        x0, y0 = (int(v) for v in rng.integers(0, 500, 2))
        if k % 3 == 0:  # a ring like an eye's contour
            t = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
            r = rng.uniform(0.3, 0.5)
            pts = np.stack([w / 2 + r * w * np.cos(t), h / 2 + 0.5 * r * h * np.sin(t)], 1)
            pts += rng.normal(0.0, 1.0, pts.shape)
        elif k % 3 == 1:  # anywhere, on whole and half pixels (ties rounded to even)
            pts = rng.integers(0, 2 * min(h, w) - 1, (n, 2)) / 2.0
        else:
            pts = rng.uniform(0.0, 1.0, (n, 2)) * (w - 1, h - 1)
        pts = np.clip(pts, 0.0, (w - 1.5, h - 1.5)) + (x0, y0)
        want = np.zeros((h, w), np.uint8)
        cv2.fillPoly(want, [np.round(pts - [x0, y0]).astype(np.int32)], 1)
        assert np.array_equal(FK._contour(pts, x0, y0, h, w), want), k


def test_the_iris_kernels_growth_and_opening_are_opencvs():
    """faces.kernels._grown and _opened (the contour's growth and the glints' opening made in
    the compiled iris fit) are cv2.dilate with iris._GROW and cv2.morphologyEx's opening with
    iris._GLINT to the bit: random masks and grey levels of every size from one pixel, the
    crop's edges included."""
    from articast.core.faces import iris as I
    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(11)
    for _ in range(800):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        mask = (rng.random((h, w)) < rng.random()).astype(np.uint8)
        assert np.array_equal(FK._grown(mask), cv2.dilate(mask, I._GROW)), (h, w)
        patch = rng.integers(0, 256, (h, w)).astype(np.float32)
        assert np.array_equal(FK._opened(patch),
                              cv2.morphologyEx(patch, cv2.MORPH_OPEN, I._GLINT)), (h, w)


def test_the_compile_notice_counts_the_iris_kernel(tmp_path):
    """The iris fit's own cache check, which the service's compile notice now counts
    (``kernels_on_disk``): an empty cache (a fresh process, NUMBA_CACHE_DIR empty, nothing
    compiled, only imported) holds neither it nor the tracker's kernels, and the service
    would say it compiles; once warmed, this process's cache holds the iris fit (a check
    reading the wrong numba attribute answers True, or False after the warm-up)."""
    import os
    import subprocess
    import sys

    from articast.core.faces import kernels as FK

    if not FK.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    code = ("from articast.core.faces import kernels as FK\n"
            "from articast.service.processors import kernels_on_disk\n"
            "print(FK.compiled_on_disk(), kernels_on_disk(('cauchy',)), kernels_on_disk())\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False", "False"]
    FK.warm_up()
    assert FK.compiled_on_disk()

"""The reader's own lip gap as the streamed lips' measurement (issue 38).

Fitted through the speaker's model, a reading's ~300 points weigh the lips' few little: on
faces the enrolment never saw, the fused live estimate read the lip aperture worse than the
reader it reads with (against the networks of other families: r 0.74-0.84 where the FaceMesh
v1 loop read 0.92-0.97, seven clips of seven new people), and a frame or two late. The
reader's inner-lip gap over its mouth width is the one image measure of the opening every
landmark network shares; here it becomes a measurement of the streamed articulation:

    ratio(points) = ((lower - upper) . n) / |left - right|

with ``n`` the unit normal of the corner line (the benchmark's measure, ``benchmarks/peers.py``
``aperture_ratio``), read on the reader's landmarks 13, 14, 61, 291 and on the speaker's model
at the corresponding points (inner midpoints 2.2, 2.3; outer corners 8.4, 8.3, which the model
was built from), projected at the frame's pose. The streamed articulation is moved by the
smallest step (in the model's s.d. units, the speaker's own prior metric) that makes the
model's projected ratio equal the reader's: the other six directions of the articulation and
the pose stay the fused estimate's, the opening is the reader's, frame by frame, with no
filter between (no lag added to the reader's).

Pure functions over numpy arrays; :class:`~articast.core.faces.live.LiveTracker` applies them.
"""

from __future__ import annotations

import math
import weakref

import cv2
import numpy as np

from articast.core.model.camera import Camera, Pose
from articast.core.model.face import FaceModel

READER_POINTS = (13, 14, 61, 291)
"""MediaPipe topology (FaceMesh v1 and FaceLandmarker v2 alike): inner upper and lower lip
midpoints, then the outer corners (the subject's right, then left)."""
MODEL_POINTS = ("2.2", "2.3", "8.4", "8.3")
"""The model's MPEG-4 points the scheme builds from those four landmarks, in the same order."""
WIDTH_POINTS = ("2.5", "2.4")
"""The inner lip corners: the streamed mouth width (``lips.width_mm``) is theirs."""
LIP_BOX_POINTS = (61, 291, 0, 17)
"""MediaPipe topology: the outer lip corners and midpoints, whose box places the mouth's
patch (:func:`lip_box`; ``benchmarks/peers.py``'s lip box)."""
PATCH_SIZE = (64, 32)
"""The (width, height) px of :func:`mouth_patch`."""
STILL_MIN_GAIN = 0.05
"""The least share of a frame's change that :func:`still_gain` lets through (the fit's
opening is never frozen: a bias between it and the reading still settles, in ~20 frames)."""


PROBE_STEP = 1e-3
"""The central differences' step of :func:`matched` (s.d.)."""
MAX_CHANGE = 3.0
"""The longest step :func:`matched` takes (s.d.)."""
TOLERANCE = 1e-4
""":func:`matched` stops where the ratio is this close to its target."""


def gap_ratio(points: np.ndarray) -> np.ndarray:
    """(...,) inner-lip gap over mouth width of (..., 4, 2) image points (upper, lower, right
    corner, left corner): the gap projected on the normal of the corner line. NaN where the
    corners coincide."""
    p = np.asarray(points, np.float64)
    up, low, right, left = p[..., 0, :], p[..., 1, :], p[..., 2, :], p[..., 3, :]
    across = left - right
    width = np.linalg.norm(across, axis=-1)
    down = np.stack([-across[..., 1], across[..., 0]], -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sum((low - up) * down, -1) / (width * width)


def reader_ratio(landmarks: np.ndarray) -> float:
    """The reader's ratio from its (L, 2+) landmarks in pixels (NaN if not finite)."""
    if len(landmarks) <= max(READER_POINTS):
        return float("nan")
    # (four points: :func:`gap_ratio` in floats, a tenth of its numpy calls' overhead)
    (ux, uy), (lx, ly), (rx, ry), (fx, fy) = (
        (float(landmarks[i][0]), float(landmarks[i][1])) for i in READER_POINTS)
    ax, ay = fx - rx, fy - ry
    w2 = ax * ax + ay * ay
    ratio = ((lx - ux) * -ay + (ly - uy) * ax) / w2 if w2 > 0.0 else float("nan")
    return ratio if math.isfinite(ratio) else float("nan")


_POINTS_OF: weakref.WeakKeyDictionary[FaceModel, tuple[np.ndarray, np.ndarray]] = (
    weakref.WeakKeyDictionary())


def lip_points(model: FaceModel) -> tuple[np.ndarray, np.ndarray]:
    """The four points and the two inner corners: their mean (6, 3) and basis (K, 18), taken
    once per model."""
    got = _POINTS_OF.get(model)
    if got is None:
        idx = [model.point(label) for label in (*MODEL_POINTS, *WIDTH_POINTS)]
        got = (model.mean[idx], model.basis[:, idx, :].reshape(model.n_params, -1))
        _POINTS_OF[model] = got
    return got


def model_measures(model: FaceModel, camera: Camera, alphas: np.ndarray, pose: Pose
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the model's ratio at each of ``alphas`` (N, K), projected at ``pose``, and (N,)
    its mouth width in mm (the inner corners' distance: the streamed ``lips.width_mm``)."""
    mean, basis = lip_points(model)
    a = np.atleast_2d(np.asarray(alphas, np.float64))
    pts = (a @ basis).reshape(len(a), 6, 3) + mean
    if not camera.pinhole:
        uv = camera.project_head(pts[:, :4].reshape(-1, 3), pose).reshape(len(a), 4, 2)
    else:  # (the pinhole inline: this runs on every frame, twice, Camera.project's checks
        # and Jacobian plumbing cost more than the sums; behind the camera gives NaN alike)
        cam_pts = pts[:, :4] @ pose.matrix.T + pose.translation
        z = cam_pts[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = np.where(z > 1e-6, 1.0 / z, np.nan)
        uv = np.empty((len(a), 4, 2))
        uv[..., 0] = camera.fx * cam_pts[..., 0] * iz + camera.cx
        uv[..., 1] = camera.fy * cam_pts[..., 1] * iz + camera.cy
    d = pts[:, 5] - pts[:, 4]
    return gap_ratio(uv), np.sqrt((d * d).sum(-1))


def model_ratios(model: FaceModel, camera: Camera, alphas: np.ndarray, pose: Pose
                 ) -> np.ndarray:
    """(N,) the model's ratio at each of ``alphas`` (N, K), projected at ``pose``."""
    return model_measures(model, camera, alphas, pose)[0]


def _solve2(gram: np.ndarray, r0: float, r1: float) -> np.ndarray | None:
    """The solution of the symmetric positive semi-definite 2 x 2 system ``gram`` x = (r0,
    r1), or None where its condition number is 1e8 or more (closed forms: numpy's ``cond``
    and ``solve`` cost more on a 2 x 2 than the step they serve)."""
    a, b, d = float(gram[0, 0]), float(gram[0, 1]), float(gram[1, 1])
    half = 0.5 * (a + d)
    disc = math.sqrt(max(0.25 * (a - d) ** 2 + b * b, 0.0))
    low, high = half - disc, half + disc
    if not (low > 0.0 and high < 1e8 * low):
        return None
    det = a * d - b * b
    return np.array([(d * r0 - b * r1) / det, (a * r1 - b * r0) / det])


def matched(model: FaceModel, camera: Camera, alpha: np.ndarray, pose: Pose, target: float,
            iterations: int = 2, step: float = PROBE_STEP, max_change: float = MAX_CHANGE,
            tolerance: float = TOLERANCE) -> np.ndarray:
    """``alpha`` moved by the smallest step (Euclidean, in the model's s.d. units) after which
    the model's projected ratio is ``target`` and its mouth width what it was (the reading
    tells the opening, not the width: a step along the ratio's gradient alone moved the
    rendered speaker's width error from 4.56 to 4.95 mm) (Gauss-Newton on the linearised
    constraints,
    the gradient by central differences: the ratio is a smooth function of 7 numbers; each
    iteration is one batched projection, whose first row is the ratio where it stands). The
    step is at most ``max_change`` s.d. long (a reading that asks for more than the speaker's
    articulation holds is followed that far). An iteration stops the search where the ratio
    is within ``tolerance`` of the target (nearly linear in the articulation: the live
    tracker's one iteration leaves ~1e-5 of a frame-to-frame change). ``alpha`` unchanged
    when ``target`` is not finite or the ratio does not move with the articulation."""
    a = np.asarray(alpha, np.float64).copy()
    if not np.isfinite(target):
        return a
    k = len(a)
    probes = np.concatenate([np.zeros((1, k)), np.eye(k) * step, -np.eye(k) * step])
    width = None
    for _ in range(iterations):
        rs, ws = model_measures(model, camera, a + probes, pose)
        if not np.all(np.isfinite(rs)):
            return np.asarray(alpha, np.float64).copy()
        width = ws[0] if width is None else width
        if abs(target - rs[0]) <= tolerance:
            break
        grad = (rs[1:k + 1] - rs[k + 1:]) / (2 * step)
        g2 = float(grad @ grad)
        if g2 <= 1e-18:
            break
        jac = np.stack([grad, (ws[1:k + 1] - ws[k + 1:]) / (2 * step)])
        gram = jac @ jac.T
        both = _solve2(gram, target - float(rs[0]), float(width - ws[0]))
        if both is not None:  # both: the smallest step that keeps the width
            a = a + jac.T @ both
        else:  # (the width moves with the opening alone: the ratio's step)
            a = a + grad * (target - rs[0]) / g2
    change = a - alpha
    norm = float(np.linalg.norm(change))
    if norm > max_change:
        a = alpha + change * (max_change / norm)
    return a


def lip_box(landmarks: np.ndarray) -> np.ndarray:
    """(4,) the image box (x0, y0, x1, y1 px) of a reading's outer lips (its (L, 2+)
    landmarks, :data:`LIP_BOX_POINTS`); NaN where not read."""
    if len(landmarks) <= max(LIP_BOX_POINTS):
        return np.full(4, np.nan)
    # (four points: their bounds in Python floats, numpy's where all are finite)
    xs = [float(landmarks[i][0]) for i in LIP_BOX_POINTS]
    ys = [float(landmarks[i][1]) for i in LIP_BOX_POINTS]
    if all(map(math.isfinite, xs + ys)):
        return np.array([min(xs), min(ys), max(xs), max(ys)])
    pts = np.asarray(landmarks)[list(LIP_BOX_POINTS), :2].astype(np.float64)
    return np.concatenate([pts.min(0), pts.max(0)])


def mouth_patch(image: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(32, 64) grey patch of ``image`` (BGR or grey, uint8) around a lip ``box``, grown 30 %
    (the still-mouth windows' patch of ``benchmarks/face_landmarks_clips.py``)."""
    # (an array's values as Python floats at once: ~5 us a call less in the live loop than
    # float() of each of its numpy scalars; the same values)
    x0, y0, x1, y1 = map(float, box.tolist() if isinstance(box, np.ndarray) else box)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    hx, hy = (x1 - x0) * 0.65 + 2, (y1 - y0) * 0.65 + 2
    w, h = PATCH_SIZE
    sx, sy = w / (2 * hx), h / (2 * hy)  # (the box's corners onto the patch's: an axis-
    # aligned scale and shift, getAffineTransform's own result written out)
    to = np.array([[sx, 0.0, -sx * (cx - hx)], [0.0, sy, -sy * (cy - hy)]])
    patch = cv2.warpAffine(image, to, PATCH_SIZE)
    return cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY) if patch.ndim == 3 else patch


def patch_change(patch: np.ndarray, before: np.ndarray) -> float:
    """The mean absolute difference of two patches of :func:`mouth_patch` (grey levels)."""
    return float(cv2.mean(cv2.absdiff(patch, before))[0])


def still_gain(change: float, scale: float, least: float = STILL_MIN_GAIN) -> float:
    """The share of a frame's change in the fit's opening let through where the mouth's
    pixels changed by ``change`` (mean absolute grey level, the same box in both frames):
    ``change`` / ``scale``, between ``least`` and 1; 1 where the change is not known."""
    if not math.isfinite(change):
        return 1.0
    return min(1.0, max(least, change / scale))

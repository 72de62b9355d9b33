"""Enrolment of a real speaker from landmarks: a posture corpus without beads (METHOD.md §1).

A webcam clip of the speaker reading aloud gives, per frame, a face landmark set (image px,
with a relative depth in the same px scale: MediaPipe's convention). Enrolment turns it into
the same kind of speaker model a bead lab gives:

1. **Pose removal** — each frame's landmarks, read as a weak-perspective 3D shape in camera
   axes, are aligned to a common reference by a similarity (rotation, translation, scale)
   estimated on the *stable* points only (nose, eye corners, forehead: what speech does not
   move), iterated to a generalised Procrustes mean. Frames whose stable points do not fit the
   reference (a blink of the landmarker, a hand) are rejected, with the reason.
2. **Units** — the reference is scaled to millimetres from a stated assumption: the
   inter-pupillary distance (``ipd_mm``, adult mean 63 mm) when the eyes are seen, else the
   mouth width at the median posture (``mouth_width_mm``, 50 mm). The head frame is the
   model's (x speaker's left, y up, z out of the face), with its origin between the inner lip
   corners, ``teeth_depth_mm`` behind the lips: near the upper incisors on the bite plane.
3. **Guided PCA** on the aligned frames (:func:`articast.core.model.build.build_model`) with
   the point groups of the landmark scheme, giving jaw1, lips1, lips2, lips3, lips4, jaw2 with
   the paper's meanings. **lar1** (larynx height) is not observable by a camera that sees
   landmarks of the face only (no point on the throat): its basis is zero, so it stays 0 in
   every frame and every output; the six others keep their meaning.

Everything here is pure: arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from articast.core.errors import InputError
from articast.core.model.build import Corpus, VarianceTable, build_model, invert
from articast.core.model.camera import Camera, Pose, axis_angle, rotation_matrix
from articast.core.model.face import PARAM_NAMES, FaceModel, ParamStats

OBSERVABLE = PARAM_NAMES[:6]
"""Parameters a face-landmark enrolment can determine; lar1 (throat) is not among them."""

# camera axes (x right, y down, z away) -> head axes (x speaker's left, y up, z out of face)
_TO_HEAD = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True, eq=False)
class LandmarkScheme:
    """How a landmark set becomes a speaker model.

    points : (N,) int landmark indices kept as model points (model point i = landmark
        ``points[i]``).
    groups : point group name -> model point indices (``POINT_GROUPS`` of the face model).
    stable : model point indices that speech does not move (pose removal).
    feature_points : MPEG-4 label -> model point index.
    eyes : (left, right) landmark indices of the pupils, or None (no scale from the IPD).
    mouth_corners : (left, right) model point indices of the outer lip corners.
    lip_inner_corners : (left, right) model point indices of the inner lip corners.
    triangles : (T, 3) model point indices, counter-clockwise seen from the front.
    fapu_overrides : MPEG-4 units the points cannot measure (e.g. ES0 without eyes), mm.
    """

    name: str
    n_landmarks: int
    points: np.ndarray
    groups: Mapping[str, np.ndarray]
    stable: np.ndarray
    feature_points: Mapping[str, int]
    mouth_corners: tuple[int, int]
    lip_inner_corners: tuple[int, int]
    triangles: np.ndarray
    eyes: tuple[int, int] | None = None
    point_names: tuple[str, ...] = ()
    fapu_overrides: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class EnrolOptions:
    """Assumptions and thresholds of an enrolment (all stated in its report).

    ipd_mm : inter-pupillary distance used for scale when the eyes are seen.
    mouth_width_mm : outer mouth width at the median posture, for scale without eyes.
    teeth_depth_mm : depth of the head-frame origin behind the inner lip corners.
    outlier_mad : a frame whose stable-point misfit exceeds the median by this many MADs
        (and 2 % of the reference size) is rejected.
    iterations : generalised Procrustes iterations.
    fixed_pose : one head pose for the whole clip (a head-mounted camera), see :func:`align`.
    """

    ipd_mm: float = 63.0
    mouth_width_mm: float = 50.0
    teeth_depth_mm: float = 10.0
    outlier_mad: float = 6.0
    iterations: int = 4
    use_eyes: bool = True
    fixed_pose: bool = False


@dataclass(frozen=True, eq=False)
class Enrolment:
    """The geometric result of an enrolment.

    model : the speaker's FaceModel (mm, head frame), lar1 with a zero basis.
    table : variance explained per parameter (% of the corpus variance).
    frames : (F,) indices of the frames kept (into the input sequence).
    alpha : (F, K) landmark-inverted articulation of the kept frames.
    shapes : (F, N, 3) mm head frame, the aligned landmark shapes of the kept frames.
    rejected : frame index -> reason, for every frame not kept.
    mm_per_unit : scale of the landmark px at the reference; scale_source : how it was set.
    """

    model: FaceModel
    table: VarianceTable
    frames: np.ndarray
    alpha: np.ndarray
    shapes: np.ndarray
    rejected: dict[int, str] = field(default_factory=dict)
    mm_per_unit: float = 1.0
    scale_source: str = ""


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991).

    src, dst : (M, 3). Returns s, R (3, 3) proper rotation, t (3,).
    """
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sv, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    corr = np.diag([1.0, 1.0, d])
    rot = u @ corr @ vt
    var = float((a**2).sum())
    s = float((sv * np.diag(corr)).sum() / var) if var > 0 else 1.0
    return s, rot, mu_d - s * rot @ mu_s


def to_head_axes(landmarks: np.ndarray) -> np.ndarray:
    """Landmarks (..., L, 3) image px + relative depth -> weak-perspective shapes in head axes."""
    return np.asarray(landmarks, np.float64) @ _TO_HEAD


def align(shapes: np.ndarray, stable: np.ndarray, iterations: int = 4, fixed: bool = False
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generalised Procrustes alignment on the stable points.

    shapes : (F, N, 3) in head axes. Returns aligned (F, N, 3) in the reference's units, the
    reference (N, 3), and the per-frame RMS misfit of the stable points (F,) in those units.
    fixed : the camera does not move on the head (a head-mounted camera): one similarity for
        every frame, from the median shape, instead of one per frame — a per-frame fit on the
        few stable points a head-mounted camera sees (the nose) turns landmark noise into
        rotations that the lips' lever arm amplifies.
    """
    if fixed:
        ref = np.median(shapes, axis=0)
        aligned = shapes
        misfit = np.sqrt(((aligned[:, stable] - ref[stable]) ** 2).sum(-1).mean(-1))
        return aligned, ref, misfit
    ref = shapes[len(shapes) // 2]
    aligned = shapes
    for _ in range(max(1, iterations)):
        out = np.empty_like(shapes)
        for f, x in enumerate(shapes):
            s, r, t = similarity(x[stable], ref[stable])
            out[f] = s * x @ r.T + t
        aligned = out
        new = np.median(aligned, axis=0)
        # keep the reference's size and place: the Procrustes mean shrinks otherwise
        s, r, t = similarity(new[stable], ref[stable])
        ref = s * new @ r.T + t
    misfit = np.sqrt(((aligned[:, stable] - ref[stable]) ** 2).sum(-1).mean(-1))
    return aligned, ref, misfit


def _reject_outliers(misfit: np.ndarray, size: float, mad_factor: float) -> np.ndarray:
    med = float(np.median(misfit))
    mad = float(np.median(np.abs(misfit - med))) + 1e-12
    return misfit <= max(med + mad_factor * 1.4826 * mad, med + 0.02 * size)


def _frame_to_head(ref: np.ndarray, scheme: LandmarkScheme, opts: EnrolOptions,
                   eye_ref: np.ndarray | None) -> tuple[float, np.ndarray, np.ndarray, str]:
    """Scale (mm per unit), rotation and origin that put the reference into the head frame."""
    lc, rc = scheme.mouth_corners
    if eye_ref is not None:
        ipd = float(np.linalg.norm(eye_ref[0] - eye_ref[1]))
        mm, source = opts.ipd_mm / ipd, f"inter-pupillary distance {opts.ipd_mm:g} mm (assumed)"
        across = eye_ref[0] - eye_ref[1]
    else:
        width = float(np.linalg.norm(ref[lc] - ref[rc]))
        mm = opts.mouth_width_mm / width
        source = f"mouth width {opts.mouth_width_mm:g} mm at the median posture (assumed)"
        across = ref[lc] - ref[rc]
    # x along the speaker's left (eye line, or mouth corners), y up as seen, z completes
    x = across / np.linalg.norm(across)
    y = np.array([0.0, 1.0, 0.0]) - x[1] * x
    y /= np.linalg.norm(y)
    rot = np.stack([x, y, np.cross(x, y)])  # rows: head axes in reference coordinates
    il, ir = scheme.lip_inner_corners
    origin = 0.5 * (ref[il] + ref[ir]) - opts.teeth_depth_mm / mm * rot[2]
    return mm, rot, origin, source


def unproject(landmarks: np.ndarray, camera: Camera, mm_per_px: np.ndarray) -> np.ndarray:
    """Landmarks (..., L, 3) -> camera-frame points (..., L, 3) mm, perspective-correct.

    mm_per_px : (...,) size of one pixel at the face (its landmarks' mean depth). The face
    centre is at depth D = fx * mm_per_px; each landmark's relative depth (px) becomes
    ``z * mm_per_px`` mm, and its pixel is back-projected at its own depth. A weak-perspective
    reading instead distorts a face 20 cm from a head-mounted camera by ~3 mm.
    """
    lm = np.asarray(landmarks, np.float64)
    k = np.asarray(mm_per_px, np.float64)[..., None]
    depth = camera.fx * k + (lm[..., 2] - lm[..., 2].mean(-1, keepdims=True)) * k
    x = (lm[..., 0] - camera.cx) / camera.fx * depth
    y = (lm[..., 1] - camera.cy) / camera.fy * depth
    return np.stack([x, y, depth], -1)


def _shapes_mm(lm: np.ndarray, keep: np.ndarray, stable: np.ndarray, camera: Camera,
               reference: np.ndarray | None, iterations: int, fixed: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """Perspective shapes in head axes (F, M, 3) and their pixel size (F,), two passes: a
    weak-perspective alignment gives each frame's scale, hence its depth."""
    weak = to_head_axes(lm[:, keep])
    if reference is None:
        _, ref, _ = align(weak, stable, iterations)
    else:
        ref = reference
    scale = np.array([similarity(x[stable], ref[stable])[0] for x in weak])
    if fixed:
        scale = np.full_like(scale, np.median(scale))
    if reference is None:  # reference units -> mm: one px of the middle frame ~ 0.5 mm
        scale = scale / np.median(scale) * 0.5
    return to_head_axes(unproject(lm[:, keep], camera, scale)), scale


def enrol_geometry(landmarks: np.ndarray, found: np.ndarray, scheme: LandmarkScheme,
                   camera: Camera, options: EnrolOptions | None = None,
                   name: str = "speaker") -> Enrolment:
    """Build the speaker model from per-frame landmarks.

    landmarks : (F, L, 3) float, image px (x right, y down) and relative depth (same scale,
        smaller = nearer the camera); rows of frames without a face are ignored.
    found : (F,) bool, False where no face was found.
    camera : the camera of the clip (a default one from the frame size will do: the depth of
        the face is only used to undo perspective, relative to the assumed scale).
    """
    opts = options or EnrolOptions()
    lm = np.asarray(landmarks, np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (scheme.n_landmarks, 3):
        raise InputError(f"landmarks must have shape (F, {scheme.n_landmarks}, 3), got {lm.shape}")
    found = np.asarray(found, bool) & np.isfinite(lm).all((1, 2))
    rejected = {int(i): "no face found" for i in np.flatnonzero(~found)}
    idx = np.flatnonzero(found)
    if idx.size < len(OBSERVABLE) + 2:
        raise InputError(f"a face was found in {idx.size} frames: too few to enrol")
    eyes = scheme.eyes if opts.use_eyes else None
    keep = np.concatenate([scheme.points, list(eyes)]) if eyes else scheme.points
    n = scheme.points.size
    mm = 1.0
    for _ in range(2):  # the second pass undoes perspective at the assumed scale
        shapes, _ = _shapes_mm(lm[idx], keep, scheme.stable, camera, None, opts.iterations,
                               opts.fixed_pose)
        shapes = shapes * mm
        aligned, ref, misfit = align(shapes, scheme.stable, opts.iterations, opts.fixed_pose)
        mm_ref, rot, origin, source = _frame_to_head(ref[:n], scheme, opts,
                                                     ref[n:] if eyes else None)
        mm *= mm_ref
    size = float(np.ptp(ref[:n], axis=0).max())
    good = _reject_outliers(misfit, size, opts.outlier_mad)
    for j in np.flatnonzero(~good):
        rejected[int(idx[j])] = (f"head pose did not fit the stable points (misfit "
                                 f"{misfit[j] / size:.1%} of the face)")
    if good.sum() < len(OBSERVABLE) + 2:
        raise InputError(f"{good.sum()} frames fit a common head pose: too few to enrol")
    idx, aligned = idx[good], aligned[good]
    aligned, ref, _ = align(aligned, scheme.stable, opts.iterations, opts.fixed_pose)
    mm_ref, rot, origin, source = _frame_to_head(ref[:n], scheme, opts,
                                                 ref[n:] if eyes else None)
    pts = (aligned[:, :n] - origin) @ rot.T * mm_ref  # (F, N, 3) mm, head frame
    corpus = Corpus(pts, tuple(f"frame{i}" for i in idx),
                    scheme.point_names or tuple(f"lm{i}" for i in scheme.points),
                    scheme.groups, scheme.triangles, scheme.feature_points,
                    scheme.fapu_overrides, name=name)
    six, table6 = build_model(corpus, OBSERVABLE)
    model = with_unobserved(six, PARAM_NAMES)
    alpha = invert(model, pts)
    table = VarianceTable(PARAM_NAMES, np.append(table6.variance_pct, 0.0),
                          np.append(table6.cumulative_pct, table6.cumulative_pct[-1]),
                          table6.rms_mm_per_posture)
    return Enrolment(model, table, idx, alpha, pts, rejected, mm * mm_ref, source)


def with_unobserved(model: FaceModel, names: tuple[str, ...]) -> FaceModel:
    """``model`` extended to ``names`` with a zero basis (and zero range) for the parameters
    it lacks: they stay 0 under any fit (the prior holds them) and in every output."""
    k = len(names)
    basis = np.zeros((k, model.n_points, 3))
    stats = ParamStats(np.zeros(k), np.ones(k), np.zeros(k), np.zeros(k))
    mean_, std_, min_, max_ = (np.array(a) for a in (stats.mean, stats.std, stats.min, stats.max))
    for j, nm in enumerate(model.param_names):
        i = names.index(nm)
        basis[i] = model.basis[j]
        mean_[i], std_[i] = model.stats.mean[j], model.stats.std[j]
        min_[i], max_[i] = model.stats.min[j], model.stats.max[j]
    return FaceModel(model.mean, basis, tuple(names), ParamStats(mean_, std_, min_, max_),
                     model.point_names, model.groups, model.triangles, model.feature_points,
                     model.fapu_overrides, model.name)


def fit_pose(shape: np.ndarray, uv: np.ndarray, camera: Camera, init: Pose | None = None
             ) -> Pose | None:
    """Head pose (head -> camera) that projects ``shape`` onto ``uv``; None if it fails.

    shape : (N, 3) mm head frame; uv : (N, 2) px (rows with NaN are ignored).
    """
    ok = np.isfinite(uv).all(1) & np.isfinite(shape).all(1)
    if ok.sum() < 6:
        return None
    obj = np.ascontiguousarray(shape[ok], np.float64)
    img = np.ascontiguousarray(uv[ok], np.float64)
    dist = np.asarray(camera.dist, np.float64)
    if init is None:
        # global solution first (no local minimum of a mirrored or far-away face), then the
        # iterative refinement of the reprojection error from it
        done, rvec, tvec = cv2.solvePnP(obj, img, camera.K, dist, flags=cv2.SOLVEPNP_SQPNP)
        if not done:
            return None
    else:
        rvec = np.array(init.rotation, np.float64).reshape(3, 1)
        tvec = np.array(init.translation, np.float64).reshape(3, 1)
    done, rvec, tvec = cv2.solvePnP(obj, img, camera.K, dist, rvec, tvec,
                                    useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not done or not np.all(np.isfinite(rvec)) or float(tvec[2, 0]) <= 0:
        return None
    return Pose(rvec.ravel(), tvec.ravel())


def state_from_landmarks(model: FaceModel, scheme: LandmarkScheme, camera: Camera,
                         landmarks: np.ndarray, init: Pose | None = None
                         ) -> tuple[np.ndarray, Pose] | None:
    """Articulation and head pose of one frame from its landmarks (for (re-)initialisation).

    landmarks : (L, 3) image px and relative depth. The frame's landmark shape is aligned to
    the model's neutral stable points (a similarity: pose and scale removed), inverted for
    alpha, and the pose solved from the model shape at alpha and the landmarks' px.
    Returns (alpha (K,), pose) or None if the landmarks do not determine them.
    """
    lm = np.asarray(landmarks, np.float64)
    if lm.shape != (scheme.n_landmarks, 3) or not np.isfinite(lm).all():
        return None
    x = to_head_axes(lm[scheme.points])
    st = scheme.stable
    s, r, t = similarity(x[st], model.mean[st])
    alpha = invert(model, s * x @ r.T + t)
    alpha = np.clip(alpha, model.stats.min - 1.0, model.stats.max + 1.0)
    uv = lm[scheme.points, :2]
    pose = fit_pose(model.shape(alpha), uv, camera, init)
    if pose is None:
        return None
    return fit_to_landmarks(model, camera, uv, alpha, pose)


def fit_to_landmarks(model: FaceModel, camera: Camera, uv: np.ndarray, alpha: np.ndarray,
                     pose: Pose, iterations: int = 10, sigma_px: float = 2.0,
                     alpha_sd: float = 1.5) -> tuple[np.ndarray, Pose]:
    """Articulation and pose that project the model onto the landmarks (Levenberg-Marquardt on
    the reprojection error, px, with a Gaussian prior on alpha of ``alpha_sd`` training s.d.
    against landmark noise of ``sigma_px``). The 3D reading of the landmarks used to start it
    is only as good as their relative depth and the stable points; this uses what a camera
    measures, their pixels, with the real perspective.

    uv : (N, 2) px of the model points. Returns (alpha (K,), pose).
    """
    k = model.n_params
    a = np.array(alpha, np.float64)
    rot = rotation_matrix(pose.rotation)
    tr = np.array(pose.translation, np.float64)
    w_prior = (sigma_px / alpha_sd) ** 2
    live = np.ptp(model.basis.reshape(k, -1), axis=1) > 0  # parameters the model can move
    lam = 1e-3

    def cost_of(a_: np.ndarray, rot_: np.ndarray, t_: np.ndarray) -> tuple[float, ...]:
        pc = model.shape(a_) @ rot_.T + t_
        proj, jac = camera.project_jacobian(pc)
        r = (proj - uv).ravel()
        return float(r @ r + w_prior * a_ @ a_), r, jac, pc

    cost, r, jac, pc = cost_of(a, rot, tr)
    for _ in range(iterations):
        # d uv / d alpha_k = J R b_k ; d uv / d t = J ; d uv / d omega = J [-(R x)]_x
        rb = np.einsum("ij,knj->kni", rot, model.basis)  # (K, N, 3)
        d_alpha = np.einsum("nij,knj->nik", jac, rb)  # (N, 2, K)
        rx = pc - tr
        skew = np.zeros((len(rx), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = rx[:, 2], -rx[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = -rx[:, 2], rx[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = rx[:, 1], -rx[:, 0]
        d_rot = np.einsum("nij,njk->nik", jac, skew)
        full = np.concatenate([d_alpha[:, :, live], d_rot, jac], axis=2).reshape(len(uv) * 2, -1)
        ok = np.isfinite(full).all(1) & np.isfinite(r)
        jj, rr = full[ok], r[ok]
        h = jj.T @ jj
        g = jj.T @ rr
        na = int(live.sum())
        h[:na, :na] += w_prior * np.eye(na)
        g[:na] += w_prior * a[live]
        step = -np.linalg.solve(h + lam * np.diag(np.diag(h) + 1e-9), g)
        a_new = a.copy()
        a_new[live] += step[:na]
        rot_new = rotation_matrix(step[na:na + 3]) @ rot
        t_new = tr + step[na + 3:]
        c_new, r_new, jac_new, pc_new = cost_of(a_new, rot_new, t_new)
        if np.isfinite(c_new) and c_new < cost:
            a, rot, tr, cost, r, jac, pc = a_new, rot_new, t_new, c_new, r_new, jac_new, pc_new
            lam = max(lam / 10, 1e-7)
        else:
            lam *= 10
    return a, Pose(axis_angle(rot), tr)

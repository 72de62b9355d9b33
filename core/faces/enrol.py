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
from articast.core.model.camera import Camera
from articast.core.model.face import PARAM_NAMES, FaceModel, ParamStats

OBSERVABLE = PARAM_NAMES[:6]
"""Parameters a face-landmark enrolment can determine; lar1 (throat) is not among them."""
DEPTHS = ("rigid", "landmarks")
"""Where an enrolment takes each frame's depth from (:class:`EnrolOptions` ``depth``)."""

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
    depth : where each frame's depth comes from. A camera sees pixels; the landmarker's depth
        is its guess. "rigid" (default): the reference shape (the median of the aligned
        frames) posed on each frame's stable points by their pixels (PnP), every point
        back-projected along its pixel's ray at the posed reference's depth (see
        :func:`rigid_depth`): the head's rotation moves the depth, the landmarker's
        per-frame guesses (articulation, noise) do not. "landmarks": the landmarks' depth as
        given (the head pose from it too).
    jaw_moves_upper_lip : jaw1's basis regressed on every point (default, as the guided PCA
        does). False: the upper lip's rows kept off jaw1 (the upper lip hangs from the skull;
        what the corpus shows of it moving with the jaw is coarticulation and the landmark
        model's coupling of the lips), so that motion stays in the residual for lips1-lips3.
        Measured on the rendered head rig (docs/history/REAL_SPEAKERS_LOG.md): it took
        speaker 2's tracked lips3 from 0.83 to 0.91 (the tracker had read a jaw opening as
        lips3 < 0), but cost lips4 on speakers 3-5 (0.91-0.93 -> 0.82-0.91) and was mixed on
        the desk: off.
    """

    ipd_mm: float = 63.0
    mouth_width_mm: float = 50.0
    teeth_depth_mm: float = 10.0
    outlier_mad: float = 6.0
    iterations: int = 4
    use_eyes: bool = True
    fixed_pose: bool = False
    depth: str = "rigid"
    jaw_moves_upper_lip: bool = True


JAW_UNMOVED = {"jaw1": ("upper_lip",)}
"""What the guided PCA keeps off jaw1 with :class:`EnrolOptions` ``jaw_moves_upper_lip`` False."""


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


def rigid_depth(uv: np.ndarray, shapes: np.ndarray, ref: np.ndarray, stable: np.ndarray,
                camera: Camera, fixed: bool = False) -> np.ndarray:
    """Each frame's shape with the depth the rigid head gives it, the pixels kept.

    uv : (F, M, 2) px of the points; shapes : (F, M, 3) their back-projection (head axes,
    camera-centred, any common unit); ref : (M, 3) the reference shape in that unit. Per frame,
    the head's pose is solved from the *pixels* of the stable points against ``ref`` (PnP;
    with ``fixed`` one pose, ``ref``'s own), each point takes the depth of the posed ``ref``
    and is back-projected along its pixel's ray at that depth: the head's rotation moves the
    depth, the landmarker's per-frame depth guesses (articulation, noise) do not.
    """
    k = camera.K
    obj = np.ascontiguousarray(ref @ _TO_HEAD, np.float64)  # camera axes
    out = np.empty_like(shapes)
    for f, x in enumerate(shapes):
        cam = x @ _TO_HEAD
        depth = obj[:, 2]
        if not fixed:
            img = np.ascontiguousarray(uv[f][stable], np.float64)
            done, rvec, tvec = cv2.solvePnP(obj[stable], img, k, None, flags=cv2.SOLVEPNP_SQPNP)
            if done:
                done, rvec, tvec = cv2.solvePnP(obj[stable], img, k, None, rvec, tvec, True,
                                                cv2.SOLVEPNP_ITERATIVE)
            if not done or not np.all(np.isfinite(tvec)):
                out[f] = x
                continue
            depth = (obj @ cv2.Rodrigues(rvec)[0].T + tvec.ravel())[:, 2]
        ratio = depth / cam[:, 2]
        out[f] = np.column_stack([cam[:, 0] * ratio, cam[:, 1] * ratio, depth]) @ _TO_HEAD
    return out


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
    if opts.depth not in DEPTHS:
        raise InputError(f"depth must be one of {DEPTHS}, got {opts.depth!r}")
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
    if opts.depth == "rigid":
        # the reference is the median of the frames: their depth guesses averaged; each frame
        # keeps its pixels and takes the depth of that reference posed as its head
        shapes = rigid_depth(lm[idx][:, keep, :2], shapes[good], ref, scheme.stable, camera,
                             opts.fixed_pose)
        aligned, ref, _ = align(shapes, scheme.stable, opts.iterations, opts.fixed_pose)
    mm_ref, rot, origin, source = _frame_to_head(ref[:n], scheme, opts,
                                                 ref[n:] if eyes else None)
    pts = (aligned[:, :n] - origin) @ rot.T * mm_ref  # (F, N, 3) mm, head frame
    corpus = Corpus(pts, tuple(f"frame{i}" for i in idx),
                    scheme.point_names or tuple(f"lm{i}" for i in scheme.points),
                    scheme.groups, scheme.triangles, scheme.feature_points,
                    scheme.fapu_overrides, name=name)
    six, table6 = build_model(corpus, OBSERVABLE,
                              None if opts.jaw_moves_upper_lip else JAW_UNMOVED)
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

"""Appearance models (METHOD.md §2): local appearance (la) and texture (tex), cst or lin.

Both kinds are features sampled from the image at *sample points* on the face: each sample
point is a fixed barycentric combination of up to three model points, so its head-frame
position is linear in alpha like the model itself. la samples 8 Gaussian-derivative
responses at selected model points; tex samples the smoothed, luminance-normalised Y channel
at a dense grid of points spread over the mesh in its normalized shape (the piecewise-affine
texture frame of the paper).

Descriptor channels of la, from the Gaussian-smoothed Y, Cr, Cb image S (sigma px):
``(Yx, Yy, Cr, Crx, Cry, Cb, Cbx, Cby)`` — derivatives scale-normalised (x sigma).
The model predicts, per feature value, ``f(alpha) = W[0] + alpha @ W[1:K+1]`` (lin), or
``W[0]`` (cst); ``la_quad`` (ours, beyond the paper) adds ``alpha**2 @ W[K+1:]`` so the
appearance of lip-contour points, which changes non-linearly as lips open and round, is
predicted without bias at the extremes. ``channel_weight`` balances the features in the cost.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from articast.core.appearance.maps import ImageMaps, image_maps, roi_of, sample_la, sample_tex
from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.errors import InputError
from articast.core.model.camera import Camera, Pose, axis_angle, rotation_matrix
from articast.core.model.face import FaceModel, range_motion

APPEARANCE_KIND = "appearance-model"
APPEARANCE_VERSION = 1
KINDS = ("la_cst", "la_lin", "la_quad", "tex_cst", "tex_lin")
SELECTIONS = ("auto", "information", "displacement")
# rotation regressors of la models with rotation terms are in units of 3 degrees, so that the
# ridge penalises them like the articulation's (which is in training s.d.)
ROTATION_SCALE = float(np.radians(3.0))


# --------------------------------------------------------------------------- sample points
@dataclass(frozen=True, eq=False)
class SamplePoints:
    """Sample points as barycentric combinations of model points.

    index : (S, 3) int model point indices; weight : (S, 3) float, rows sum to 1.
    """

    index: np.ndarray
    weight: np.ndarray

    def positions(self, model: FaceModel) -> tuple[np.ndarray, np.ndarray]:
        """Head-frame mean (S, 3) and basis (K, S, 3) of the sample points."""
        mean = np.einsum("sj,sjd->sd", self.weight, model.mean[self.index])
        basis = np.einsum("sj,ksjd->ksd", self.weight, model.basis[:, self.index])
        return mean, basis

    @classmethod
    def of_points(cls, idx: np.ndarray) -> SamplePoints:
        idx = np.asarray(idx, np.int64)
        return cls(np.repeat(idx[:, None], 3, 1), np.tile([1.0, 0.0, 0.0], (idx.size, 1)))


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) of a mesh (triangles CCW seen from outside)."""
    a, b, c = (points[triangles[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(points)
    for i in range(3):
        np.add.at(n, triangles[:, i], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def sample_normals(model: FaceModel, appearance: AppearanceModel) -> np.ndarray | None:
    """Unit surface normals (S, 3), head frame, of the appearance's sample points on the
    model's mean face (its vertex normals blended as the points are); None when the model
    has no triangles."""
    if len(model.triangles) == 0:
        return None
    vn = vertex_normals(model.mean, model.triangles)
    s = appearance.samples
    n = np.einsum("sj,sjd->sd", s.weight, vn[s.index])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def select_points(
    model: FaceModel, per_param: int = 5, candidates: np.ndarray | None = None
) -> np.ndarray:
    """Automatic point selection (METHOD.md §2): for each parameter, the ``per_param`` points
    whose displacement under its basis vector over the training range is largest; merged and
    de-duplicated. ``candidates`` restricts the choice (e.g. visible points, no markers).
    """
    allowed = np.arange(model.n_points) if candidates is None else np.asarray(candidates)
    motion = range_motion(model.basis[:, allowed], model.stats)
    chosen: set[int] = set()
    for k in range(model.n_params):
        chosen.update(int(i) for i in allowed[np.argsort(-motion[k])[:per_param]])
    return np.array(sorted(chosen), np.int64)


def _regress(dmat: np.ndarray, fmat: np.ndarray, ridge: float, constant: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Appearance regression of features (F, D') on regressors (F, D): weights (D, D'), fitted
    residuals and leave-one-out residuals (e / (1 - h)). Feature weights must reflect how well
    a feature is *predicted* on frames it was not fitted on, not how well it was fitted.
    ``constant``: the cst models, the training mean (no leave-one-out correction)."""
    if constant:
        w = np.zeros((dmat.shape[1], fmat.shape[1]))
        w[0] = fmat.mean(0)
        fitted = fmat - dmat @ w
        return w, fitted, fitted
    reg = ridge * len(dmat) * np.diag([0.0] + [1.0] * (dmat.shape[1] - 1))  # intercept free
    inv = np.linalg.inv(dmat.T @ dmat + reg)
    w = inv @ (dmat.T @ fmat)
    fitted = fmat - dmat @ w
    hat = np.einsum("fi,ij,fj->f", dmat, inv, dmat)
    return w, fitted, fitted / np.maximum(1.0 - hat, 0.05)[:, None]


def _feature_weights(resid: np.ndarray, c: int, floor_min: float) -> np.ndarray:
    """Inverse residual s.d. per feature (S, C), floored at half the channel's median and at
    ``floor_min`` so that none dominates the cost."""
    rms_f = np.sqrt((resid**2).mean(0)).reshape(-1, c)
    floor = np.maximum(np.median(rms_f, axis=0) * 0.5, floor_min)
    return 1.0 / np.maximum(rms_f, floor)


def informative_points(
    model: FaceModel, camera: Camera, frames: list[TrainingFrame], candidates: np.ndarray,
    n_points: int, sigma: float = 2.5, ridge: float = 1e-2, prior: float = 1.0,
    noise_floor: float = 1.0, pose_sigma: tuple[float, float] | None = None,
) -> np.ndarray:
    """Point selection by the information the la lin cost carries about alpha (ours, beyond
    the paper's largest-displacement rule).

    For every candidate point and training frame, the Jacobian of its 8 weighted residuals
    w.r.t. alpha, ``cw * (dD/duv . duv/dalpha - W_k)``, is computed at the true state (cw: the
    inverse leave-one-out residual s.d. of a la lin model of that point, so badly predicted
    points — inner lips, teeth — carry little information). Points are then added greedily,
    each time the one that most reduces the expected RMS 3D error of the estimate,
    ``trace(G (prior I + sum_i J_i^T J_i)^-1)`` with G the model's geometric metric (mm^2 per
    alpha^2 over all points): parameters that move the face a lot but are barely seen in the
    image (jaw advance, along the optical axis) get the points that do see them.

    ``pose_sigma`` (rad, mm): the head pose is estimated with the articulation, with this
    prior s.d. per frame. J then also has the 6 pose columns and the score is the
    articulation block of the inverse (the pose marginalised out): a point that moves with
    the jaw *and* with the head tells nothing about the jaw unless other points pin the
    head. On the desk camera (free head motion) this picks rigid points (nose, eyes) that
    fix the pose, and took the la lin error from 1.13 to 0.79 mm; without it, the jaw's
    opening traded against the head's vertical position (error correlation -0.97).
    """
    cand = np.asarray(candidates, np.int64)
    if cand.size <= n_points:
        return np.sort(cand)
    k = model.n_params
    alphas = np.stack([np.asarray(f.alpha, np.float64) for f in frames])
    dmat = design(alphas, "la_lin")
    basis = model.basis[:, cand]  # (K, S, 3)
    feats, jacs = [], []
    for fr in frames:
        pts = model.mean[cand] + np.einsum("k,ksd->sd", fr.alpha, basis)
        cam = fr.pose.transform(pts)
        uv, jp = camera.project_jacobian(cam)
        maps = image_maps(fr.image, roi_of(uv, 4 * sigma + 8), sigma, 0)
        f, df, _ = sample_la(maps, uv)
        dcam = np.einsum("de,kse->sdk", fr.pose.matrix, basis)  # (S, 3, K)
        if pose_sigma is not None:  # rotation (left-multiplied) and translation columns
            rel = cam - fr.pose.translation
            drot = np.zeros((len(cand), 3, 3))
            drot[:, 0, 1], drot[:, 0, 2] = rel[:, 2], -rel[:, 1]
            drot[:, 1, 0], drot[:, 1, 2] = -rel[:, 2], rel[:, 0]
            drot[:, 2, 0], drot[:, 2, 1] = rel[:, 1], -rel[:, 0]
            dtr = np.broadcast_to(np.eye(3), (len(cand), 3, 3))
            dcam = np.concatenate([dcam, drot, dtr], axis=2)  # (S, 3, K + 6)
        feats.append(f)
        jacs.append(np.matmul(df, np.matmul(jp, dcam)))  # (S, 8, K (+ 6))
    fmat = np.stack(feats).reshape(len(frames), -1)  # (F, S*8)
    w, _, loo = _regress(dmat, fmat, ridge, constant=False)
    cw = _feature_weights(loo, 8, noise_floor)  # (S, 8)
    n = k if pose_sigma is None else k + 6
    wk = np.zeros((cand.size, 8, n))
    wk[:, :, :k] = w[1:].T.reshape(-1, 8, k)  # model derivative (none w.r.t. the pose)
    info = np.zeros((cand.size, n, n))
    for jac in jacs:
        jr = (jac - wk) * cw[:, :, None]
        info += np.einsum("sck,scl->skl", jr, jr)
    info /= len(frames)
    gmat = np.zeros((n, n))
    gmat[:k, :k] = np.einsum("kpd,lpd->kl", model.basis, model.basis) / model.n_points
    diag = [prior] * k
    if pose_sigma is not None:
        diag += [pose_sigma[0] ** -2] * 3 + [pose_sigma[1] ** -2] * 3
    h = np.diag(diag)
    chosen: list[int] = []
    free = np.ones(cand.size, bool)
    for _ in range(n_points):
        trials = np.linalg.inv(h[None] + info)  # (S, K, K)
        score = np.einsum("kl,slk->s", gmat, trials)
        score[~free] = np.inf
        best = int(np.argmin(score))
        chosen.append(best)
        free[best] = False
        h = h + info[best]
    return np.sort(cand[chosen])


def texture_grid(model: FaceModel, spacing_mm: float = 2.0,
                 triangles: np.ndarray | None = None) -> SamplePoints:
    """A regular grid over the mesh in its normalized shape (frontal x-y of the mean face),
    each grid point bound to the triangle containing it (the piecewise-affine texture frame).
    """
    tri = model.triangles if triangles is None else np.asarray(triangles)
    if tri.size == 0:
        raise InputError("texture models need a triangulated face model")
    xy = model.mean[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing_mm), np.arange(lo[1], hi[1], spacing_mm))
    g = np.c_[gx.ravel(), gy.ravel()]
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    v0, v1 = b - a, c - a
    den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    ok_tri = np.abs(den) > 1e-9
    tri, a, v0, v1, den = tri[ok_tri], a[ok_tri], v0[ok_tri], v1[ok_tri], den[ok_tri]
    idx, wts = [], []
    for start in range(0, len(g), 4096):
        q = g[start:start + 4096, None, :] - a[None]
        l1 = (q[..., 0] * v1[:, 1] - q[..., 1] * v1[:, 0]) / den
        l2 = (v0[:, 0] * q[..., 1] - v0[:, 1] * q[..., 0]) / den
        inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
        hit = inside.any(1)
        t = np.argmax(inside, axis=1)[hit]
        rows = np.nonzero(hit)[0]
        b1, b2 = l1[rows, t], l2[rows, t]
        idx.append(tri[t])
        wts.append(np.c_[1 - b1 - b2, b1, b2])
    return SamplePoints(np.concatenate(idx), np.concatenate(wts))


# --------------------------------------------------------------------------- models
@dataclass(frozen=True, eq=False)
class AppearanceModel:
    """A trained appearance model (one of :data:`KINDS`).

    samples : where features are sampled. levels : pyramid levels trained (0 = full res).
    weights : (L, D, S*C) per level, rows of :func:`design` (D = 1 + K, or 1 + 2K for quad).
    channel_weight : (L, S*C) per-feature cost weights (inverse residual s.d. in training).
    sigma : smoothing scale in pixels of each level (image px x 2**level).
    explained : (L,) fraction of the feature variance explained on the training frames.
    rotation_weights : (L, 3, S*C) or None: la models trained with ``rotation_terms`` also
    predict ``rotation_terms(R) @ rotation_weights``, how the features change as the head
    turns (shading, foreshortening) around ``rotation_ref`` (axis-angle, the training
    frames' central pose).
    """

    kind: str
    samples: SamplePoints
    levels: tuple[int, ...]
    weights: np.ndarray
    channel_weight: np.ndarray
    sigma: float
    explained: np.ndarray
    rotation_weights: np.ndarray | None = None
    rotation_ref: np.ndarray | None = None

    def rotation_terms(self, rot: np.ndarray) -> np.ndarray | None:
        """The rotation regressors (3,) of a head rotation matrix: the rotation away from the
        training frames' reference, in units of :data:`ROTATION_SCALE` (None: no such terms)."""
        if self.rotation_weights is None or self.rotation_ref is None:
            return None
        return axis_angle(rot @ self._rotation_ref_matrix.T) / ROTATION_SCALE

    @cached_property
    def _rotation_ref_matrix(self) -> np.ndarray:
        return rotation_matrix(self.rotation_ref)

    @property
    def n_channels(self) -> int:
        return 8 if self.kind.startswith("la") else 1

    @property
    def n_samples(self) -> int:
        return int(self.samples.index.shape[0])

    def sample(self, maps: ImageMaps, uv: np.ndarray):
        return sample_la(maps, uv) if self.kind.startswith("la") else sample_tex(maps, uv)

    def level_index(self, level: int) -> int:
        try:
            return self.levels.index(level)
        except ValueError:
            raise InputError(f"appearance model has no pyramid level {level}") from None

    def save(self, path: str | os.PathLike[str]) -> None:
        arrays = {"index": self.samples.index, "weight": self.samples.weight,
                  "weights": self.weights, "channel_weight": self.channel_weight,
                  "explained": self.explained}
        if self.rotation_weights is not None and self.rotation_ref is not None:
            arrays["rotation_weights"] = self.rotation_weights
            arrays["rotation_ref"] = self.rotation_ref
        save_bundle(path, APPEARANCE_KIND, APPEARANCE_VERSION, arrays,
                    {"appearance_kind": self.kind, "levels": list(self.levels),
                     "sigma": self.sigma})

    @classmethod
    def load(cls, path: str | os.PathLike[str], model: FaceModel | None = None) -> AppearanceModel:
        arrays, meta = load_bundle(path, APPEARANCE_KIND, (APPEARANCE_VERSION,))
        with reading(path, "appearance"):
            for key in ("index", "weight", "weights", "channel_weight", "explained"):
                require(key in arrays, path, f"missing array {key!r}")
            kind = meta.get("appearance_kind")
            require(kind in KINDS, path, f"unknown appearance kind {kind!r}")
            idx, w = arrays["index"], arrays["weight"]
            s = idx.shape[0]
            require(idx.shape == (s, 3) and w.shape == (s, 3), path, "sample points are malformed")
            c = 8 if kind.startswith("la") else 1
            levels = tuple(int(v) for v in meta.get("levels", []))
            wt = arrays["weights"]
            require(wt.ndim == 3 and wt.shape[0] == len(levels) and wt.shape[2] == s * c, path,
                    f"weights have shape {wt.shape}, expected ({len(levels)}, K+1, {s * c})")
            if model is not None:
                d = 2 * model.n_params + 1 if kind.endswith("quad") else model.n_params + 1
                require(wt.shape[1] == d, path,
                        f"weights have {wt.shape[1]} rows, a {kind} model of {model.n_params} "
                        f"parameters has {d}")
                require(idx.max() < model.n_points, path,
                        "sample points index points the face model does not have")
            rw, rref = arrays.get("rotation_weights"), arrays.get("rotation_ref")
            require((rw is None) == (rref is None), path,
                    "rotation_weights and rotation_ref come together")
            if rw is not None:
                require(kind.startswith("la") and rw.shape == (len(levels), 3, s * c)
                        and rref.shape == (3,) and np.all(np.isfinite(rref)), path,
                        f"rotation terms have shape {rw.shape}, expected "
                        f"({len(levels)}, 3, {s * c}) on a la model")
            return cls(kind, SamplePoints(idx, w), levels, wt, arrays["channel_weight"],
                       float(meta["sigma"]), arrays["explained"], rw, rref)


def design(alpha: np.ndarray, kind: str) -> np.ndarray:
    """Regressors of an appearance model: alpha (F, K) -> (F, D) = [1, alpha(, alpha**2)]."""
    alpha = np.atleast_2d(alpha)
    cols = [np.ones((alpha.shape[0], 1)), alpha]
    if kind.endswith("quad"):
        cols.append(alpha**2)
    return np.concatenate(cols, axis=1)


@dataclass(frozen=True)
class TrainingFrame:
    """An image with its known state: BGR uint8 (H, W, 3), alpha (K,), head pose."""

    image: np.ndarray
    alpha: np.ndarray
    pose: Pose


def visible_points(model: FaceModel, camera: Camera, frames: list[TrainingFrame],
                   min_cos: float = 0.25, margin: float = 12.0) -> np.ndarray:
    """Model points facing the camera and inside the image in every training frame."""
    ok = np.ones(model.n_points, bool)
    for fr in frames:
        pts = model.shape(fr.alpha)
        normals = vertex_normals(pts, model.triangles) @ fr.pose.matrix.T
        cam_pts = fr.pose.transform(pts)
        view = -cam_pts / np.linalg.norm(cam_pts, axis=1, keepdims=True)
        ok &= (normals * view).sum(1) > min_cos
        ok &= camera.inside(camera.project(cam_pts), margin)
    return np.nonzero(ok)[0]


def train_appearance(
    model: FaceModel,
    camera: Camera,
    frames: list[TrainingFrame],
    kind: str = "la_lin",
    *,
    sigma: float | None = None,
    levels: tuple[int, ...] = (0, 1, 2),
    per_param: int = 12,
    tex_spacing_mm: float = 2.0,
    ridge: float | None = None,
    noise_floor: float = 1.0,
    selection: str = "auto",
    n_points: int | None = None,
    pose_sigma: tuple[float, float] | None = None,
    rotation_terms: bool = False,
) -> AppearanceModel:
    """Fit an appearance model by least squares on frames with known state.

    la: sample points among those visible in every frame, chosen by ``selection``:
    "information" (:func:`informative_points`, ``n_points`` of them, default ``per_param``
    per parameter), "displacement" (the paper's rule, :func:`select_points`), or "auto"
    (information when there are at least 2(K+1) frames to fit and cross-validate it).
    tex: a grid in the normalized shape over front-facing triangles, features z-scored per
    frame (luminance normalisation). cst models predict the training mean; lin models regress
    every feature value on [1, alpha] (ridge-regularised, intercept free; ``ridge`` default
    0.1 for la, whose few points must extrapolate beyond the enrolment's range — 0.01 gave
    ~20 % more error there — and 0.01 for tex, whose dense grid does not). Features are
    weighted by the inverse of their training residual s.d., floored at half the channel's
    median and at ``noise_floor`` grey levels (la), so that features the model predicts badly
    (occluded inner-lip points, teeth) count little and none dominates the cost.
    ``pose_sigma``: the per-frame s.d. (rad, mm) of the head motion the tracker will estimate
    (tracking.tracker.POSE_SIGMA[rig]); the information selection then plans for an unknown
    pose (:func:`informative_points`). None: the pose is taken as known.
    ``per_param``: 12 points per parameter (84 for 7): on the synthetic speaker, 84 points
    instead of 56 took the desk condition from 0.79 to 0.70 mm and the head rig from 0.47 to
    0.45 (la lin, speaker 0), at 1.5x the points' arithmetic.
    ``sigma``: the filters' scale in px; None (default): :func:`face_sigma`, the same size on
    the face whatever the camera's distance.
    ``rotation_terms`` (la_lin, la_quad): the features are also regressed on the head's
    rotation away from the training frames' mean rotation (3 more rows,
    :attr:`AppearanceModel.rotation_weights`): under a light fixed to the camera, a head
    that turns changes its shading, which a model of the articulation alone reads as
    articulation. For cameras that do not move with the head (desk).
    """
    if kind not in KINDS:
        raise InputError(f"appearance kind must be one of {KINDS}, got {kind!r}")
    if sigma is None:
        sigma = face_sigma(camera, frames)
    if rotation_terms and kind not in ("la_lin", "la_quad"):
        raise InputError(f"rotation terms are for la_lin and la_quad models, not {kind}")
    n_terms = design(np.zeros((1, model.n_params)), kind).shape[1]
    if len(frames) < (2 if kind.endswith("cst") else n_terms + 1):
        raise InputError(f"{len(frames)} training frames are too few for {kind}")
    vis = visible_points(model, camera, frames)
    if ridge is None:  # measured on the teleconference condition (README, Results)
        ridge = 0.1 if kind.startswith("la") else 0.01
    if selection not in SELECTIONS:
        raise InputError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    if kind.startswith("la"):
        if selection == "auto":  # information needs a la lin fit with spare frames
            enough = len(frames) >= 2 * (model.n_params + 1)
            selection = "information" if enough else "displacement"
        if selection == "information":
            chosen = informative_points(model, camera, frames, vis,
                                        n_points or per_param * model.n_params, sigma, ridge,
                                        noise_floor=noise_floor, pose_sigma=pose_sigma)
        else:
            chosen = select_points(model, per_param, vis)
        samples = SamplePoints.of_points(chosen)
    else:
        tri = model.triangles
        tri = tri[np.isin(tri, vis).all(1)]
        samples = texture_grid(model, tex_spacing_mm, tri)
    if samples.index.shape[0] == 0:
        raise InputError("no model point is visible in every training frame")
    s_mean, s_basis = samples.positions(model)
    alphas = np.stack([np.asarray(f.alpha, np.float64) for f in frames])
    dmat = design(alphas, kind)
    n_design = dmat.shape[1]
    rot_ref = None
    if rotation_terms:
        rot_ref = mean_rotation([f.pose.matrix for f in frames])
        ref_m = rotation_matrix(rot_ref)
        rot_cols = np.stack([axis_angle(f.pose.matrix @ ref_m.T) for f in frames])
        dmat = np.concatenate([dmat, rot_cols / ROTATION_SCALE], axis=1)
    weights, cweights, explained = [], [], []
    for level in levels:
        feats = []
        for fr in frames:
            pts = s_mean + np.einsum("k,ksd->sd", fr.alpha, s_basis)
            uv = camera.project(fr.pose.transform(pts))
            maps = image_maps(fr.image, roi_of(uv, 4 * sigma * 2**level + 8), sigma, level)
            f = (sample_la if kind.startswith("la") else sample_tex)(maps, uv)[0]
            if kind.startswith("tex"):
                f = (f - f.mean()) / max(f.std(), 1e-6)
            feats.append(f.reshape(-1))
        fmat = np.stack(feats)  # (F, S*C)
        w, fitted, loo = _regress(dmat, fmat, ridge, kind.endswith("cst"))
        c = 8 if kind.startswith("la") else 1
        cweights.append(_feature_weights(loo, c, noise_floor if c == 8 else 0.02).reshape(-1))
        total = ((fmat - fmat.mean(0)) ** 2).sum()
        explained.append(1.0 - (fitted**2).sum() / total if total > 0 else 0.0)
        weights.append(w)
    wts = np.stack(weights)
    return AppearanceModel(kind, samples, tuple(levels), wts[:, :n_design], np.stack(cweights),
                           float(sigma), np.array(explained),
                           wts[:, n_design:] if rotation_terms else None, rot_ref)


SIGMA_MM = 0.7  # filter scale on the face: 2.5 px on the head rig (3.6 px/mm)
SIGMA_MIN_PX = 1.25  # below that, sensor noise dominates the derivatives


def face_sigma(camera: Camera, frames: list[TrainingFrame]) -> float:
    """The la filter scale (px) that is :data:`SIGMA_MM` on the face at the training frames'
    median depth, never under :data:`SIGMA_MIN_PX`. A fixed 2.5 px suited the head-mounted
    camera (0.7 mm) and blurred the desk camera's face (1.2 px/mm) over 2 mm: 1.25 px there
    took the desk la_lin error from 0.62 / 0.76 / 0.73 mm to 0.56 / 0.46 / 0.62 (speakers
    0-2), with pose-aware selection and rotation terms."""
    depth = float(np.median([f.pose.translation[2] for f in frames])) if frames else 0.0
    if not np.isfinite(depth) or depth <= 0:
        return 2.5
    return float(max(SIGMA_MM * camera.fx / depth, SIGMA_MIN_PX))


def mean_rotation(matrices: list[np.ndarray]) -> np.ndarray:
    """The chordal mean of rotation matrices, as an axis-angle (3,)."""
    u, _, vt = np.linalg.svd(np.mean(matrices, axis=0))
    m = u @ vt
    if np.linalg.det(m) < 0:
        m = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return axis_angle(m)

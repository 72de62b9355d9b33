"""Landmark evidence in the per-frame fit: a linear observation model of how a landmark
network reads the speaker's face, and the whitened reprojection term it gives the fit.

A landmark network does not place its points where the speaker's model puts its own: FaceMesh
v1 never quite closes a mouth and reads openings ~25 % small (docs/FACES.md), and every
network has its own per-point offsets on a given face. So the live fit does not compare the
network's pixels with the model's points; it compares them with what the network *would
read* at a state, learned at enrolment from the same clip (:func:`learn_point_model`)::

    X_i(alpha) = m_i + sum_k alpha_k B_ik          (head frame, mm)
    uv_i = project(R X_i + t)

with m and B regressed on the enrolment frames' states (the model's own points as the prior
of the regression), and each point's residual s.d. (mm on the face) as its uncertainty. The
term's residuals are ``(uv_i(theta) - observed_i) / sigma_px_i`` with a Cauchy loss per point,
so a point the network loses (a hand, an extreme turn) stops pulling the fit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.errors import ModelFileError
from articast.core.model.camera import Camera, Pose, turn_jacobian
from articast.core.model.face import FaceModel
from articast.core.tracking import kernels

POINT_MODEL_KIND = "landmark-observation"
POINT_MODEL_VERSION = 1


@dataclass(frozen=True, eq=False)
class ReadingRegression:
    """The articulation read straight off one reading: a ridge regression, learned at
    enrolment, of the enrolled states on the reader's points (a discriminative estimate).

    Through the observation model (:class:`PointModel`, generative) the 7 parameters are the
    compromise that best explains all ~300 points: on the held-out parts of the real clips
    that fit reproduced the reader's own lip opening at r 0.26-0.998 and read the aperture
    against the consensus at r 0.91 (franck) where the reader's points give 0.96; the
    regression, weighing each point by what it told about the states at enrolment, read it
    at 0.96 from the same readings, and 0.98 against the rendered speaker's truth where the
    fit read 0.977 (``benchmarks/landmark_term.py``).

    feature_mean, feature_scale : (2M,) the enrolment's mean and s.d. of the features, the
        reading's offsets from the observation model's mean points (:meth:`features`).
    weights : (2M, K) on the standardised features. alpha_mean : (K,).
    information : (K, K) the inverse covariance of its error, from a cross-validation over
        two halves of the enrolment in time (a parameter the enrolment never moved: 0).
    ridge : the ridge the cross-validation chose (x frames, on standardised features).
    """

    feature_mean: np.ndarray
    feature_scale: np.ndarray
    weights: np.ndarray
    alpha_mean: np.ndarray
    information: np.ndarray
    ridge: float

    def __post_init__(self) -> None:
        f, k = self.weights.shape if self.weights.ndim == 2 else (-1, -1)
        if (f < 0 or self.feature_mean.shape != (f,) or self.feature_scale.shape != (f,)
                or self.alpha_mean.shape != (k,) or self.information.shape != (k, k)):
            raise ModelFileError("reading regression: inconsistent shapes")
        if not all(np.isfinite(a).all() for a in (self.feature_mean, self.feature_scale,
                                                   self.weights, self.alpha_mean,
                                                   self.information)) or np.any(
                self.feature_scale <= 0):
            raise ModelFileError("reading regression: non-finite values or a scale <= 0")
        info = self.information
        if (not np.allclose(info, info.T, atol=1e-9 * max(1.0, float(np.abs(info).max())))
                or np.linalg.eigvalsh(0.5 * (info + info.T)).min() < -1e-9):
            raise ModelFileError("reading regression: its information is not a covariance's "
                                 "inverse (symmetric, positive semi-definite)")

    @staticmethod
    def features(mean: np.ndarray, camera: Camera, uv: np.ndarray, rotation: np.ndarray,
                 translation: np.ndarray) -> np.ndarray:
        """(2M,) the reading ``uv`` (M, 2) px as head-frame x, y offsets (mm, at each point's
        depth) from the points ``mean`` (M, 3) seen at the pose (rotation matrix, mm), less
        every part a small move of the head would make: the live pose is a prediction, and a
        pose off by a millimetre shifts every offset alike, a pattern the enrolment never
        showed the regression (which would read it as articulation)."""
        if kernels.AVAILABLE and camera.pinhole:  # the same in one compiled call
            return kernels.reading_features(
                np.array(mean, np.float64), np.array(rotation, np.float64),
                np.array(translation, np.float64), camera.intrinsics,
                np.array(uv, np.float64))  # (copies: a read-only array is another type)
        return ReadingRegression.features_numpy(mean, camera, uv, rotation, translation)

    @staticmethod
    def features_numpy(mean: np.ndarray, camera: Camera, uv: np.ndarray, rotation: np.ndarray,
                       translation: np.ndarray) -> np.ndarray:
        """:meth:`features` in numpy (the reference of the compiled call)."""
        cam = mean @ rotation.T + translation
        pred, jac = camera.project_jacobian(cam, True)
        assert jac is not None
        f = head_offsets(cam, pred, uv, camera, rotation)[:, :2].reshape(-1)
        # the same offsets of a small head move (turn on the left, translation): (2M, 6)
        dcam = np.zeros((len(mean), 3, 6))
        dcam[:, :, :3] = turn_jacobian(cam - translation)
        dcam[:, 0, 3] = dcam[:, 1, 4] = dcam[:, 2, 5] = 1.0
        duv = np.matmul(jac, dcam)  # (M, 2, 6) px
        dd = np.zeros((len(mean), 3, 6))
        dd[:, 0] = duv[:, 0] * cam[:, 2:3] / camera.fx
        dd[:, 1] = duv[:, 1] * cam[:, 2:3] / camera.fy
        moves = np.einsum("mjp,ji->mip", dd, rotation)[:, :2].reshape(-1, 6)
        q, _ = np.linalg.qr(moves)
        return f - q @ (q.T @ f)

    def alpha(self, features: np.ndarray) -> np.ndarray:
        """(K,) the articulation the features (:meth:`features`) read."""
        return self.alpha_mean + ((features - self.feature_mean) / self.feature_scale
                                  ) @ self.weights


def head_offsets(cam: np.ndarray, pred: np.ndarray, uv: np.ndarray, camera: Camera,
                 rotation: np.ndarray) -> np.ndarray:
    """(M, 3) readings ``uv`` (M, 2) px off the points ``cam`` (M, 3, camera frame) projected
    at ``pred``: px -> mm in the image plane at each point's depth, then turned to the head
    frame (R^T d) by the head's ``rotation``."""
    d = np.zeros((len(cam), 3))
    d[:, 0] = (uv[:, 0] - pred[:, 0]) * cam[:, 2] / camera.fx
    d[:, 1] = (uv[:, 1] - pred[:, 1]) * cam[:, 2] / camera.fy
    return d @ rotation


RIDGES = (0.003, 0.01, 0.03, 0.1, 0.3)
"""The ridges (x frames, standardised features) the enrolment's cross-validation chooses
from."""


def learn_reading_regression(mean: np.ndarray, camera: Camera, poses: list[Pose | None],
                             alphas: np.ndarray, readings: np.ndarray, times: np.ndarray,
                             ridges: tuple[float, ...] = RIDGES,
                             floor: float = 0.01) -> ReadingRegression | None:
    """Learn :class:`ReadingRegression` from the enrolment's articulations ``alphas`` (F, K),
    the reader's points ``readings`` (F, M, 2) px (NaN: not read) taken at ``times`` (F,) s,
    and the head ``poses`` (None: not posed). The ridge and the
    error covariance come from a two-fold cross-validation over the first and second half
    of the frames in time (neighbouring frames look alike: a random split would measure
    the regression on frames it has all but seen); ``floor`` (s.d.^2) is added to each
    error variance. None when there are too few frames to learn it."""
    rows, ys, ts = [], [], []
    for alpha, pose, uv, t in zip(alphas, poses, readings, times, strict=True):
        if pose is None or not np.isfinite(uv).all():
            continue
        rows.append(ReadingRegression.features(mean, camera, uv, pose.matrix,
                                               np.asarray(pose.translation, float)))
        ys.append(np.asarray(alpha, float))
        ts.append(float(t))
    k = np.asarray(alphas).shape[1]
    if len(rows) < 4 * (k + 1):
        return None
    x, y = np.array(rows), np.array(ys)
    first = np.zeros(len(x), bool)
    first[np.argsort(ts)[:len(x) // 2]] = True

    def fit(xs: np.ndarray, yv: np.ndarray, ridge: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        mu, sd = xs.mean(0), xs.std(0) + 1e-6
        z = (xs - mu) / sd
        am = yv.mean(0)
        w = np.linalg.solve(z.T @ z + ridge * len(z) * np.eye(z.shape[1]), z.T @ (yv - am))
        return mu, sd, am, w

    def errors(ridge: float) -> np.ndarray:
        out = np.zeros_like(y)
        for train in (first, ~first):
            mu, sd, am, w = fit(x[train], y[train], ridge)
            out[~train] = y[~train] - (am + ((x[~train] - mu) / sd) @ w)
        return out

    moved = y.var(0) > 1e-9
    cv = {r: errors(r) for r in ridges}
    best = min(ridges, key=lambda r: float((cv[r][:, moved] ** 2).mean()))
    mu, sd, am, w = fit(x, y, best)
    cov = np.cov(cv[best].T) + floor * np.eye(k)
    info = np.linalg.inv(cov)
    info[~moved, :] = 0.0
    info[:, ~moved] = 0.0
    return ReadingRegression(mu, sd, w, am, 0.5 * (info + info.T), float(best))


@dataclass(frozen=True, eq=False)
class PointModel:
    """How one landmark network reads one speaker's face.

    network : which network (a key of ``articast.core.faces.finder.LANDMARK_MODELS``).
    landmarks : (M,) int, the network's point indices that are modelled.
    mean : (M, 3) mm, head frame; basis : (K, M, 3) mm per unit alpha.
    sigma_mm : (M,) s.d. of a point's own reading error about its prediction, mm on the face
        (in the image plane: px x depth / focal length), from the enrolment frames.
    modes : (R, M, 2) the reading errors the points share, in units of ``sigma_mm`` (image
        plane x, y): their covariance is diag(sigma^2) + sigma modes_r modes_r^T sigma. A
        landmark network's errors are far from independent: on the three real clips the
        600 image-plane residuals of its 300 points had the spread of only 5-7 independent
        ones (participation ratio of their covariance); weighing them as independent made
        the fit follow the network's shared errors (a mouth read a little open as a whole).
    offset_p99 : 99th percentile, over the enrolment frames, of :func:`offset_fraction` of
        the readings at the enrolled states (NaN: unknown, a model saved before it was kept).
        The live tracker's ``ok`` is judged against it.
    regression : the articulation read straight off a reading (None: not learned, a model
        saved before it was).
    """

    network: str
    landmarks: np.ndarray
    mean: np.ndarray
    basis: np.ndarray
    sigma_mm: np.ndarray
    modes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2)))
    offset_p99: float = float("nan")
    regression: ReadingRegression | None = None

    def __post_init__(self) -> None:
        m = len(self.landmarks)
        if self.modes.size == 0:
            object.__setattr__(self, "modes", np.zeros((0, m, 2)))
        if (self.mean.shape != (m, 3) or self.basis.ndim != 3 or self.basis.shape[1:] != (m, 3)
                or self.sigma_mm.shape != (m,) or self.modes.ndim != 3
                or self.modes.shape[1:] != (m, 2) or len(self.modes) > 64):
            raise ModelFileError("landmark observation model: inconsistent shapes "
                                 f"{self.mean.shape}, {self.basis.shape}, {self.sigma_mm.shape}, "
                                 f"{self.modes.shape}")
        finite = all(np.isfinite(a).all() for a in (self.mean, self.basis, self.sigma_mm,
                                                     self.modes))
        if not finite or np.any(self.sigma_mm <= 0):
            raise ModelFileError("landmark observation model: non-finite values or sigma <= 0")
        reg = self.regression
        if reg is not None and reg.weights.shape != (2 * m, self.basis.shape[0]):
            raise ModelFileError(f"landmark observation model: a reading regression of shape "
                                 f"{reg.weights.shape} for {m} points")

    @cached_property
    def every_point(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The per-reading set-up of :class:`PointTerm` when every point was read (the usual
        frame), computed once: the basis as (M, 3, K), the shared modes as (2M, R) and
        (I + V^T V)^-1."""
        return _term_setup(self, np.ones(len(self.landmarks), bool))

    @property
    def n_params(self) -> int:
        return int(self.basis.shape[0])

    def points(self, alpha: np.ndarray) -> np.ndarray:
        """(M, 3) head-frame points at ``alpha`` (K,)."""
        return self.mean + np.tensordot(alpha, self.basis, axes=1)

    def save(self, path: str | os.PathLike[str]) -> None:
        reg = self.regression
        save_bundle(path, POINT_MODEL_KIND, POINT_MODEL_VERSION,
                    {"landmarks": self.landmarks, "mean": self.mean, "basis": self.basis,
                     "sigma_mm": self.sigma_mm, "modes": self.modes,
                     **({} if reg is None else {
                         "reg_feature_mean": reg.feature_mean,
                         "reg_feature_scale": reg.feature_scale, "reg_weights": reg.weights,
                         "reg_alpha_mean": reg.alpha_mean,
                         "reg_information": reg.information})},
                    {"network": self.network, **({"offset_p99": self.offset_p99}
                                                 if np.isfinite(self.offset_p99) else {}),
                     **({} if reg is None else {"reg_ridge": reg.ridge})})

    @classmethod
    def load(cls, path: str | os.PathLike[str], n_params: int | None = None) -> PointModel:
        """Read one; one clear :class:`ModelFileError` on any defect."""
        arrays, meta = load_bundle(path, POINT_MODEL_KIND, (POINT_MODEL_VERSION,))
        with reading(path, "landmark observation model"):
            for key in ("landmarks", "mean", "basis", "sigma_mm"):
                require(key in arrays, path, f"missing array {key!r}")
            network = meta.get("network", "")
            require(isinstance(network, str), path, "network must be a name (a string)")
            marks, sigma = arrays["landmarks"], arrays["sigma_mm"]
            # negative indices read the network's points from the end, silently; a reading
            # error of 1e-300 mm weighs a point by 1e600
            require(marks.size == 0 or (int(marks.min()) >= 0 and int(marks.max()) < 100_000
                                        and len(np.unique(marks)) == marks.size), path,
                    "landmarks must be distinct point numbers from 0")
            require(sigma.size == 0 or (float(sigma.min()) >= MIN_SIGMA_MM
                                        and float(sigma.max()) <= MAX_SIGMA_MM), path,
                    f"sigma_mm must lie within {MIN_SIGMA_MM:g} to {MAX_SIGMA_MM:g} mm")
            pm = cls(network, np.asarray(marks, np.int64),
                     np.asarray(arrays["mean"], np.float64),
                     np.asarray(arrays["basis"], np.float64),
                     np.asarray(arrays["sigma_mm"], np.float64),
                     np.asarray(arrays["modes"], np.float64) if "modes" in arrays
                     else np.zeros((0, 0, 2)), _offset(meta.get("offset_p99")),
                     _regression(arrays, meta))
            require(n_params is None or pm.n_params == n_params, path,
                    f"{pm.n_params} parameters, the speaker's model has {n_params}")
        return pm


MIN_SIGMA_MM, MAX_SIGMA_MM = 1e-3, 1e3
"""A landmark's reading error a stored model may hold (enrolment floors it at
``min_sigma_mm``, far above the lower bound; real ones are 0.3-1 mm)."""


def _regression(arrays: dict[str, np.ndarray], meta: dict) -> ReadingRegression | None:
    """A stored :class:`ReadingRegression` (None: a model saved without one)."""
    if "reg_weights" not in arrays:
        return None
    def arr(key: str) -> np.ndarray:
        return np.asarray(arrays[f"reg_{key}"], np.float64)

    return ReadingRegression(arr("feature_mean"), arr("feature_scale"), arr("weights"),
                             arr("alpha_mean"), arr("information"), float(meta["reg_ridge"]))


def _offset(value: object) -> float:
    """A stored ``offset_p99`` (absent or not a positive finite number: NaN, unknown)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")
    return v if np.isfinite(v) and v > 0 else float("nan")


def offset_fraction(predicted_px: np.ndarray, readings_px: np.ndarray) -> float:
    """How far a reading is from a state's points, as a fraction of the face's size: the
    median distance between ``readings_px`` (M, 2) and ``predicted_px`` (M, 2) over the
    points read (NaN rows left out), over the RMS spread of the predicted points about their
    centre. NaN when nothing was read."""
    e = np.asarray(readings_px, float) - predicted_px
    d = np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1])
    d = d[np.isfinite(d)]
    if d.size == 0:
        return float("nan")
    c = predicted_px - predicted_px.mean(0)
    size = float(np.sqrt((c * c).sum() / len(c)))
    return float(np.median(d)) / max(size, 1.0)


def state_offset(pm: PointModel, camera: Camera, alpha: np.ndarray, rotation: np.ndarray,
                 translation: np.ndarray, seen: np.ndarray) -> float:
    """:func:`offset_fraction` of a reading's points ``seen`` (M, 2) px (those of
    ``pm.landmarks``) from the state (alpha (K,), rotation matrix (3, 3), translation (3,)
    mm). Compiled (:func:`~articast.core.tracking.kernels.point_offset`) where the camera has
    no distortion; :func:`state_offset_numpy` is the reference."""
    if kernels.AVAILABLE and camera.pinhole:
        intr = camera.intrinsics
        return float(kernels.point_offset(
            np.ascontiguousarray(pm.mean, np.float64), pm.every_point[0],
            np.array(alpha, np.float64), np.array(rotation, np.float64),
            np.array(translation, np.float64), intr,
            np.ascontiguousarray(seen, np.float64)))
    return state_offset_numpy(pm, camera, alpha, rotation, translation, seen)


def state_offset_numpy(pm: PointModel, camera: Camera, alpha: np.ndarray,
                       rotation: np.ndarray, translation: np.ndarray, seen: np.ndarray) -> float:
    """The reference of :func:`state_offset` (any camera)."""
    cam = pm.points(alpha) @ np.asarray(rotation).T + translation
    return offset_fraction(camera.project(cam), seen)


def model_point_model(model: FaceModel, landmarks: np.ndarray, network: str,
                      sigma_mm: float = 1.0) -> PointModel:
    """The observation model that assumes the network reads the model's own points (a
    speaker enrolled before observation models existed)."""
    return PointModel(network, np.asarray(landmarks, np.int64), model.mean.copy(),
                      model.basis.copy(), np.full(len(landmarks), float(sigma_mm)))


def learn_point_model(model: FaceModel, camera: Camera, states: list[tuple[np.ndarray, Pose]],
                      readings: np.ndarray, model_points: np.ndarray, landmarks: np.ndarray,
                      network: str, ridge: float = 1.0, min_sigma_mm: float = 0.2,
                      n_modes: int = 12) -> PointModel:
    """Regress how ``network`` reads the model points ``model_points`` (M,) (its point indices
    ``landmarks`` (M,)) from the enrolment frames.

    states : per frame, the enrolled (alpha (K,), pose). readings : (F, M, 2) px of the
    network's points in those frames (NaN where it found no face). Each reading is carried to
    the head frame at the depth of the model point it reads (its offset from the projected
    model point, in mm on the face), and the offsets are regressed on [1, alpha] with a ridge
    of ``ridge`` (in training s.d.^2 frames: few frames or a narrow range keep the model's own
    basis). Returns the model's points plus the regressed offsets, each point's own residual
    s.d. (at least ``min_sigma_mm``) and the ``n_modes`` largest error modes the points share
    (principal components of the image-plane residuals, :class:`PointModel` ``modes``).
    """
    k = model.n_params
    rows, offs, rots = [], [], []
    sd = np.maximum(model.stats.std, 1e-6)
    for (alpha, pose), uv in zip(states, readings, strict=True):
        if not np.isfinite(uv).all():
            continue
        head = model.shape(alpha)[model_points]
        rot = pose.matrix
        cam = head @ rot.T + pose.translation
        offs.append(head_offsets(cam, camera.project(cam), uv, camera, rot))
        rots.append(rot)
        rows.append(np.concatenate([[1.0], np.asarray(alpha) / sd]))
    if len(rows) < 2 * (k + 1):
        return model_point_model(model, landmarks, network)
    a = np.array(rows)  # (F, K + 1)
    y = np.array(offs).reshape(len(rows), -1)  # (F, M * 3)
    reg = ridge * np.eye(k + 1)
    reg[0, 0] = 0.0
    coef = np.linalg.solve(a.T @ a + reg, a.T @ y)  # (K + 1, M * 3)
    res = (y - a @ coef).reshape(len(rows), -1, 3)
    # back to each frame's image plane (x, y), where the readings' errors live
    plane = np.einsum("fij,fmj->fmi", np.array(rots), res)[:, :, :2]  # (F, M, 2)
    m = len(model_points)
    flat = plane.reshape(len(rows), 2 * m)
    cov = flat.T @ flat / len(rows)
    n_modes = int(min(n_modes, len(rows) // 4, 2 * m))
    lam, vec = np.linalg.eigh(cov)
    lam, vec = lam[::-1][:n_modes], vec[:, ::-1][:, :n_modes]
    shared = (vec ** 2) @ lam  # (2M,) the variance the modes explain, per coordinate
    own = np.maximum(np.diag(cov) - shared, 0.0).reshape(m, 2).mean(1)
    sigma = np.maximum(np.sqrt(own), min_sigma_mm)
    modes = (vec * np.sqrt(np.maximum(lam, 0.0))).T.reshape(n_modes, m, 2) / sigma[None, :, None]
    mean = model.mean[model_points] + coef[0].reshape(m, 3)
    basis = model.basis[:, model_points] + (coef[1:] / sd[:, None]).reshape(k, m, 3)
    pm = PointModel(network, np.asarray(landmarks, np.int64), mean, basis, sigma, modes)
    offsets = [offset_fraction(camera.project(pm.points(alpha) @ pose.matrix.T
                                              + pose.translation), uv)
               for (alpha, pose), uv in zip(states, readings, strict=True)
               if np.isfinite(uv).all()]
    return replace(pm, offset_p99=float(np.percentile(offsets, 99)))


def _term_setup(pm: PointModel, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:class:`PointTerm`'s set-up for the points ``ok`` (M,) bool of ``pm``: the basis as
    (M', 3, K), the shared error modes in whitened units (2M', R), and (I + V^T V)^-1
    (Woodbury)."""
    basis_mk = np.ascontiguousarray(pm.basis[:, ok].transpose(1, 2, 0))
    n_modes = len(pm.modes)
    v = np.ascontiguousarray(pm.modes[:, ok].reshape(n_modes, 2 * int(ok.sum())).T)
    return basis_mk, v, np.linalg.inv(np.eye(v.shape[1]) + v.T @ v)


class PointTerm:
    """One frame's landmark readings as a term of the fit.

    readings : (M, 2) px (rows with NaN are left out). depth_mm : the head's distance, which
    turns the model's mm uncertainties into px (fixed while a frame is fitted).
    scale : Cauchy scale of each point's whitened residual norm (None: least squares).
    """

    def __init__(self, pm: PointModel, camera: Camera, readings: np.ndarray, depth_mm: float,
                 scale: float | None = 3.0, weight: float = 1.0) -> None:
        uv = np.asarray(readings, np.float64)
        ok = np.asarray(np.isfinite(uv).all(1), bool)
        self.ok = ok
        every = bool(ok.all())
        self.mean: np.ndarray = pm.mean if every else pm.mean[ok]
        self.basis: np.ndarray = pm.basis if every else pm.basis[:, ok]
        # (M, 3, K) basis, the shared modes in whitened units (2M, R), (I + V^T V)^-1
        self._basis_mk, self._v, self._c = pm.every_point if every else _term_setup(pm, ok)
        self.uv = np.ascontiguousarray(uv if every else uv[ok])
        self.camera = camera
        px_per_mm = 0.5 * (camera.fx + camera.fy) / max(float(depth_mm), 1.0)
        self.inv_sigma = np.sqrt(weight) / ((pm.sigma_mm if every else pm.sigma_mm[ok])
                                            * px_per_mm)
        self.scale = scale
        self.k = pm.n_params
        self._jit = kernels.AVAILABLE and camera.pinhole
        self._intr = camera.intrinsics
        self._mean = np.ascontiguousarray(self.mean)

    @property
    def n_points(self) -> int:
        return len(self.uv)

    @property
    def compiled(self) -> bool:
        """Whether :meth:`residuals` runs the compiled kernel (a camera without distortion)."""
        return self._jit

    def kernel_args(self) -> tuple:
        """The landmark term's arguments of :func:`~articast.core.tracking.kernels.fit_terms`
        (p_mean to p_scale)."""
        return (self._mean, self._basis_mk, self._intr, self.inv_sigma, self.uv,
                -1.0 if self.scale is None else float(self.scale))

    def shared_args(self) -> tuple[np.ndarray, np.ndarray]:
        """The shared error modes' arguments of
        :func:`~articast.core.tracking.kernels.gn_terms` (p_v (2M, R), p_c (R, R)): what
        :meth:`shared` reads."""
        return self._v, self._c

    def shared(self, r: np.ndarray, jac: np.ndarray
               ) -> tuple[float, np.ndarray, np.ndarray]:
        """The correction for the errors the points share: with whitened residuals r (2M,)
        and Jacobian (2M, P) (IRLS-weighted), the cost r^T (I + V V^T)^-1 r is r^T r minus
        c = (V^T r)^T C (V^T r); returns c, and the halves of its gradient and Gauss-Newton
        Hessian (J^T V C V^T r, J^T V C V^T J) to subtract."""
        if self._v.shape[1] == 0:
            p = jac.shape[1]
            return 0.0, np.zeros(p), np.zeros((p, p))
        vr = self._v.T @ r
        vj = self._v.T @ jac  # (R, P)
        cvr = self._c @ vr
        return float(vr @ cvr), vj.T @ cvr, vj.T @ (self._c @ vj)

    def residuals(self, alpha: np.ndarray, rot: np.ndarray, t: np.ndarray, jacobian: bool
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals (2M,) and their Jacobian (2M, K + 6) w.r.t. (alpha, rotation
        increment on the left, translation). Compiled
        (:func:`~articast.core.tracking.kernels.point_residuals`) where the camera has no
        distortion; :meth:`residuals_numpy` is the reference."""
        if self._jit:
            r, jac = kernels.point_residuals(
                self._mean, self._basis_mk, np.asarray(alpha, np.float64), rot,
                np.asarray(t, np.float64), self._intr, self.inv_sigma, self.uv, jacobian)
            return r, (jac if jacobian else None)
        return self.residuals_numpy(alpha, rot, t, jacobian)

    def residuals_numpy(self, alpha: np.ndarray, rot: np.ndarray, t: np.ndarray,
                        jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The reference of :meth:`residuals` (any camera)."""
        head = self.mean + np.tensordot(alpha, self.basis, axes=1)
        rh = head @ rot.T
        uv, jp = self.camera.project_jacobian(rh + t, jacobian)
        w = self.inv_sigma[:, None]
        r = ((uv - self.uv) * w).reshape(-1)
        if not jacobian:
            return r, None
        assert jp is not None
        m, k = len(head), self.k
        dcam = np.zeros((m, 3, k + 6))
        dcam[:, :, :k] = np.matmul(rot, self._basis_mk)
        dcam[:, :, k:k + 3] = turn_jacobian(rh)
        dcam[:, 0, k + 3] = dcam[:, 1, k + 4] = dcam[:, 2, k + 5] = 1.0
        jac = np.matmul(jp, dcam) * w[:, :, None]  # (M, 2, P)
        return r, jac.reshape(2 * m, k + 6)

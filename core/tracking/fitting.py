"""Analysis-by-synthesis fitting of one frame (METHOD.md §3).

State theta = (alpha (K), rotation (3, axis-angle), translation (3, mm)): head -> camera.

    E(theta) = sum_i L(|| c * (D(I, p_i(theta)) - f_i(alpha)) ||^2) + rho(alpha)
    rho(alpha) = w * sum_k exp((|alpha_k| - a_k) / s)

D samples the image features at the projected sample points, f is the appearance model's
prediction, c the per-channel weights. L is the paper's least squares (L(q) = q) or, by
default, ours: a Cauchy loss per sample point, L(q) = s^2 log(1 + q / s^2) with s = 2 (the
weighted residuals are ~unit s.d. where the model is right). A point whose appearance the
linear model gets wrong (lips beyond the enrolment's range, a hand) then stops pulling the
whole state: on the teleconference condition it cuts the la lin mean error by 9-16 % over
three speakers (benchmarks/tracking_ablation.py).

Two optimisers: :func:`fit_gauss_newton` (default: Levenberg-Marquardt with analytic
Jacobians, rotation updated multiplicatively) and :func:`fit_nelder_mead` (the paper's
downhill simplex centred on the start, the baseline).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from articast.core.appearance.maps import ImageMaps
from articast.core.appearance.models import ROTATION_SCALE, AppearanceModel
from articast.core.model.camera import (
    Camera,
    axis_angle,
    rotation_matrix,
    small_turn,
    turn_jacobian,
)
from articast.core.model.face import FaceModel
from articast.core.tracking import kernels
from articast.core.tracking.points import PointTerm

_NO_W2 = np.zeros((0, 0))
_NOT_LAZY = (np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), np.uint8),
             np.zeros((0, 0, 3), np.float32), np.zeros((0, 0), np.uint8), np.zeros(0))
_EYE = np.eye(3)
_ZERO3 = np.zeros(3)  # (shared constants: read, never written)
FIT_TERMS = kernels.AVAILABLE
"""Evaluate a Gauss-Newton state in one compiled call (:func:`kernels.gn_terms`) and run
each iteration in one (:func:`kernels.lm_step`) where the la cost and the landmark term are
compiled (False: the numpy assembly and loop, the reference)."""
_NO_POINTS = (np.zeros((0, 3)), np.zeros((0, 3, 0)), np.ones(4), np.zeros(0), np.zeros((0, 2)),
              -1.0)
_NO_STATE_PRIOR = (np.zeros(0), np.eye(3), np.zeros(3), np.zeros((0, 0)))
_NO_SHARED = (np.zeros((0, 0)), np.zeros((0, 0)))


@dataclass(frozen=True)
class PriorPolicy:
    """Exponential prior on alpha: grows e-fold every ``softness`` s.d. beyond the training
    range widened by ``margin`` s.d.; ``weight`` is the penalty at the boundary."""

    weight: float = 1.0
    margin: float = 0.5
    softness: float = 0.25


@dataclass(frozen=True)
class FitPolicy:
    """Stopping rules of one frame's fit, and an optional Gaussian prior on the head pose
    around a reference pose (``pose_sigma_rad``, ``pose_sigma_mm``: s.d. of the motion
    expected from the reference; None = no prior). A head-mounted camera barely moves
    relative to the head, and monocular depth trades off against articulation (jaw advance,
    scale): the prior removes that ambiguity where the rig makes it physically implausible."""

    max_iterations: int = 5
    tol_alpha: float = 1e-2
    tol_rotation: float = 1e-4
    tol_translation_mm: float = 1e-2
    lm_lambda: float = 1e-3
    nelder_mead_evals: int = 300
    prior: PriorPolicy = field(default_factory=PriorPolicy)
    # s.d. of the image gain's change from its start value (la models estimate a gain)
    pose_sigma_rad: float | None = None
    pose_sigma_mm: float | None = None
    gain_sigma: float = 0.02
    # per-point Cauchy loss scale on the weighted residual norm, la models (None: least
    # squares; tex models always: one z-scored value per point, measured worse robustly)
    robust_scale: float | None = 2.0
    # s.d. (training s.d. units) of the articulation's departure from its prediction, per
    # frame: a Gaussian motion prior (None: none). It damps what the image does not pin down
    # (noise on a still mouth); where the image is clear the data term wins.
    alpha_sigma: float | None = None
    # Levenberg-Marquardt: rejected trial steps (each one an evaluation) before the fit stops
    # as converged (None: until the damping exceeds 1e6). At a minimum every trial is
    # rejected: a fused live fit spent 10 of its 14 evaluations there on some frames.
    max_rejections: int | None = None


@functools.lru_cache(maxsize=16)
def _zeros(k: int) -> np.ndarray:
    """(K,) zeros, made once per K (a fit's ``alpha_ref`` when none is given; shared: not
    written into)."""
    return np.zeros(k)


@functools.lru_cache(maxsize=16)
def _speaker_measurement(k: int, weight: float) -> tuple[np.ndarray, np.ndarray]:
    """(zeros (K,), weight * I (K, K)): :meth:`StatePrior.with_speaker`'s measurement, made
    once per (K, weight) (every live frame asks for it; shared: not written into)."""
    return np.zeros(k), weight * np.eye(k)


@dataclass(frozen=True, eq=False)
class StatePrior:
    """A Gaussian prior on the whole state (a motion model's prediction): ``alpha`` (K,),
    ``rotation`` (3, 3) matrix, ``translation`` (3,), and ``information`` (K + 6, K + 6), the
    inverse covariance of (alpha, rotation increment on the left, translation)."""

    alpha: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    information: np.ndarray
    # (weight, :meth:`with_speaker`'s prior at that weight) where the motion model made it
    # in the prediction's own compiled call (``ConstantVelocity(speaker=)``, :meth:`made`),
    # else None (not an argument: a prior made otherwise, e.g. by dataclasses.replace, has none)
    speaker: tuple[float, StatePrior] | None = field(default=None, init=False, repr=False)

    @classmethod
    def made(cls, alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
             information: np.ndarray, speaker: tuple[float, StatePrior] | None) -> StatePrior:
        """The prior with its speaker's prior (weight, prior) made already, if any."""
        prior = cls(alpha, rotation, translation, information)
        if speaker is not None:
            object.__setattr__(prior, "speaker", speaker)
        return prior

    def with_speaker(self, weight: float = 1.0) -> StatePrior:
        """This prior times the speaker's own distribution of articulations, N(0, I / weight)
        on ``alpha`` (the model's parameters are in units of the enrolment's s.d. about its
        mean): the Gaussian whose cost is the sum of the two (the pose moves with ``alpha``
        where the prediction correlates them). Where the frame's evidence pins an
        articulation the term changes nothing; where it does not (a direction the landmarks
        and the appearance hardly see), the estimate stays where the speaker's mouth goes
        instead of wandering several s.d. away with the reader's noise."""
        if self.speaker is not None and self.speaker[0] == weight:  # (made with the prior)
            return self.speaker[1]
        return self.with_measurement(*_speaker_measurement(len(self.alpha), float(weight)))

    def with_measurement(self, alpha: np.ndarray, information: np.ndarray) -> StatePrior:
        """This prior times a Gaussian measurement of the articulation, N(``alpha``,
        ``information``^-1) (K,), (K, K): the Gaussian whose cost is the sum of the two."""
        if kernels.AVAILABLE:  # the same sums in one compiled call (the numpy below: the
            # reference; two calls a live frame)
            return StatePrior(*kernels.state_measured(
                np.asarray(self.alpha, np.float64), np.asarray(self.rotation, np.float64),
                np.asarray(self.translation, np.float64),
                np.asarray(self.information, np.float64), np.asarray(alpha, np.float64),
                np.asarray(information, np.float64)))
        return self.with_measurement_numpy(alpha, information)

    def with_measurement_numpy(self, alpha: np.ndarray, information: np.ndarray
                               ) -> StatePrior:
        """:meth:`with_measurement` in numpy (the reference of
        :func:`~articast.core.tracking.kernels.state_measured`)."""
        k = len(self.alpha)
        info = self.information.copy()
        info[:k, :k] += information
        # minimise e^T I e + (alpha0 + e_alpha - alpha)^T J (...) over the offset e from this
        # prior's mean alpha0
        e = -np.linalg.solve(info, np.concatenate([information @ (self.alpha - alpha),
                                                   np.zeros(6)]))
        return StatePrior(self.alpha + e[:k], rotation_matrix(e[k:k + 3]) @ self.rotation,
                          self.translation + e[k + 3:], info)

    def terms(self, alpha: np.ndarray, rot: np.ndarray, t: np.ndarray
              ) -> tuple[float, np.ndarray, np.ndarray]:
        """Cost, gradient (K + 6,) and Gauss-Newton Hessian (K + 6, K + 6) at a state."""
        e = np.concatenate([alpha - self.alpha, small_turn(rot @ self.rotation.T),
                            t - self.translation])
        le = self.information @ e
        return float(e @ le), 2.0 * le, 2.0 * self.information


@dataclass(frozen=True, eq=False)
class FitResult:
    """Outcome of one fit: state, cost, counters, cost of each iteration.

    residual : mean squared (weighted) residual value. robust_residual : the robust (Cauchy)
    data term per value, where the fit is robust (else = residual): a few points the model
    mispredicts (an articulation beyond the enrolment's range) barely raise it, an occlusion,
    which spoils most points, does. point_q : per sample point, the squared norm of its
    weighted residual over its C values (the Cauchy weight of the point is
    1 / sqrt(1 + point_q / scale^2)).
    """

    alpha: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    cost: float
    residual: float
    evals: int
    iterations: int
    converged: bool
    valid_fraction: float
    costs: tuple[float, ...] = ()
    gain: float = 1.0
    robust_residual: float | None = None
    # (S,) squared weighted residual norm of each sample point at the solution (0 where the
    # point falls outside the image): the per-point evidence the occlusion test reads
    point_q: np.ndarray | None = None
    # (K + 6, K + 6) the data terms' Gauss-Newton information about (alpha, rotation
    # increment, translation) at the solution (the image gain marginalised out), without the
    # priors: what the frame told, for a motion model's update (fits with a state prior only)
    information: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.robust_residual is None:
            object.__setattr__(self, "robust_residual", self.residual)

    @property
    def theta(self) -> np.ndarray:
        return np.concatenate([self.alpha, self.rotation, self.translation])


class Problem:
    """Everything fixed while fitting: model, appearance model and camera.

    Precomputes the sample points' head-frame mean (S, 3) and basis (K, S, 3).
    """

    def __init__(self, model: FaceModel, appearance: AppearanceModel, camera: Camera,
                 prior: PriorPolicy | None = None, jit: bool | None = None) -> None:
        self.model, self.appearance, self.camera = model, appearance, camera
        self.s_mean, self.s_basis = appearance.samples.positions(model)
        self._basis_flat = np.ascontiguousarray(  # (K, S*3)
            self.s_basis.reshape(self.s_basis.shape[0], -1), np.float64)
        self._basis_sdk = np.ascontiguousarray(self.s_basis.transpose(1, 2, 0))  # (S, 3, K)
        self.k = model.n_params
        self.c = appearance.n_channels
        self.prior = prior or PriorPolicy()
        st = model.stats
        self.bound = np.maximum(np.abs(st.min), np.abs(st.max)) + self.prior.margin
        self._tex = appearance.kind.startswith("tex")
        self._quad = appearance.kind.endswith("quad")
        self.estimate_gain = not self._tex  # tex features are z-scored: gain-invariant
        # la residuals through the compiled kernel (same numbers as the numpy code below)
        self.jit = (kernels.AVAILABLE if jit is None else jit) and not self._tex
        self._cw = [np.ascontiguousarray(cw.reshape(-1, self.c), np.float64)
                    for cw in appearance.channel_weight]
        self._cw_flat = [cw.reshape(-1) for cw in self._cw]
        rw = appearance.rotation_weights  # weighted once, not per evaluation
        self._rot_w = [] if rw is None else [w * cw for w, cw in zip(rw, self._cw_flat,
                                                                      strict=True)]
        self._s_mean = np.ascontiguousarray(self.s_mean, np.float64)
        self._intr = camera.intrinsics
        self._project_jit = kernels.AVAILABLE and camera.pinhole
        self._rot_ref = (None if rw is None or appearance.rotation_ref is None
                         else rotation_matrix(appearance.rotation_ref))
        k = self.k
        # per level, fit_terms's fixed arguments between the state and the gain (kernel_args)
        self._middle = [(self._s_mean, self._basis_sdk, self._intr, camera.dist, w[0],
                         w[1:k + 1], w[k + 1:] if self._quad else _NO_W2)
                        for w in appearance.weights]

    # -------------------------------------------------------------- geometry
    def sample_points_cam(self, alpha: np.ndarray, rot: np.ndarray,
                          t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Head-frame (S, 3) and camera-frame (S, 3) positions of the sample points."""
        head = self.s_mean + (alpha @ self._basis_flat).reshape(-1, 3)
        return head, head @ rot.T + t

    def project(self, theta: np.ndarray, rot: np.ndarray | None = None) -> np.ndarray:
        """Image positions (S, 2) of the sample points at state theta (K + 6,). Compiled
        (:func:`~articast.core.tracking.kernels.sample_uv`, the same numbers) for an
        undistorted camera; :meth:`project_numpy` is the reference. rot : (3, 3) theta's
        rotation as a matrix (``rotation_matrix(theta[K:K + 3])``), if the caller has it."""
        if self._project_jit:  # (once a tracked frame)
            theta = np.asarray(theta, np.float64)
            return kernels.sample_uv(self._s_mean, self._basis_flat,
                                     np.ascontiguousarray(theta[:self.k]),
                                     rotation_matrix(theta[self.k:self.k + 3]) if rot is None
                                     else rot,
                                     np.ascontiguousarray(theta[self.k + 3:]), self._intr)
        return self.project_numpy(theta)

    def project_numpy(self, theta: np.ndarray) -> np.ndarray:
        """The reference of :meth:`project` (any camera)."""
        rot = rotation_matrix(theta[self.k:self.k + 3])
        return self.camera.project(self.sample_points_cam(theta[:self.k], rot,
                                                          theta[self.k + 3:])[1])

    # -------------------------------------------------------------- cost
    def prior_terms(self, alpha: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """rho(alpha), its gradient (K,) and diagonal Hessian (K,)."""
        p = self.prior
        e = p.weight * np.exp(np.minimum((np.abs(alpha) - self.bound) / p.softness, 50.0))
        return float(e.sum()), np.sign(alpha) * e / p.softness, e / p.softness**2

    def residuals(self, maps: ImageMaps, level_index: int, alpha: np.ndarray, rot: np.ndarray,
                  t: np.ndarray, jacobian: bool, gain: float = 1.0,
                  with_gain: bool = False) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Weighted residuals r (S*C,), Jacobian (S*C, P) w.r.t. (alpha, rotation increment,
        translation[, gain]), and the fraction of valid samples. Invalid samples contribute 0.

        la models predict ``gain * f(alpha)``: every la descriptor (first-order derivatives,
        chroma centred on 128) scales with a global image gain, so exposure and light-level
        changes are one more unknown (P = K + 7 with ``with_gain``) instead of an error.
        """
        if self.jit:
            r, jac, valid = self._residuals_jit(maps, level_index, alpha, rot, t, jacobian,
                                                gain, with_gain)
        else:
            r, jac, valid = self._residuals_numpy(maps, level_index, alpha, rot, t, jacobian,
                                                  gain, with_gain)
        om = self.appearance.rotation_terms(rot)
        if om is not None:  # la with rotation terms: f(alpha) + om @ Wr
            wr = self._rot_w[level_index]
            if not valid.all():  # invalid samples contribute 0
                wr = wr * np.repeat(valid, self.c)[None]
            r = r - gain * (om @ wr)
            if jac is not None:
                # d(om)/d(rotation increment) ~ I / scale: the head turns by a few degrees
                jac[:, self.k:self.k + 3] -= gain * wr.T / ROTATION_SCALE
                if jac.shape[1] > self.k + 6:
                    jac[:, self.k + 6] -= om @ wr
        return r, jac, float(valid.mean())

    def _residuals_numpy(self, maps, level_index, alpha, rot, t, jacobian, gain, with_gain):
        app = self.appearance
        head, cam = self.sample_points_cam(alpha, rot, t)
        uv, jp = self.camera.project_jacobian(cam, jacobian)
        feats, dfeats, valid = app.sample(maps, uv)
        w = app.weights[level_index]
        s, c = feats.shape
        cw = app.channel_weight[level_index].reshape(s, c)
        if self._tex:
            mu, sd = feats[valid].mean() if valid.any() else 0.0, feats[valid].std() + 1e-6
            feats = (feats - mu) / sd
            dfeats = dfeats / sd
        k = self.k
        pred = w[0] + alpha @ w[1:k + 1]
        if self._quad:
            pred = pred + (alpha * alpha) @ w[k + 1:]
        pred = pred.reshape(s, c)
        r = (feats - gain * pred) * cw
        r[~valid] = 0.0
        if not jacobian:
            return r.reshape(-1), None, valid
        # d(cam)/d(alpha) = R basis ; d(cam)/d(delta) = -[R head]x ; d(cam)/d(t) = I
        rh = head @ rot.T
        with_gain = with_gain and self.estimate_gain
        dcam = np.zeros((s, 3, k + 6 + int(with_gain)))
        dcam[:, :, :k] = np.matmul(rot, self._basis_sdk)
        dcam[:, :, k:k + 3] = turn_jacobian(rh)
        dcam[:, 0, k + 3] = dcam[:, 1, k + 4] = dcam[:, 2, k + 5] = 1.0
        duv = np.matmul(jp, dcam)  # (S, 2, P)
        jac = np.matmul(dfeats, duv)  # (S, C, P)
        if self._tex:
            jac -= jac[valid].mean(0, keepdims=True) if valid.any() else 0.0
        dpred = w[1:k + 1]
        if self._quad:
            dpred = dpred + 2.0 * alpha[:, None] * w[k + 1:]
        jac[:, :, :k] -= gain * dpred.T.reshape(s, c, k)
        if with_gain:
            jac[:, :, k + 6] = -pred
        jac *= cw[:, :, None]
        jac[~valid] = 0.0
        return r.reshape(-1), jac.reshape(s * c, -1), valid

    def loss_scale(self, robust_scale: float | None) -> float | None:
        """The Cauchy scale the data term uses: the policy's for la models; None (least
        squares) for tex, whose one z-scored value per point measured worse robustly."""
        return None if self._tex else robust_scale

    def _residuals_jit(self, maps, level_index, alpha, rot, t, jacobian, gain, with_gain):
        w = self.appearance.weights[level_index]
        k = self.k
        cam = self.camera
        r, jac, valid = kernels.la_residuals(
            maps.smooth, float(maps.origin[0]), float(maps.origin[1]), float(maps.scale),
            float(maps.sigma), np.asarray(alpha, np.float64), rot, np.asarray(t, np.float64),
            self._s_mean, self._basis_sdk, self._intr, cam.dist, w[0], w[1:k + 1],
            w[k + 1:] if self._quad else _NO_W2, float(gain), self._cw[level_index],
            bool(jacobian), bool(with_gain and self.estimate_gain),
            *((maps.source, maps.done, maps.rows, maps.rows_done, maps.taps) if maps.lazy
              else _NOT_LAZY))
        return r, (jac if jacobian else None), np.asarray(valid, bool)

    def kernel_args(self, maps: ImageMaps, level_index: int) -> tuple[tuple, tuple]:
        """The fixed arguments of :func:`~articast.core.tracking.kernels.fit_terms` for one
        map: those before the state (alpha, rot, t) and those between the state and the gain.
        """
        return ((maps.smooth, float(maps.origin[0]), float(maps.origin[1]), float(maps.scale),
                 float(maps.sigma)), self._middle[level_index])

    def kernel_tail(self, maps: ImageMaps, level_index: int) -> tuple:
        """The arguments of :func:`~articast.core.tracking.kernels.fit_terms` from the
        channel weights to the rotation terms' unit."""
        lazy = ((maps.source, maps.done, maps.rows, maps.rows_done, maps.taps) if maps.lazy
                else _NOT_LAZY)
        rot = ((self._rot_w[level_index], self._rot_ref) if self._rot_ref is not None
               else (_NO_W2, _EYE))
        return (self._cw[level_index], *lazy, *rot, ROTATION_SCALE)

    def cost(self, maps: ImageMaps, level_index: int, theta: np.ndarray,
             robust_scale: float | None = None) -> float:
        """E(theta) for the Nelder-Mead baseline (theta with absolute axis-angle rotation)."""
        a = theta[:self.k]
        r, _, _ = self.residuals(maps, level_index, a, rotation_matrix(theta[self.k:self.k + 3]),
                                 theta[self.k + 3:], jacobian=False)
        return _robust(r, None, self.c, self.loss_scale(robust_scale))[0] + self.prior_terms(a)[0]


def _robust(r: np.ndarray, jac: np.ndarray | None, c: int, scale: float | None
            ) -> tuple[float, np.ndarray, np.ndarray | None]:
    """Per-sample-point Cauchy loss: cost sum_s scale^2 log(1 + q_s / scale^2) with q_s the
    squared residual norm of point s over its C channels, and the IRLS-weighted residuals and
    Jacobian whose Gauss-Newton step minimises it. scale None: plain least squares."""
    if scale is None:
        return float(r @ r), r, jac
    if kernels.AVAILABLE:
        cost, rw, jw = kernels.cauchy(r, _NO_W2 if jac is None else jac, c, float(scale))
        return cost, rw, None if jac is None else jw
    q = (r.reshape(-1, c) ** 2).sum(1)
    s2 = scale * scale
    w = np.repeat(1.0 / np.sqrt(1.0 + q / s2), c)
    cost = float(s2 * np.log1p(q / s2).sum())
    return cost, r * w, None if jac is None else jac * w[:, None]


def _point_q(r: np.ndarray, c: int) -> np.ndarray:
    """Squared weighted residual norm per sample point (S,) from the residuals (S*C,)."""
    rs = r.reshape(-1, c)
    return np.einsum("sc,sc->s", rs, rs)


def _pose_prior(pol: FitPolicy, rot: np.ndarray, t: np.ndarray,
                ref: tuple[np.ndarray, np.ndarray] | None) -> tuple[float, np.ndarray, np.ndarray]:
    """Cost, gradient (6,) and Gauss-Newton Hessian (6, 6) of the pose prior."""
    g, h = np.zeros(6), np.zeros((6, 6))
    if ref is None or pol.pose_sigma_mm is None or pol.pose_sigma_rad is None:
        return 0.0, g, h
    d_rot = small_turn(rot @ ref[0].T)  # left increment from the reference: small
    d_t = t - ref[1]
    wr, wt = 1.0 / pol.pose_sigma_rad**2, 1.0 / pol.pose_sigma_mm**2
    g[:3], g[3:] = 2 * wr * d_rot, 2 * wt * d_t
    h[np.arange(3), np.arange(3)] = 2 * wr
    h[np.arange(3, 6), np.arange(3, 6)] = 2 * wt
    return float(wr * d_rot @ d_rot + wt * d_t @ d_t), g, h


def fit_gauss_newton(problem: Problem, maps: ImageMaps, level: int, alpha0: np.ndarray,
                     rotation0: np.ndarray, translation0: np.ndarray,
                     policy: FitPolicy | None = None,
                     pose_ref: tuple[np.ndarray, np.ndarray] | None = None,
                     gain0: float = 1.0, estimate_gain: bool = False,
                     alpha_ref: np.ndarray | None = None,
                     points: PointTerm | None = None,
                     state_prior: StatePrior | None = None,
                     appearance_weight: float = 1.0,
                     rot0: np.ndarray | None = None) -> FitResult:
    """Levenberg-Marquardt from (alpha0, rotation0, translation0) on one pyramid level.

    pose_ref : (rotation (3,), translation (3,)) the pose prior is centred on, if any.
    alpha_ref : (K,) the articulation the motion prior (``policy.alpha_sigma``) is centred on.
    gain0, estimate_gain : the image gain of la models and whether to refine it. Far from the
        solution, shrinking the gain is a cheap way to shrink a misaligned residual, so the
        tracker refines it only in the final fine-level fit of a frame.
    points : landmark readings of this frame (:class:`~articast.core.tracking.points.PointTerm`),
        a second data term beside the appearance (Cauchy per point).
    state_prior : a Gaussian prior on the whole state (a motion model's prediction); with it,
        give no ``pose_ref`` / ``alpha_ref`` (it replaces both).
    appearance_weight : the appearance term's weight (0: the landmarks and priors alone; the
        appearance is then not sampled at all).
    rot0 : (3, 3) ``rotation_matrix(rotation0)``, if the caller has it (not written into).
    """
    pol = policy or FitPolicy()
    ref = None if pose_ref is None else (rotation_matrix(pose_ref[0]), np.asarray(pose_ref[1]))
    li = problem.appearance.level_index(level)
    k = problem.k
    alpha = np.array(alpha0, np.float64)
    rot = rotation_matrix(rotation0) if rot0 is None else rot0
    t = np.array(translation0, np.float64)
    gain = gain0 = float(gain0)
    lam = pol.lm_lambda
    nc = problem.c
    scale = problem.loss_scale(pol.robust_scale)
    wg = 1.0 / pol.gain_sigma**2
    wa = 0.0 if alpha_ref is None or pol.alpha_sigma is None else 1.0 / pol.alpha_sigma**2
    a_ref = _zeros(k) if alpha_ref is None else np.asarray(alpha_ref, np.float64)
    use_app = appearance_weight > 0
    sw = math.sqrt(appearance_weight)
    with_gain = estimate_gain and use_app
    # one compiled call per evaluation (kernels.gn_terms) and per iteration (kernels.lm_step)
    # where the la cost and the landmark term are compiled; `evaluate_numpy` and the numpy
    # loop below are the reference
    compiled = FIT_TERMS and problem.jit and use_app and (points is None or points.compiled)
    if compiled:
        head, middle = problem.kernel_args(maps, li)
        tail = (*problem.kernel_tail(maps, li), appearance_weight,
                -1.0 if scale is None else float(scale))
        pts = points.kernel_args() if points is not None and points.n_points else _NO_POINTS
        pr_ = problem.prior
        sp_args = ((state_prior.alpha, state_prior.rotation, state_prior.translation,
                    state_prior.information) if state_prior is not None else _NO_STATE_PRIOR)
        ref_args: tuple = (_EYE, _ZERO3, -1.0, -1.0)  # as _pose_prior: none
        if ref is not None and pol.pose_sigma_mm is not None and pol.pose_sigma_rad is not None:
            ref_args = (ref[0], np.asarray(ref[1], np.float64), 1.0 / pol.pose_sigma_rad**2,
                        1.0 / pol.pose_sigma_mm**2)
        shared = (points.shared_args() if points is not None and points.n_points
                  else _NO_SHARED)
        # kernels.gn_terms's arguments after the state: fit_terms's, then the shared errors'
        # and the motion and gain priors'
        rest: tuple[Any, ...] = (*head, *middle, *tail[:1], bool(with_gain), *tail[1:], *pts,
                                 problem.bound, float(pr_.weight), float(pr_.softness),
                                 *sp_args, *ref_args, *shared, wa, a_ref, wg, gain0)
        max_rej = -1 if pol.max_rejections is None else int(pol.max_rejections)

    def evaluate(a_: np.ndarray, rot_: np.ndarray, t_: np.ndarray, g_: float):
        """Everything at one state: the total cost, the data rows (whitened, IRLS-weighted)
        and the priors' gradient and Hessian."""
        if not compiled:
            return evaluate_numpy(a_, rot_, t_, g_)
        cost_, *terms_ = kernels.gn_terms(a_, rot_, t_, float(g_), *rest)
        return cost_, tuple(terms_)

    def evaluate_numpy(a_: np.ndarray, rot_: np.ndarray, t_: np.ndarray, g_: float):
        if use_app:
            r_, jac_, vf_ = problem.residuals(maps, li, a_, rot_, t_, True, g_, with_gain)
            rc_, rw_, jw_o = _robust(r_, jac_, nc, scale)
            assert jw_o is not None
            rc_, rw_, jw_ = appearance_weight * rc_, sw * rw_, sw * jw_o
        else:
            r_, vf_, rc_ = np.zeros(0), 1.0, 0.0
            rw_, jw_ = np.zeros(0), np.zeros((0, k + 6))
        pc_ = 0.0
        g_s, h_s = np.zeros(k + 6), np.zeros((k + 6, k + 6))
        h_shared = h_s.copy()
        if points is not None and points.n_points:
            pr, pj = points.residuals(a_, rot_, t_, True)
            pc_, prw, pjw_o = _robust(pr, pj, 2, points.scale)
            assert pjw_o is not None
            pjw = pjw_o
            shared_c, shared_g, shared_h = points.shared(prw, pjw)
            pc_ -= shared_c  # the errors the landmarks share count once
            g_s -= 2.0 * shared_g
            h_s -= 2.0 * shared_h
            h_shared = shared_h
            if jw_.shape[1] > k + 6:  # the landmarks do not see the image gain
                pjw = np.hstack([pjw, np.zeros((len(pjw), jw_.shape[1] - k - 6))])
            rw_, jw_ = np.concatenate([rw_, prw]), np.vstack([jw_, pjw])
        prior_, g_p_, h_p_ = problem.prior_terms(a_)
        sp_ = 0.0
        if state_prior is not None:
            sp_, g_sp, h_sp = state_prior.terms(a_, rot_, t_)
            g_s, h_s = g_s + g_sp, h_s + h_sp
        pp_, g_pp_, h_pp_ = _pose_prior(pol, rot_, t_, ref)
        g_s[k:] += g_pp_
        h_s[k:, k:] += h_pp_
        cost_ = (rc_ + pc_ + prior_ + pp_ + sp_ + wa * float((a_ - a_ref) @ (a_ - a_ref))
                 + wg * (g_ - gain0) ** 2 * with_gain)
        return cost_, (r_, vf_, rc_, rw_, jw_, g_p_, h_p_, g_s, h_s, h_shared)

    cost, (r, vf, rc, rw, jw, g_p, h_p, g_s, h_s, h_shared) = evaluate(alpha, rot, t, gain)
    evals, costs, converged, it = 1, [cost], False, 0
    jtj, jtj_of = None, None  # J^T J of the data rows jw (kept for the information)
    for it in range(1, pol.max_iterations + 1):  # noqa: B007 - `it` is reported
        jtj, jtj_of = jw.T @ jw, jw
        if compiled:  # the whole iteration, the same sums, in one compiled call
            (accepted, lam, n_evals, step, a_new, rot_new, t_new, g_new,
             (cost_new, *terms_c)) = kernels.lm_step(jtj, jw.T @ rw, lam, max_rej, cost, h_p,
                                                     g_p, h_s, g_s, alpha, rot, t, gain, *rest)
            evals += n_evals
            terms_new = tuple(terms_c)
        else:
            h = jtj.copy()
            g = jw.T @ rw
            h[np.arange(k), np.arange(k)] += h_p / 2 + wa
            g[:k] += g_p / 2 + wa * (alpha - a_ref)
            h[:k + 6, :k + 6] += h_s / 2
            g[:k + 6] += g_s / 2
            if h.shape[0] > k + 6:  # gain prior around its start value
                h[k + 6, k + 6] += wg
                g[k + 6] += wg * (gain - gain0)
            diag = np.diag(h).copy()
            diag[diag <= 0] = 1.0
            accepted = False
            rejected = 0
            while not accepted:
                try:
                    step = -np.linalg.solve(h + lam * np.diag(diag), g)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                a_new = alpha + step[:k]
                rot_new = rotation_matrix(step[k:k + 3]) @ rot
                t_new = t + step[k + 3:k + 6]
                # (min and max, not np.clip: its call on one number costs more than these sums)
                g_new = (float(min(max(gain + step[k + 6], 0.2), 5.0)) if step.size > k + 6
                         else gain)
                cost_new, terms_new = evaluate(a_new, rot_new, t_new, g_new)
                evals += 1
                if cost_new <= cost or lam > 1e6:
                    accepted = cost_new <= cost
                    break
                rejected += 1
                if pol.max_rejections is not None and rejected >= pol.max_rejections:
                    break
                lam *= 10
        if not accepted:
            converged = True  # no descent direction left at this damping: a minimum
            break
        lam = max(lam / 10, 1e-7)
        alpha, rot, t, gain = a_new, rot_new, t_new, g_new
        cost = cost_new
        r, vf, rc, rw, jw, g_p, h_p, g_s, h_s, h_shared = terms_new
        costs.append(cost)
        if _small_step(step.tolist(), k, pol):
            converged = True
            break
    info = None
    if state_prior is not None:  # what a motion model's update needs (fused tracking only)
        reuse = jtj is not None and jtj_of is jw
        if compiled and jw.shape[1] <= k + 7:  # the same sums in one compiled call
            info = kernels.fit_information(jtj if reuse else jw.T @ jw, h_shared, k + 6, wg)
        else:
            hd = jtj.copy() if reuse else jw.T @ jw
            hd[:k + 6, :k + 6] -= h_shared
            info = _marginal_information(hd, k + 6, wg)
    n = max(r.size * vf, 1.0)
    rc_n = rc / max(appearance_weight, 1e-12) / n if use_app else 0.0
    return FitResult(alpha, axis_angle(rot), t, cost, float(r @ r) / n if use_app else 0.0,
                     evals, it, converged, vf, tuple(costs), gain, rc_n,
                     _point_q(r, nc) if use_app else None, info)


def _small_step(step: list[float], k: int, pol: FitPolicy) -> bool:
    """Whether every part of an LM step (K + 6 or more, as Python floats) is below the
    policy's tolerances (a NaN is not): numpy's ``abs(...).max() < tol`` per part, on floats
    (a frame's few iterations: three numpy reductions cost more than these comparisons)."""
    ta, tr, tt = pol.tol_alpha, pol.tol_rotation, pol.tol_translation_mm
    return (all(abs(x) < ta for x in step[:k]) and all(abs(x) < tr for x in step[k:k + 3])
            and all(abs(x) < tt for x in step[k + 3:k + 6]))


def _marginal_information(h: np.ndarray, p: int, wg: float) -> np.ndarray:
    """The information about the first ``p`` unknowns, the others (the image gain, with its
    prior ``wg``) marginalised out (Schur complement)."""
    if h.shape[0] == p:
        return h
    if h.shape[0] == p + 1:  # the gain alone: a scalar (numpy's solve costs more than it)
        return h[:p, :p] - np.outer(h[:p, p], h[p, :p]) / (h[p, p] + wg)
    hgg = h[p:, p:] + wg * np.eye(h.shape[0] - p)
    return h[:p, :p] - h[:p, p:] @ np.linalg.solve(hgg, h[p:, :p])


def fit_nelder_mead(problem: Problem, maps: ImageMaps, level: int, alpha0: np.ndarray,
                    rotation0: np.ndarray, translation0: np.ndarray,
                    policy: FitPolicy | None = None,
                    steps: tuple[float, float, float] = (0.3, 0.01, 1.0)) -> FitResult:
    """The paper's downhill simplex, its initial simplex centred on the start state.

    steps : half-widths of the simplex in alpha (s.d.), rotation (rad) and translation (mm).
    """
    from scipy.optimize import minimize

    pol = policy or FitPolicy()
    li = problem.appearance.level_index(level)
    k = problem.k
    x0 = np.concatenate([alpha0, rotation0, translation0]).astype(np.float64)
    p = x0.size
    scale = np.r_[np.full(k, steps[0]), np.full(3, steps[1]), np.full(3, steps[2])]
    # regular simplex centred on x0: vertices x0 + scale * (e_i - centroid)
    base = np.vstack([np.zeros(p), np.eye(p)])
    base -= base.mean(0)
    simplex = x0 + base * scale * (p + 1) / p
    res = minimize(lambda th: problem.cost(maps, li, th, pol.robust_scale), x0,
                   method="Nelder-Mead",
                   options={"initial_simplex": simplex, "maxfev": pol.nelder_mead_evals,
                            "xatol": 1e-4, "fatol": 1e-6})
    th = res.x
    r, _, vf = problem.residuals(maps, li, th[:k], rotation_matrix(th[k:k + 3]), th[k + 3:],
                                 False)
    n = max(r.size * vf, 1.0)
    rc = _robust(r, None, problem.c, problem.loss_scale(pol.robust_scale))[0]
    return FitResult(th[:k], th[k:k + 3], th[k + 3:], float(res.fun), float(r @ r) / n,
                     int(res.nfev), int(res.nit), bool(res.success), vf, robust_residual=rc / n,
                     point_q=_point_q(r, problem.c))

"""Articulation and head pose from one frame's landmarks: how the live tracker starts and
restarts (and how enrolment poses its frames).

:func:`fit_pose` solves the pose of a known shape (PnP, from a global solution);
:func:`state_from_landmarks` reads alpha off the landmarks' 3D shape, then
:func:`fit_to_landmarks` refines alpha and pose on their pixels with the real perspective.
"""

from __future__ import annotations

import cv2
import numpy as np

from articast.core.faces.enrol import LandmarkScheme, similarity, to_head_axes
from articast.core.model.build import invert
from articast.core.model.camera import Camera, Pose, axis_angle, rotation_matrix, turn_jacobian
from articast.core.model.face import FaceModel


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


def landmark_cost(model: FaceModel, camera: Camera, uv: np.ndarray, w_prior: float,
                  a: np.ndarray, rot: np.ndarray, t: np.ndarray
                  ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_to_landmarks`' cost at (alpha ``a``, rotation matrix ``rot``, translation
    ``t``): the squared reprojection error (px) plus ``w_prior`` |a|^2, the residuals (2N,),
    the projection's Jacobian (N, 2, 3) and the points in the camera frame (N, 3)."""
    pc = model.shape(a) @ rot.T + t
    proj, jac = camera.project_jacobian(pc)
    r = (proj - uv).ravel()
    return float(r @ r + w_prior * a @ a), r, jac, pc


def landmark_normal_equations(model: FaceModel, rot: np.ndarray, t: np.ndarray, a: np.ndarray,
                              live: np.ndarray, w_prior: float, r: np.ndarray, jac: np.ndarray,
                              pc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton normal equations (H, g) of :func:`landmark_cost` at a state, over the
    ``live`` parameters, the rotation's 3 and the translation's 3."""
    # d uv / d alpha_k = J R b_k ; d uv / d t = J ; d uv / d omega = J [-(R x)]_x
    rb = np.einsum("ij,knj->kni", rot, model.basis)  # (K, N, 3)
    d_alpha = np.einsum("nij,knj->nik", jac, rb)  # (N, 2, K)
    d_rot = np.einsum("nij,njk->nik", jac, turn_jacobian(pc - t))
    full = np.concatenate([d_alpha[:, :, live], d_rot, jac], axis=2).reshape(len(pc) * 2, -1)
    ok = np.isfinite(full).all(1) & np.isfinite(r)
    jj, rr = full[ok], r[ok]
    h = jj.T @ jj
    g = jj.T @ rr
    na = int(live.sum())
    h[:na, :na] += w_prior * np.eye(na)
    g[:na] += w_prior * a[live]
    return h, g


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
    cost, r, jac, pc = landmark_cost(model, camera, uv, w_prior, a, rot, tr)
    h = g = None
    for _ in range(iterations):
        if h is None or g is None:  # the normal equations at this state (a rejected step
            # leaves the state, hence them, as they were: only the damping grows)
            h, g = landmark_normal_equations(model, rot, tr, a, live, w_prior, r, jac, pc)
        a_new, rot_new, t_new = landmark_step(h, g, lam, live, a, rot, tr)
        c_new, r_new, jac_new, pc_new = landmark_cost(model, camera, uv, w_prior, a_new,
                                                      rot_new, t_new)
        if np.isfinite(c_new) and c_new < cost:
            a, rot, tr, cost, r, jac, pc = a_new, rot_new, t_new, c_new, r_new, jac_new, pc_new
            lam = max(lam / 10, 1e-7)
            h = g = None
        else:
            lam *= 10
    return a, Pose(axis_angle(rot), tr)


def landmark_step(h: np.ndarray, g: np.ndarray, lam: float, live: np.ndarray, a: np.ndarray,
                  rot: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Levenberg-Marquardt step of the normal equations (H, g) damped by ``lam``, applied
    to the state (alpha ``a``, rotation matrix ``rot``, translation ``t``): the new state."""
    na = int(live.sum())
    step = -np.linalg.solve(h + lam * np.diag(np.diag(h) + 1e-9), g)
    a_new = a.copy()
    a_new[live] += step[:na]
    return a_new, rotation_matrix(step[na:na + 3]) @ rot, t + step[na + 3:]

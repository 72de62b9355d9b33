"""The head's motion between two consecutive frames, from sparse optical flow of the face's
rigid points: a cheap measure of its change of distance, which the appearance fit hardly sees.

On a desk camera a face that grows in the image is explained by the la fit as well by lips
that open as by a head that comes closer, and the fit's pose prior (``POSE_SIGMA``, 0.5 mm per
frame, centred on the last pose) holds the depth back. On the real clip cap12 the head came
30 % closer in 1.4 s while the tracked depth moved 5 %, and the lips "opened" by 7 mm.

Here the model's rigid points on the front of the face (forehead, brows, eyes, nose: no
articulation moves them by more than ``rigid_motion`` of the largest motion) are projected
with the last fitted state, carried into this frame by pyramidal Lucas-Kanade with a
per-frame outlier pass, and the head pose that takes their 3D positions (head frame) to where
they went is solved by Gauss-Newton from the last pose, with a prior on the rotation's change.
Perspective separates a turn of the head from a change of distance, which a 2D similarity of
the face's features did not: on cap13 its scale read a turn as the head going 12 % farther.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.model.camera import (
    Camera,
    Pose,
    axis_angle,
    rotation_matrix,
    turn_jacobian,
)
from articast.core.model.face import FaceModel, range_motion


@dataclass(frozen=True)
class MotionPolicy:
    """Sparse flow of the face's rigid points and the pose it implies.

    rigid_motion : a model point is rigid when its largest displacement over the training range
        of every parameter is at most this fraction of the largest of any point.
    front_mm : ... and it lies within this depth (head frame, mm) of the face's front (the
        sides of the head are on the silhouette, against the background).
    window, levels : Lucas-Kanade window (px) and pyramid levels.
    fb_max_px : a point whose backward flow misses its start by more than this is dropped
        (None: no backward flow; the PnP's outlier pass does the job: on cap12 and cap13 the
        same figures within their noise, at half the flow's cost).
    min_points : fewer points left (after the flow, then after PnP's outliers) -> no estimate.
    outlier_px : after a first solution, points reprojected farther than this (and 3 x the
        median) are dropped and it is solved again.
    sigma_px, rotation_sigma, iterations : the pose solution's reprojection s.d. (px), the s.d.
        of the head's rotation between frames (rad; the desk rig's fit uses the same), the
        Gauss-Newton iterations.
    median_of : the translation's step is the median of the last this many frames' steps.
    max_depth_step : a change of distance beyond this fraction in one frame is not believed.
    """

    rigid_motion: float = 0.1
    front_mm: float = 40.0
    window: int = 15
    levels: int = 2
    fb_max_px: float | None = None
    min_points: int = 12
    outlier_px: float = 1.0
    sigma_px: float = 0.3
    rotation_sigma: float = 0.003
    iterations: int = 3
    median_of: int = 3
    max_depth_step: float = 0.1


def rigid_points(model: FaceModel, policy: MotionPolicy) -> np.ndarray:
    """Indices of the model's rigid points on the front of the face (see ``MotionPolicy``)."""
    motion = range_motion(model.basis, model.stats).max(0)
    rest = model.shape(np.zeros(model.n_params))
    front = rest[:, 2] >= rest[:, 2].max() - policy.front_mm
    return np.flatnonzero((motion <= policy.rigid_motion * motion.max()) & front)


class FaceMotion:
    """The head's pose on each frame from the last fitted state and the image motion since
    the previous frame (one stream's state: the previous frame's grey image)."""

    def __init__(self, model: FaceModel, camera: Camera, policy: MotionPolicy | None = None
                 ) -> None:
        self.policy = policy or MotionPolicy()
        self.model, self.camera = model, camera
        self.ids = rigid_points(model, self.policy)
        self._mean, self._basis = model.mean[self.ids], model.basis[:, self.ids]  # per frame
        self.reset()

    def reset(self) -> None:
        self._grey: np.ndarray | None = None
        self._steps: list[np.ndarray] = []

    def step(self, image: np.ndarray, alpha: np.ndarray | None, pose: Pose | None
             ) -> Pose | None:
        """The head's pose on ``image`` given its state (``alpha``, ``pose``) on the previous
        frame given to ``step``, or None (no previous frame or state, too few points tracked,
        an implausible step). Keeps ``image`` for the next call."""
        pol = self.policy
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        prev, self._grey = self._grey, grey
        if prev is None or alpha is None or pose is None or len(self.ids) < pol.min_points:
            return None
        x = self._mean + np.einsum("k,kpc->pc", np.asarray(alpha, np.float64), self._basis)
        uv = self.camera.project_head(x, pose)
        h, w = grey.shape
        inside = (np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1)
                  & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1))
        if inside.sum() < pol.min_points:
            return None
        x, uv = x[inside], uv[inside]
        # the flow on the points' box only (grown by what the coarsest level's window can
        # reach): opencv builds the pyramids of the images it is given, the whole frame cost
        # 1.6 ms per call
        pad = pol.window * 2 ** pol.levels
        x0, y0 = np.maximum(np.floor(uv.min(0) - pad), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(uv.max(0) + pad) + 1, [w, h]).astype(int)
        a, b = prev[y0:y1, x0:x1], grey[y0:y1, x0:x1]
        start = (uv - [x0, y0]).astype(np.float32).reshape(-1, 1, 2)
        lk = {"winSize": (pol.window, pol.window), "maxLevel": pol.levels,
              "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}
        fwd, st, _ = cv2.calcOpticalFlowPyrLK(a, b, start, None, **lk)
        good = st.ravel() == 1
        if pol.fb_max_px is not None:
            back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, None, **lk)
            good &= (st2.ravel() == 1) & (
                np.linalg.norm((back - start).reshape(-1, 2), axis=1) < pol.fb_max_px)
        fwd = fwd + np.float32([x0, y0])
        if good.sum() < pol.min_points:
            self._steps = []
            return None
        new = self._solve(x[good], fwd[good].reshape(-1, 2).astype(np.float64), pose)
        if new is None or abs(new.translation[2] / pose.translation[2] - 1.0) > pol.max_depth_step:
            self._steps = []  # (on cap12 and cap13: never) no stale step in the next median
            return None
        # the translation moves by the median of the last few frames' steps: one frame's step
        # can be off by several mm (compression artefacts, a blink), a head's approach lasts
        self._steps = (self._steps + [new.translation - pose.translation])[-pol.median_of:]
        step = np.median(np.array(self._steps), axis=0)
        return Pose(new.rotation, pose.translation + step)

    def _solve(self, obj: np.ndarray, img: np.ndarray, pose: Pose) -> Pose | None:
        """The pose taking head-frame points ``obj`` (M, 3) to pixels ``img`` (M, 2): Gauss-Newton
        from ``pose`` on the reprojection error (``sigma_px``) and a Gaussian prior on the
        rotation's change (``rotation_sigma``: the points span a few cm, so alone they trade
        a small turn for a shift and a change of distance, mm per mrad); the points reprojected
        farther than ``outlier_px`` (and 3 x the median) are dropped once and it is solved
        again."""
        pol = self.policy
        r0 = pose.matrix
        dr, t = np.zeros(3), np.array(pose.translation, np.float64)
        wr = (pol.sigma_px / pol.rotation_sigma) ** 2
        for attempt in range(2):
            for _ in range(pol.iterations):
                rx = rotation_matrix(dr) @ r0
                xr = obj @ rx.T
                uv, jac = self.camera.project_jacobian(xr + t)
                e = (uv - img).reshape(-1)
                j = np.empty((len(obj), 2, 6))
                j[:, :, :3] = jac @ turn_jacobian(xr)
                j[:, :, 3:] = jac
                j = j.reshape(-1, 6)
                h = j.T @ j
                h[np.arange(3), np.arange(3)] += wr
                g = j.T @ e
                g[:3] += wr * dr
                step = np.linalg.solve(h, -g)
                dr, t = dr + step[:3], t + step[3:]
                if np.abs(step[3:]).max() < 0.01:
                    break
            if not np.all(np.isfinite(t)):
                return None
            uv = self.camera.project((obj @ (rotation_matrix(dr) @ r0).T) + t)
            err = np.linalg.norm(uv - img, axis=1)
            keep = err <= max(pol.outlier_px, 3.0 * float(np.median(err)))
            if keep.all() or attempt:
                break
            if keep.sum() < pol.min_points:
                return None
            obj, img = obj[keep], img[keep]
        return Pose(axis_angle(rotation_matrix(dr) @ r0), t)

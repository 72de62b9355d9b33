"""The face's image motion between two consecutive frames, from sparse optical flow: a cheap
measure of the head's change of distance that the live tracker's fit cannot see by itself.

On a desk camera the appearance fit barely observes the head's depth: a face that grows in the
image is explained as well by lips that open as by a head that comes closer, and the fit's
pose prior (``POSE_SIGMA``, 0.5 mm per frame) holds the depth back. On the real clip cap12 the
head came 30 % closer in 1.4 s while the tracked depth moved 5 %, and the lips "opened" by
7 mm. The points of the upper face (eyes, brows, nose: no articulation moves them) are carried
from the previous frame by pyramidal Lucas-Kanade with a forward-backward check; a robust
similarity (RANSAC) between their two positions gives the face's change of scale and image
position, hence the head's new translation, which the tracker starts from and centres its
pose prior on (:meth:`articast.core.tracking.tracker.Tracker.track`, ``translation_hint``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.model.camera import Camera


@dataclass(frozen=True)
class MotionPolicy:
    """Sparse flow of the upper face.

    max_points, min_points : features tracked; fewer survivors than ``min_points`` -> no
        estimate this frame, and new features are found (Shi-Tomasi, in the box of the face's
        rigid points, grown by ``box_margin`` of its size, except downwards).
    window, levels : Lucas-Kanade window (px) and pyramid levels.
    fb_max_px : a point whose backward flow misses its start by more than this is dropped.
    ransac_px : RANSAC inlier threshold of the similarity (px).
    max_scale_step : a frame-to-frame scale change beyond this fraction is not believed (no
        estimate: the tracker predicts by itself).
    """

    max_points: int = 40
    min_points: int = 12
    window: int = 15
    levels: int = 2
    fb_max_px: float = 0.5
    ransac_px: float = 1.0
    max_scale_step: float = 0.1
    box_margin: float = 0.3
    quality: float = 0.01


class FaceMotion:
    """Carries features of the upper face from frame to frame (one stream's state)."""

    def __init__(self, policy: MotionPolicy | None = None) -> None:
        self.policy = policy or MotionPolicy()
        self.reset()

    def reset(self) -> None:
        self._grey: np.ndarray | None = None
        self._pts: np.ndarray | None = None  # (N, 1, 2) float32, in the previous frame

    def step(self, image: np.ndarray, box_uv: np.ndarray | None) -> np.ndarray | None:
        """This frame's similarity from the previous frame's image, (2, 3) ``A`` with
        ``u_now = A[:, :2] @ u_before + A[:, 2]`` (its scale: ``sqrt(det(A[:, :2]))``), or None
        (first frame, too few points, an implausible step).

        box_uv : image positions (P, 2) of the face's rigid points on the previous frame (e.g.
            the last fit projected): new features are looked for in their box when too few
            are left; None: no new features.
        """
        pol = self.policy
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        prev, pts = self._grey, self._pts
        self._grey = grey
        out = None
        if prev is not None and pts is not None and len(pts) >= pol.min_points:
            lk = {"winSize": (pol.window, pol.window), "maxLevel": pol.levels,
                  "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}
            fwd, st, _ = cv2.calcOpticalFlowPyrLK(prev, grey, pts, None, **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, prev, fwd, None, **lk)
            good = ((st.ravel() == 1) & (st2.ravel() == 1)
                    & (np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < pol.fb_max_px))
            if good.sum() >= pol.min_points:
                a, inl = cv2.estimateAffinePartial2D(
                    pts[good], fwd[good], method=cv2.RANSAC,
                    ransacReprojThreshold=pol.ransac_px, maxIters=200, confidence=0.99)
                if a is not None and inl is not None:
                    keep = np.flatnonzero(good)[inl.ravel() == 1]
                    scale = float(np.sqrt(abs(np.linalg.det(a[:, :2]))))
                    if len(keep) >= pol.min_points and abs(scale - 1) <= pol.max_scale_step:
                        out = a
                    self._pts = fwd[keep]
                else:
                    self._pts = None
            else:
                self._pts = fwd[good]
        if (self._pts is None or len(self._pts) < pol.min_points) and box_uv is not None:
            self._pts = self._features(grey, box_uv)
        return out

    def _features(self, grey: np.ndarray, box_uv: np.ndarray) -> np.ndarray | None:
        pol = self.policy
        h, w = grey.shape
        lo, hi = np.nanmin(box_uv, 0), np.nanmax(box_uv, 0)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            return None
        pad = pol.box_margin * (hi - lo)  # not below: the upper lip is just there
        x0, y0 = np.maximum(np.floor(lo - pad), 0).astype(int)
        x1, y1 = np.minimum(np.ceil([hi[0] + pad[0], hi[1]]), [w, h]).astype(int)
        if x1 - x0 < 2 * pol.window or y1 - y0 < 2 * pol.window:
            return None
        pts = cv2.goodFeaturesToTrack(grey[y0:y1, x0:x1], pol.max_points, pol.quality,
                                      max(3.0, 0.05 * float(x1 - x0)), blockSize=5)
        if pts is None:
            return None
        return (pts.reshape(-1, 1, 2) + np.float32([x0, y0])).astype(np.float32)


def translation_after(similarity: np.ndarray, translation: np.ndarray,
                      camera: Camera) -> np.ndarray:
    """The head's translation (3,) mm on this frame, from its last one and the face's image
    similarity since then: the distance divides by the image scale (a pinhole image's size
    goes as 1 / depth), and the head's origin goes where the similarity takes its image."""
    t = np.asarray(translation, np.float64)
    scale = float(np.sqrt(abs(np.linalg.det(similarity[:, :2]))))
    uv = camera.project(t[None])[0]
    shift = similarity[:, :2] @ uv + similarity[:, 2] - uv
    z = t[2] / scale
    return np.array([t[0] / scale + shift[0] * z / camera.fx,
                     t[1] / scale + shift[1] * z / camera.fy, z])

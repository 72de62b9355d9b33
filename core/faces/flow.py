"""Landmark pixels refined by image registration (pyramidal Lucas-Kanade), for enrolment.

Each point is carried from frame to frame by optical flow (with a forward-backward check) and
pulled back towards the landmark model's own pixel by ``gain`` per frame, so the flow cannot
drift away while the landmarks' frame-to-frame noise and their prior's pull are smoothed by
what the image shows. Frames without a face restart from the landmarks.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

FB_MAX_PX = 1.0
"""A point whose backward flow misses its start by more than this keeps the landmark's pixel."""
MAX_DEV = 0.05
"""Default ``max_dev`` of :func:`refine_pixels`."""
BY_RIG = {"desk": False, "head": True}
"""Whether an enrolment refines the pixels by default, per rig (measured,
docs/history/REAL_SPEAKERS_LOG.md).
Head-mounted camera: on. The landmarker's pixels of the lower face seen from 22 cm under-read
the lips' small motions: on the rendered speaker (benchmarks/no_truth_path.py --rigs head,
speakers 0-2) the tracked lips2 went from 0.84 / 0.79 / 0.87 to 0.95 / 0.91 / 0.93 and lips3
from 0.93 / 0.89 / 0.71 to 0.98 / 0.95 / 0.83 with the flow. Desk camera: off. It helped the
rendered desk speaker less, and the real webcam clips not at all (franck's aperture agreement
0.89 with it, 0.90 without; cap13 0.96, 0.99). There are no real head-mounted clips to check
the head default against."""


def default_for(rig: str) -> bool:
    """Whether an enrolment for ``rig`` refines the pixels unless told (:data:`BY_RIG`)."""
    return BY_RIG.get(rig, False)


def refine_pixels(images: Sequence[np.ndarray], landmarks: np.ndarray, found: np.ndarray,
                  points: np.ndarray, gain: float = 0.1, window: int = 15,
                  max_dev: float = MAX_DEV) -> np.ndarray:
    """``landmarks`` (F, L, 3) with the pixels of ``points`` (landmark indices) refined.

    images : F BGR or grey frames; found : (F,) bool. Depth and other landmarks unchanged.
    max_dev : a point whose flow lands farther than this fraction of the face's size (the
        larger side of the points' box) from its landmark restarts from the landmark.
    """
    out = np.array(landmarks, np.float64)
    ids = np.asarray(points, np.int64)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    lk = {"winSize": (window, window), "maxLevel": 3, "criteria": crit}

    def grey(img: np.ndarray) -> np.ndarray:
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

    prev_img = None
    for f, img in enumerate(images):
        g = grey(img)
        if not found[f] or not np.isfinite(out[f, ids, :2]).all():
            prev_img = None
            continue
        if prev_img is not None:
            start = out[f - 1, ids, :2].astype(np.float32).reshape(-1, 1, 2)
            fwd, st, _ = cv2.calcOpticalFlowPyrLK(prev_img, g, start, None, **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(g, prev_img, fwd, None, **lk)
            fwd, back = fwd.reshape(-1, 2), back.reshape(-1, 2)
            ok = ((st.ravel() == 1) & (st2.ravel() == 1)
                  & (np.linalg.norm(back - start.reshape(-1, 2), axis=1) < FB_MAX_PX))
            mark = landmarks[f, ids, :2]
            size = float(np.ptp(mark, axis=0).max())
            ok &= np.linalg.norm(fwd - mark, axis=1) <= max_dev * size
            out[f, ids, :2] = np.where(ok[:, None], (1 - gain) * fwd + gain * mark, mark)
        prev_img = g
    return out

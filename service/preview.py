"""The tracking preview: the video a session tracks, small and at a low rate, with the fitted
mesh drawn on it — the view people use to trust a tracker.

Off by default (it is a picture of a face, sent to whoever can reach the server): a session
opts in (``SessionSpec.preview``: ``serve --preview``, ``"preview": true`` in
``POST /api/sessions``; the synthetic ``demo`` does). The worker encodes at most
:attr:`PreviewPolicy.rate_hz` JPEGs per second after tracking (never before: the stream of
parameters comes first), the server keeps the newest one and serves it at
``GET /api/sessions/{name}/preview.jpg``; ``hello.preview_url`` names it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class PreviewPolicy:
    rate_hz: float = 5.0
    """Frames per second encoded, at most."""
    width: int = 320
    """Width of the preview in pixels (height keeps the aspect ratio)."""
    quality: int = 70
    """JPEG quality, 0-100."""


MESH_BGR = (96, 230, 120)
LOST_BGR = (60, 60, 230)


def render_preview(image: np.ndarray, model: Any, camera: Any, result: Any,
                   policy: PreviewPolicy = PreviewPolicy()) -> bytes:
    """JPEG bytes of ``image`` (H, W, 3) uint8 BGR with the mesh of ``model`` at the tracked
    state of ``result`` (alpha, pose) drawn on it, scaled to ``policy.width`` pixels wide.
    The mesh is green when the frame was tracked, red when it was not (the last good state)."""
    h, w = image.shape[:2]
    scale = policy.width / float(w)
    small = cv2.resize(image, (policy.width, max(1, int(round(h * scale)))),
                       interpolation=cv2.INTER_AREA)
    if model is not None and camera is not None and len(model.triangles):
        uv = camera.project_head(model.shape(np.asarray(result.alpha, float)), result.pose)
        if np.all(np.isfinite(uv)):
            pts = np.round(uv * scale * 16).astype(np.int32)  # 4 fractional bits
            polys = [pts[t] for t in model.triangles]
            colour = MESH_BGR if result.ok else LOST_BGR
            cv2.polylines(small, polys, True, colour, 1, cv2.LINE_AA, shift=4)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(policy.quality)])
    return buf.tobytes() if ok else b""

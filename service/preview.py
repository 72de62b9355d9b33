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


PREVIEW_MESH_OPACITY = 0.6
"""The preview is small (320 px): its mesh is drawn a little stronger than the full-size
overlay's, still translucent, with the lip contours on top (the opaque wireframe hid them)."""


def render_preview(image: np.ndarray, model: Any, camera: Any, result: Any,
                   policy: PreviewPolicy = PreviewPolicy(), contours: Any = ()) -> bytes:
    """JPEG bytes of ``image`` (H, W, 3) uint8 BGR with the fit drawn on it as
    :mod:`articast.service.overlay` draws it (the mesh of ``model`` at the tracked state of
    ``result``, green when the frame was tracked, red when not; an enrolled speaker's lip
    ``contours`` on top), scaled to ``policy.width`` pixels wide."""
    from articast.service.overlay import draw, projected

    h, w = image.shape[:2]
    scale = policy.width / float(w)
    small = cv2.resize(image, (policy.width, max(1, int(round(h * scale)))),
                       interpolation=cv2.INTER_AREA)
    if model is not None and camera is not None and len(model.triangles):
        uv = projected(model, camera, result)
        if uv is not None:
            small = draw(small, uv * scale, model, bool(result.ok), list(contours),
                         PREVIEW_MESH_OPACITY)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(policy.quality)])
    return buf.tobytes() if ok else b""

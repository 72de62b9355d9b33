"""478-point face landmarks (MediaPipe FaceLandmarker v2) on a rotated square crop.

A *region of interest* (ROI) is a square in the image: centre (px), side (px) and an
in-plane angle (rad, the direction of the crop's x axis in the image, y down). The crop is
resampled to the network's 256x256 input with one affine warp; the network returns 478
points in crop pixels with a depth z in the same scale, and a face-presence logit. The
points are mapped back with the inverse of the same affine.

Pixel convention (as :mod:`articast.core.model.camera`): integer coordinates are pixel
centres, in the image and in the crop alike.

Useful indices (MediaPipe's topology, "right" = the person's right, on the image's left in
a non-mirrored frontal view): 13 / 14 inner upper / lower lip midpoints, 0 / 17 outer upper /
lower lip midpoints, 78 / 308 inner right / left lip corners, 61 / 291 outer right / left lip
corners, 33 / 263 right / left eye outer corners, 1 nose tip, 152 chin.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.errors import InputError

INPUT_SIZE = 256
N_LANDMARKS = 478
RIGHT_EYE, LEFT_EYE = 33, 263
"""Outer eye corners: the eye line that sets the ROI angle when re-cropping from landmarks."""


@dataclass(frozen=True, eq=False)
class Roi:
    """A rotated square region of the image.

    centre : (2,) float64 px, image frame (x, y).
    side : float, px.
    angle : float, rad: the crop's x axis points along (cos angle, sin angle) in the image.
    """

    centre: np.ndarray
    side: float
    angle: float = 0.0

    def crop_to_image(self, size: int = INPUT_SIZE) -> np.ndarray:
        """(2, 3) float64 affine mapping crop px (u, v, 1) of a ``size`` crop to image px."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        lin = np.array([[c, -s], [s, c]]) * (self.side / size)
        half = (size - 1) / 2.0
        return np.hstack([lin, (np.asarray(self.centre) - lin @ [half, half])[:, None]])


def roi_from_points(points: np.ndarray, angle: float, scale: float) -> Roi:
    """The square ROI around ``points`` seen in a frame rotated by ``angle``.

    points : (M, 2) float px, image frame. angle : rad. scale : side over the longer side of
    the points' bounding box in the rotated frame.
    """
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    local = np.asarray(points, np.float64) @ rot  # coordinates along the crop's axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    return Roi(rot @ ((lo + hi) / 2.0), float(np.max(hi - lo) * scale), float(angle))


def roi_from_landmarks(landmarks: np.ndarray, scale: float = 1.5) -> Roi:
    """MediaPipe's re-crop policy: eye-line angle, bounding square of all points x ``scale``.

    landmarks : (478, 3) float px, image frame (only x, y are used).
    """
    eye = landmarks[LEFT_EYE, :2] - landmarks[RIGHT_EYE, :2]
    angle = float(np.arctan2(eye[1], eye[0]))
    return roi_from_points(landmarks[:, :2], angle, scale)


def crop(image_bgr: np.ndarray, roi: Roi, size: int = INPUT_SIZE) -> np.ndarray:
    """The network input for ``roi``.

    image_bgr : (H, W, 3) uint8 BGR. size : network input side, px. Returns (1, size, size,
    3) float32 RGB in [0, 1]; parts of the ROI outside the image are black.
    """
    if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or image_bgr.dtype != np.uint8:
        raise InputError(f"expected an (H, W, 3) uint8 BGR image, got {image_bgr.shape}")
    if not (np.all(np.isfinite(roi.centre)) and np.isfinite(roi.side) and roi.side > 1.0):
        raise InputError(f"degenerate ROI: centre {roi.centre}, side {roi.side}")
    m = roi.crop_to_image(size)
    patch = cv2.warpAffine(image_bgr, m, (size, size),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    # BGR to RGB in OpenCV and the scaling in place: the same floats as
    # patch[:, :, ::-1].astype(np.float32) * (1 / 255), in a fifth of the time
    rgb = cv2.cvtColor(patch, cv2.COLOR_BGR2RGB).astype(np.float32)
    rgb *= 1.0 / 255.0
    return rgb[None]


def landmarks_in_roi(session, image_bgr: np.ndarray, roi: Roi) -> tuple[np.ndarray, float]:
    """Run the landmark network on ``roi``.

    session : onnxruntime.InferenceSession of a MediaPipe face landmark model with an NHWC
        square input: FaceLandmarker v2 (256 px, 478 points) or FaceMesh v1 (192 px, 468).
    image_bgr : (H, W, 3) uint8 BGR.

    Returns
    -------
    landmarks : (N, 3) float64; x, y px in the image frame (may fall outside the image);
        z relative depth in the same px scale (smaller = closer to the camera).
    presence : float in [0, 1], the network's face-presence probability.
    """
    size = int(session.get_inputs()[0].shape[1])
    outputs = session.run(None, {session.get_inputs()[0].name: crop(image_bgr, roi, size)})
    raw = outputs[0].reshape(-1, 3).astype(np.float64)
    logit = float(np.clip(outputs[1].ravel()[0], -100.0, 100.0))
    # the network's x, y are in [0, size] with pixel edges at integers: centres are at +0.5
    m = roi.crop_to_image(size)
    xy = (raw[:, :2] - 0.5) @ m[:, :2].T + m[:, 2]
    z = raw[:, 2] * (roi.side / size)
    return np.column_stack([xy, z]), 1.0 / (1.0 + np.exp(-logit))

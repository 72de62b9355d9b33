"""BlazeFace short-range face detection (MediaPipe's ``face_detector.tflite``) on onnxruntime.

The network sees a 128x128 RGB image in [-1, 1] and scores 896 SSD anchors; each anchor
regresses a box and 6 keypoints. This module does what MediaPipe's graph does around it, in
numpy: letterbox the frame, generate the anchors, decode, threshold, weighted non-maximum
suppression, and map back to image pixels.

Keypoints, in the person's terms: 0 right eye, 1 left eye, 2 nose tip, 3 mouth centre,
4 right ear tragion, 5 left ear tragion (the person's right eye is on the image's left in a
non-mirrored frontal view).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from articast.core.errors import InputError

INPUT_SIZE = 128
STRIDES = (8, 16, 16, 16)
"""SSD layers of the short-range model; each anchor position carries one anchor per layer."""
N_KEYPOINTS = 6


@dataclass(frozen=True)
class DetectorPolicy:
    """Thresholds of :func:`detect` (MediaPipe's defaults).

    min_score : minimum sigmoid score of a detection.
    min_suppression_iou : boxes overlapping a better one by more than this IoU are merged
        into it (weighted non-maximum suppression).
    tiles : where the whole frame shows no face, the detector looks again in overlapping
        square tiles of this fraction of the frame's shorter side (half a tile apart; None:
        not). The short-range model sees the frame shrunk to 128 px: a face under ~1/6 of
        the frame's longer side is too small for it (a speaker at a lectern filmed at
        1280x720, a face ~100 px wide: found in 0 frames, so never enrolled); in a tile it
        is twice as large or more. Only a frame with no face pays for the tiles (a 640x360
        frame: 18 tiles).
    """

    min_score: float = 0.5
    min_suppression_iou: float = 0.3
    tiles: float | None = 0.5


@dataclass(frozen=True, eq=False)
class Detection:
    """One detected face.

    box : (4,) float64 px, image frame: x0, y0, x1, y1.
    keypoints : (6, 2) float64 px, image frame (see the module docstring for their order).
    score : float in [0, 1].
    """

    box: np.ndarray
    keypoints: np.ndarray
    score: float


def anchors() -> np.ndarray:
    """Anchor centres of the short-range model.

    Returns
    -------
    ndarray (896, 2) float32, normalised input coordinates in [0, 1] (x, y). Anchor sizes are
    fixed to 1 (MediaPipe's ``fixed_anchor_size``), so only the centres matter.
    """
    out = []
    for stride in sorted(set(STRIDES)):
        per_cell = STRIDES.count(stride) * 2  # two aspect ratios per layer, both of size 1
        n = INPUT_SIZE // stride
        yy, xx = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        grid = np.stack([xx.ravel(), yy.ravel()], axis=1)
        out.append(np.repeat(grid, per_cell, axis=0))
    return np.concatenate(out).astype(np.float32)


def letterbox(image_bgr: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Fit the image into the 128x128 input keeping its aspect ratio (padding with zeros).

    image_bgr : (H, W, 3) uint8 BGR.

    Returns
    -------
    tensor : (1, 128, 128, 3) float32 RGB in [-1, 1] (padding is -1, i.e. black).
    scale : input px per image px.
    offset : (2,) float64, input px of the image's top-left corner (x, y).
    """
    if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or image_bgr.dtype != np.uint8:
        raise InputError(f"expected an (H, W, 3) uint8 BGR image, got {image_bgr.shape}")
    h, w = image_bgr.shape[:2]
    scale = INPUT_SIZE / max(h, w)
    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
    small = cv2.resize(image_bgr, (nw, nh), interpolation=cv2.INTER_AREA)
    canvas = np.zeros((INPUT_SIZE, INPUT_SIZE, 3), np.uint8)
    ox, oy = (INPUT_SIZE - nw) // 2, (INPUT_SIZE - nh) // 2
    canvas[oy : oy + nh, ox : ox + nw] = small
    tensor = canvas[:, :, ::-1].astype(np.float32) * (2.0 / 255.0) - 1.0
    return tensor[None], scale, np.array([ox, oy], np.float64)


def decode(regressors: np.ndarray, logits: np.ndarray, min_score: float) -> tuple[np.ndarray, ...]:
    """Decode the raw outputs into boxes, keypoints and scores above ``min_score``.

    regressors : (896, 16) float32, raw box + keypoint regressions, input px.
    logits : (896,) float32, raw scores.

    Returns
    -------
    boxes : (M, 4) x0, y0, x1, y1; keypoints : (M, 6, 2); scores : (M,) — in normalised input
    coordinates [0, 1].
    """
    scores = 1.0 / (1.0 + np.exp(-np.clip(logits.astype(np.float64), -100.0, 100.0)))
    keep = np.flatnonzero(scores >= min_score)
    reg = regressors[keep].astype(np.float64) / INPUT_SIZE
    centre = anchors()[keep].astype(np.float64)
    xy = reg[:, 0:2] + centre
    half = reg[:, 2:4] / 2.0
    boxes = np.concatenate([xy - half, xy + half], axis=1)
    keypoints = reg[:, 4:].reshape(-1, N_KEYPOINTS, 2) + centre[:, None, :]
    return boxes, keypoints, scores[keep]


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one (4,) box with (M, 4) boxes (x0, y0, x1, y1) -> (M,)."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0.0, None), axis=1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray,
                 min_iou: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """MediaPipe's weighted non-maximum suppression.

    The best remaining detection absorbs every detection overlapping it by more than
    ``min_iou``; its box and keypoints become their score-weighted mean, its score stays the
    best one. Shapes as returned by :func:`decode`; returns (box (4,), keypoints (6, 2),
    score) best first.
    """
    order = np.argsort(-scores)
    boxes, keypoints, scores = boxes[order], keypoints[order], scores[order]
    remaining = np.ones(len(scores), bool)
    out = []
    for i in range(len(scores)):
        if not remaining[i]:
            continue
        group = remaining & (iou(boxes[i], boxes) > min_iou)
        group[i] = True
        w = scores[group] / scores[group].sum()
        box = (boxes[group] * w[:, None]).sum(axis=0)
        kps = (keypoints[group] * w[:, None, None]).sum(axis=0)
        out.append((box, kps, float(scores[i])))
        remaining &= ~group
    return out


def detect(session, image_bgr: np.ndarray,
           policy: DetectorPolicy = DetectorPolicy()) -> list[Detection]:
    """Detect faces in one frame.

    session : onnxruntime.InferenceSession of the BlazeFace short-range model (NHWC input).
    image_bgr : (H, W, 3) uint8 BGR frame.

    Returns
    -------
    list of :class:`Detection` in image px, best score first (empty when no face).
    """
    faces = _detect_once(session, image_bgr, policy)
    if faces or policy.tiles is None:
        return faces
    h, w = image_bgr.shape[:2]
    side = max(16, int(round(min(h, w) * policy.tiles)))
    if side >= max(h, w):
        return faces
    step = max(1, side // 2)
    found: list[Detection] = []
    for y in sorted({*range(0, max(h - side, 0) + 1, step), max(h - side, 0)}):
        for x in sorted({*range(0, max(w - side, 0) + 1, step), max(w - side, 0)}):
            shift = np.array([x, y], np.float64)
            for d in _detect_once(session, image_bgr[y:y + side, x:x + side], policy):
                found.append(Detection(d.box + np.tile(shift, 2), d.keypoints + shift,
                                       d.score))
    found.sort(key=lambda d: -d.score)
    kept: list[Detection] = []
    for d in found:  # a face seen in two overlapping tiles is one face: the best box kept
        if all(_iou(d.box, k.box) <= policy.min_suppression_iou for k in kept):
            kept.append(d)
    return kept


def _detect_once(session, image_bgr: np.ndarray, policy: DetectorPolicy) -> list[Detection]:
    tensor, scale, offset = letterbox(image_bgr)
    regressors, logits = session.run(None, {session.get_inputs()[0].name: tensor})
    boxes, kps, scores = decode(regressors[0], logits[0, :, 0], policy.min_score)
    faces = []
    for box, keypoints, score in weighted_nms(boxes, kps, scores, policy.min_suppression_iou):
        box_px = _to_image(box.reshape(2, 2), scale, offset).ravel()
        faces.append(Detection(box_px, _to_image(keypoints, scale, offset), score))
    return faces


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    x0, y0 = np.maximum(a[:2], b[:2])
    x1, y1 = np.minimum(a[2:], b[2:])
    inter = max(0.0, float(x1 - x0)) * max(0.0, float(y1 - y0))
    union = float(np.prod(a[2:] - a[:2]) + np.prod(b[2:] - b[:2])) - inter
    return inter / union if union > 0 else 0.0


def _to_image(points: np.ndarray, scale: float, offset: np.ndarray) -> np.ndarray:
    """Normalised input coordinates (..., 2) -> image px (..., 2)."""
    return (points * INPUT_SIZE - offset) / scale

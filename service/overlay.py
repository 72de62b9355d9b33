"""Drawing a fit over the image it was fitted to: how a person checks the tracker on their
own clip (``track --overlay``, ``enroll``'s contact sheet, the benchmarks' grids, the
``serve --preview`` picture).

The fitted mesh is drawn thin and translucent (green when the frame is ok, red when not) so
the face stays visible under it; the lip contours of an enrolled speaker are drawn on top,
one pixel wide: the outer contour in yellow, the inner in magenta.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

MESH_OK = (60, 200, 60)
MESH_LOST = (60, 60, 230)
OUTER_LIP = (0, 230, 255)
INNER_LIP = (255, 0, 255)
MESH_OPACITY = 0.35
_SHIFT = 4  # fractional bits of the drawn coordinates (sub-pixel, anti-aliased lines)


def lip_contours(speaker: Any) -> list[tuple[np.ndarray, tuple[int, int, int]]]:
    """(model point indices, colour) of the outer and inner lip contours of an enrolled
    speaker (``articast.core.faces.speaker.Speaker``); [] for another model."""
    if speaker is None:
        return []
    from articast.core.faces.scheme import (
        LIP_INNER_LOWER,
        LIP_INNER_UPPER,
        LIP_OUTER_LOWER,
        LIP_OUTER_UPPER,
        mediapipe_scheme,
    )

    where = {int(p): i for i, p in enumerate(mediapipe_scheme(speaker.rig).points)}
    out = []
    for contour, colour in ((LIP_OUTER_UPPER, OUTER_LIP), (LIP_OUTER_LOWER, OUTER_LIP),
                            (LIP_INNER_UPPER, INNER_LIP), (LIP_INNER_LOWER, INNER_LIP)):
        if all(int(i) in where for i in contour):
            out.append((np.array([where[int(i)] for i in contour]), colour))
    return out


def projected(model: Any, camera: Any, result: Any) -> np.ndarray | None:
    """Image coordinates (N, 2) of the model's points at the result's state, None if any is
    not finite (a diverged fit draws nothing rather than garbage)."""
    uv = camera.project_head(model.shape(np.asarray(result.alpha, float)), result.pose)
    return uv if np.all(np.isfinite(uv)) else None


def draw(image: np.ndarray, uv: np.ndarray, model: Any, ok: bool,
         contours: list[tuple[np.ndarray, tuple[int, int, int]]],
         opacity: float = MESH_OPACITY) -> np.ndarray:
    """``image`` (BGR uint8, not modified) with the mesh at pixel coordinates ``uv`` drawn
    thin and translucent (``opacity``), and the lip ``contours`` on top."""
    q = np.round(uv * (1 << _SHIFT)).astype(np.int32)
    out = image.copy()
    if len(model.triangles):
        mesh = image.copy()
        cv2.polylines(mesh, [q[t] for t in model.triangles], True,
                      MESH_OK if ok else MESH_LOST, 1, cv2.LINE_AA, shift=_SHIFT)
        out = cv2.addWeighted(mesh, opacity, image, 1.0 - opacity, 0.0)
    for idx, colour in contours:
        cv2.polylines(out, [q[idx]], False, colour, 1, cv2.LINE_AA, shift=_SHIFT)
    return out


def draw_fit(image: np.ndarray, model: Any, camera: Any, result: Any,
             contours: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = ()) -> np.ndarray:
    """The whole frame with the fit drawn on it (the frame itself when nothing projects)."""
    uv = projected(model, camera, result)
    return image.copy() if uv is None else draw(image, uv, model, bool(result.ok),
                                                list(contours))


def fit_tile(image: np.ndarray, model: Any, camera: Any, result: Any,
             contours: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = (),
             crop: float = 1.5, size: int = 320) -> np.ndarray:
    """A ``size`` px square around the fitted face (``crop`` times its extent), magnified
    first and drawn on after, so the lines stay one pixel wide on a small face."""
    uv = projected(model, camera, result)
    if uv is None:
        return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    c = uv.mean(0)
    half = crop * 0.5 * float(np.max(np.ptp(uv, 0)))
    x0, y0 = c - half
    k = size / (2 * half)
    warp = np.array([[k, 0, -k * x0], [0, k, -k * y0]], np.float32)
    tile = cv2.warpAffine(image, warp, (size, size), flags=cv2.INTER_LINEAR)
    return draw(tile, uv * k - [k * x0, k * y0], model, bool(result.ok), list(contours))


def label(tile: np.ndarray, text: str) -> np.ndarray:
    """``text`` in white on a dark band at the top left of ``tile`` (modified and returned)."""
    cv2.putText(tile, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(tile, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    return tile


def grid(tiles: list[np.ndarray], columns: int = 3) -> np.ndarray:
    """Tiles of one size in rows of ``columns`` (the last row padded with black)."""
    blank = np.zeros_like(tiles[0])
    padded = tiles + [blank] * (-len(tiles) % columns)
    return np.vstack([np.hstack(padded[r:r + columns])
                      for r in range(0, len(padded), columns)])


class VideoOut:
    """An MP4 (OpenCV's mp4v) written frame by frame; one clear error if it cannot be."""

    def __init__(self, path: Any, fps: float, size: tuple[int, int]) -> None:
        from articast.core.errors import InputError

        self.path = path
        self._w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"),
                                  float(fps if fps and fps > 0 else 30.0), size)
        if not self._w.isOpened():
            raise InputError(f"--overlay {path}: OpenCV cannot write an mp4v video there "
                             "(a folder that does not exist, or no MPEG-4 encoder in this "
                             "OpenCV build)")

    def write(self, frame: np.ndarray) -> None:
        self._w.write(frame)

    def close(self) -> None:
        self._w.release()

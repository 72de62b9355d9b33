"""Drawing a fit over the image it was fitted to: how a person checks the tracker on their
own clip (``track --overlay``, ``enroll``'s contact sheet, the benchmarks' grids, the
``serve --preview`` picture).

The fitted mesh is drawn thin and translucent (green when the frame is ok, red when not) so
the face stays visible under it; the lip contours of an enrolled speaker are drawn on top,
one pixel wide: the outer contour in yellow, the inner in magenta. A desk speaker's tracked
upper face is drawn too (issue 39): each eye's lids (cyan, closing with the tracked closure)
and iris (blue, moved by the tracked gaze), and each brow (orange, raised by the tracked
raise), placed on the fitted eye corners.

``track --overlay`` writes H.264 through PyAV (VP9 when no H.264 encoder is present), which
browsers play, and adds a magnified inset of the face when the face is small in the frame
(a 1080x1920 phone clip).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import TYPE_CHECKING, Any, cast

import cv2
import numpy as np

if TYPE_CHECKING:
    from av.video.stream import VideoStream

MESH_OK = (60, 200, 60)
MESH_LOST = (60, 60, 230)
OUTER_LIP = (0, 230, 255)
INNER_LIP = (255, 0, 255)
EYE_LIDS = (255, 255, 0)  # cyan (BGR)
IRIS = (255, 60, 0)  # blue
BROWS = (0, 140, 255)  # orange
EYEBALL_RADIUS_MM = 11.5  # where a gaze angle puts the iris: eyeball radius x sin(angle)
IRIS_RADIUS_MM = 5.9  # when the enrolment measured none
#: MediaPipe landmarks of the eye corners (outer, inner), the speaker's left eye first
EYE_CORNERS = ((263, 362), (33, 133))
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


@dataclass(frozen=True)
class UpperLayout:
    """Where an enrolled desk speaker's eyes and brows sit on their model: each eye's corner
    points (model indices; left eye first, the speaker's own) and the enrolment's open eye,
    neutral brow heights above the eye line and iris radius (``UpperReference``)."""

    corners: tuple[tuple[int, int], tuple[int, int]]
    open_mm: tuple[float, float]
    brows_mm: tuple[float, float, float, float]
    iris_radius_mm: tuple[float, float]


def upper_layout(speaker: Any) -> UpperLayout | None:
    """The layout of an enrolled speaker whose model holds the eye corners and whose
    enrolment calibrated the upper face; None otherwise (a head rig, an older speaker)."""
    if speaker is None or getattr(speaker, "upper", None) is None:
        return None
    from articast.core.faces.scheme import mediapipe_scheme

    where = {int(p): i for i, p in enumerate(mediapipe_scheme(speaker.rig).points)}
    if len(where) != speaker.model.n_points or not all(
            i in where for pair in EYE_CORNERS for i in pair):
        return None
    ref = speaker.upper
    iris = tuple(r if r > 0 else IRIS_RADIUS_MM for r in ref.iris_radius_mm)
    return UpperLayout(tuple((where[a], where[b]) for a, b in EYE_CORNERS),  # type: ignore[arg-type]
                       tuple(ref.open_mm), tuple(ref.brows_mm), iris)  # type: ignore[arg-type]


def _curve(a: np.ndarray, b: np.ndarray, lift: np.ndarray, n: int = 9) -> np.ndarray:
    """Points from ``a`` to ``b`` bowed by ``lift`` at the middle (a parabola), (n, 3)."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    return a + (b - a) * s + lift * (4.0 * s * (1.0 - s))


def upper_lines(layout: UpperLayout, shape: np.ndarray,
                upper: Any) -> list[tuple[np.ndarray, tuple[int, int, int], bool]]:
    """Head-frame polylines (points (n, 3), colour, closed) of the tracked eyes and brows at
    the model geometry ``shape`` (N, 3); [] when the frame has no upper face."""
    if upper is None:
        return []
    out: list[tuple[np.ndarray, tuple[int, int, int], bool]] = []
    up = np.array([0.0, 1.0, 0.0])
    closure = (upper.closure_left, upper.closure_right)
    raises = ((upper.raise_inner_left_mm, upper.raise_outer_left_mm),
              (upper.raise_inner_right_mm, upper.raise_outer_right_mm))
    gaze = (upper.gaze_yaw_deg, upper.gaze_pitch_deg)
    for side, (outer, inner) in enumerate(layout.corners):
        a, b = shape[outer], shape[inner]
        centre = 0.5 * (a + b)
        opening = layout.open_mm[side]
        if upper.eyes_ok and closure[side] is not None:
            now = opening * (1.0 - float(np.clip(closure[side], 0.0, 1.0)))
            lower = _curve(a, b, -0.4 * opening * up)
            upper_lid = _curve(a, b, (now - 0.4 * opening) * up)
            out.append((np.vstack([lower, upper_lid[::-1]]), EYE_LIDS, True))
            if now > 0.3 * opening and gaze[0] is not None and gaze[1] is not None:
                yaw, pitch = np.radians(gaze[0]), np.radians(gaze[1])
                mid = centre + (0.5 * now - 0.4 * opening) * up
                c = mid + EYEBALL_RADIUS_MM * np.array([np.sin(yaw), np.sin(pitch), 0.0])
                r = min(layout.iris_radius_mm[side], 0.5 * now)
                t = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
                ring = c + r * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1)
                out.append((ring, IRIS, True))
        inner_raise, outer_raise = raises[side]
        if upper.brows_ok and inner_raise is not None and outer_raise is not None:
            h_in = layout.brows_mm[2 * side] + inner_raise
            h_out = layout.brows_mm[2 * side + 1] + outer_raise
            brow_in, brow_out = b + h_in * up, a + h_out * up
            out.append((_curve(brow_in, brow_out, 0.15 * float(np.linalg.norm(a - b)) * up),
                        BROWS, False))
    return out


def projected(model: Any, camera: Any, result: Any) -> np.ndarray | None:
    """Image coordinates (N, 2) of the model's points at the result's state, None if any is
    not finite (a diverged fit draws nothing rather than garbage)."""
    uv = camera.project_head(model.shape(np.asarray(result.alpha, float)), result.pose)
    return uv if np.all(np.isfinite(uv)) else None


def projected_upper(model: Any, camera: Any, result: Any, layout: UpperLayout | None
                    ) -> list[tuple[np.ndarray, tuple[int, int, int], bool]]:
    """The eyes' and brows' polylines of ``upper_lines`` in image coordinates (the finite
    ones)."""
    if layout is None or getattr(result, "upper", None) is None:
        return []
    shape = model.shape(np.asarray(result.alpha, float))
    out = []
    for pts, colour, closed in upper_lines(layout, shape, result.upper):
        uv = camera.project_head(pts, result.pose)
        if np.all(np.isfinite(uv)):
            out.append((uv, colour, closed))
    return out


def draw(image: np.ndarray, uv: np.ndarray, model: Any, ok: bool,
         contours: list[tuple[np.ndarray, tuple[int, int, int]]],
         opacity: float = MESH_OPACITY,
         lines: Sequence[tuple[np.ndarray, tuple[int, int, int], bool]] = ()) -> np.ndarray:
    """``image`` (BGR uint8, not modified) with the mesh at pixel coordinates ``uv`` drawn
    thin and translucent (``opacity``), the lip ``contours`` on top, and the eyes' and brows'
    ``lines`` (pixel polylines, colour, closed) two pixels wide."""
    q = np.round(uv * (1 << _SHIFT)).astype(np.int32)
    out = image.copy()
    if len(model.triangles):
        mesh = image.copy()
        cv2.polylines(mesh, [q[t] for t in model.triangles], True,
                      MESH_OK if ok else MESH_LOST, 1, cv2.LINE_AA, shift=_SHIFT)
        out = cv2.addWeighted(mesh, opacity, image, 1.0 - opacity, 0.0)
    for idx, colour in contours:
        cv2.polylines(out, [q[idx]], False, colour, 1, cv2.LINE_AA, shift=_SHIFT)
    for pts, colour, closed in lines:
        cv2.polylines(out, [np.round(pts * (1 << _SHIFT)).astype(np.int32)], closed, colour, 2,
                      cv2.LINE_AA, shift=_SHIFT)
    return out


def draw_fit(image: np.ndarray, model: Any, camera: Any, result: Any,
             contours: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = (),
             upper: UpperLayout | None = None) -> np.ndarray:
    """The whole frame with the fit drawn on it (the frame itself when nothing projects);
    with ``upper`` (:func:`upper_layout`) the tracked eyes and brows too."""
    uv = projected(model, camera, result)
    if uv is None:
        return image.copy()
    return draw(image, uv, model, bool(result.ok), list(contours),
                lines=projected_upper(model, camera, result, upper))


def fit_tile(image: np.ndarray, model: Any, camera: Any, result: Any,
             contours: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = (),
             crop: float = 1.5, size: int = 320, upper: UpperLayout | None = None,
             centre_y: float = 0.0) -> np.ndarray:
    """A ``size`` px square around the fitted face (``crop`` times its extent), magnified
    first and drawn on after, so the lines stay one pixel wide on a small face.
    ``centre_y`` moves the square's centre by that fraction of its side (- up)."""
    uv = projected(model, camera, result)
    if uv is None:
        return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    half = crop * 0.5 * float(np.max(np.ptp(uv, 0)))
    c = uv.mean(0) + [0.0, 2 * half * centre_y]
    x0, y0 = c - half
    k = size / (2 * half)
    warp = np.array([[k, 0, -k * x0], [0, k, -k * y0]], np.float32)
    tile = cv2.warpAffine(image, warp, (size, size), flags=cv2.INTER_LINEAR)
    shift = np.array([k * x0, k * y0])
    lines = [(pts * k - shift, colour, closed)
             for pts, colour, closed in projected_upper(model, camera, result, upper)]
    return draw(tile, uv * k - shift, model, bool(result.ok), list(contours), lines=lines)


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


def _encoder() -> tuple[str, str]:
    """(PyAV codec, pixel format) of the first encoder browsers play that this PyAV has:
    H.264 (libx264, else OpenH264), else VP9."""
    import av

    have = av.codecs_available
    for name in ("libx264", "libopenh264", "libvpx-vp9"):
        if name in have:
            try:
                av.codec.Codec(name, "w")
            except Exception:  # listed but not an encoder in this build
                continue
            return name, "yuv420p"
    raise RuntimeError("no H.264 or VP9 encoder")


class VideoOut:
    """A video browsers play (H.264 in MP4, or VP9; ``.webm`` asks for VP9) written frame by
    frame through PyAV; one clear error if it cannot be. Odd frame sizes are padded by a
    pixel (4:2:0 video needs even ones)."""

    def __init__(self, path: Any, fps: float, size: tuple[int, int]) -> None:
        import av

        from articast.core.errors import InputError

        self.path = path
        self._size = (int(size[0]), int(size[1]))
        w, h = (v + v % 2 for v in self._size)
        rate = Fraction(float(fps if fps and fps > 0 else 30.0)).limit_denominator(1001)
        try:
            codec, pix = (("libvpx-vp9", "yuv420p") if str(path).lower().endswith(".webm")
                          else _encoder())
            options = {"movflags": "+faststart"} if codec != "libvpx-vp9" else {}
            self._out = av.open(str(path), "w", options=options)
            self._stream = cast("VideoStream", self._out.add_stream(codec, rate=rate))
        except Exception as exc:  # (PyAV's errors: a folder missing, no encoder, a format)
            raise InputError(f"--overlay {path}: cannot write a video there "
                             f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                             ) from None
        self._stream.width, self._stream.height, self._stream.pix_fmt = w, h, pix
        if codec == "libx264":
            self._stream.options = {"crf": "20", "preset": "veryfast"}
        elif codec == "libvpx-vp9":
            self._stream.options = {"crf": "32", "b": "0", "deadline": "realtime",
                                    "cpu-used": "8"}
        self.codec = codec

    def write(self, frame: np.ndarray) -> None:
        import av

        h, w = frame.shape[:2]
        if (w, h) != (self._stream.width, self._stream.height):
            frame = cv2.copyMakeBorder(frame, 0, self._stream.height - h, 0,
                                       self._stream.width - w, cv2.BORDER_REPLICATE)
        for packet in self._stream.encode(av.VideoFrame.from_ndarray(
                np.ascontiguousarray(frame), format="bgr24")):
            self._out.mux(packet)

    def close(self) -> None:
        try:
            for packet in self._stream.encode():
                self._out.mux(packet)
        finally:
            self._out.close()


class Overlay:
    """``track --overlay``: each frame with its fit drawn (mesh, lips, eyes, brows) and, when
    the face is small in the frame (``zoom`` auto: under :data:`SMALL_FACE` of the frame's
    height) or always (``zoom`` on), a magnified inset of the face in the corner away from
    it, chosen on the first frame and kept."""

    SMALL_FACE = 0.25
    INSET = 0.5  # of the frame's shorter side

    def __init__(self, writer: Any, model: Any, camera: Any, contours: Sequence = (),
                 upper: UpperLayout | None = None, zoom: str = "auto") -> None:
        self.writer, self.model, self.camera = writer, model, camera
        self.contours, self.upper, self.zoom = list(contours), upper, zoom
        self._corner: tuple[int, int] | None = None
        self._inset = zoom == "on"

    def write(self, image: np.ndarray, result: Any) -> None:
        out = draw_fit(image, self.model, self.camera, result, self.contours, self.upper)
        h, w = image.shape[:2]
        uv = projected(self.model, self.camera, result)
        if self._corner is None and uv is not None:  # the first frame with a fit decides
            if self.zoom == "auto":
                self._inset = float(np.ptp(uv[:, 1])) < self.SMALL_FACE * h
            cx, cy = uv.mean(0)
            self._corner = (0 if cx > w / 2 else 1, 0 if cy > h / 2 else 1)
        if self._inset and self._corner is not None:
            size = int(self.INSET * min(w, h)) // 2 * 2
            tile = fit_tile(image, self.model, self.camera, result, self.contours, crop=1.25,
                            size=size, upper=self.upper, centre_y=-0.05)
            x0 = 0 if self._corner[0] == 0 else w - size
            y0 = 0 if self._corner[1] == 0 else h - size
            out[y0:y0 + size, x0:x0 + size] = tile
            cv2.rectangle(out, (x0, y0), (x0 + size - 1, y0 + size - 1), (255, 255, 255), 1)
        self.writer.write(out)

"""One peer tracker in its own venv, fed frames by ``benchmarks/peers.py`` (not run by hand).

    <venv>/bin/python benchmarks/peer_worker.py METHOD CONFIG_JSON OUT_NPZ  < frames

Standard input: one JSON line ``{"n": N, "h": H, "w": W}``, then N raw BGR uint8 frames of
H x W x 3 bytes each. The worker loads its model first (not timed), then for each frame times
exactly the tracker's own per-frame work (colour conversion, detection when its loop needs it,
landmarks) with ``time.perf_counter`` (wall) and ``time.process_time`` (CPU of all its
threads); reading the frame from the pipe is outside the timing. It writes OUT_NPZ:
``points`` (N, K, 2) image px (NaN where no face), ``ms``, ``cpu_ms`` (N,) and ``scheme``.

This file imports only numpy, OpenCV and the peer's own package: it runs in the peer's venv
(``benchmarks/setup_peers.py``), never in articast's process.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np


def read_exactly(stream, size: int) -> bytes:
    data = bytearray()
    while len(data) < size:
        chunk = stream.read(size - len(data))
        if not chunk:
            raise EOFError(f"frame stream ended after {len(data)} of {size} bytes")
        data += chunk
    return bytes(data)


class MediaPipeFaceMesh:
    """mediapipe's legacy FaceMesh solution (its own detector, tracking and smoothing), the
    468 points of FaceMesh v1 (``refine_landmarks=False``), video mode."""

    scheme = "mediapipe"
    refine = False  # mediapipe's refine_landmarks (the irises: MediaPipeIris)

    def __init__(self, cfg: dict, w: int, h: int) -> None:
        import mediapipe as mp

        self.mesh = mp.solutions.face_mesh.FaceMesh(
            static_image_mode=False, max_num_faces=1, refine_landmarks=self.refine,
            min_detection_confidence=0.5, min_tracking_confidence=0.5)
        self.size = np.array([w, h], float)

    def __call__(self, frame: np.ndarray) -> np.ndarray | None:
        import cv2

        out = self.mesh.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        if not out.multi_face_landmarks:
            return None
        lm = out.multi_face_landmarks[0].landmark
        return np.array([[p.x, p.y] for p in lm]) * self.size


class MediaPipeIris(MediaPipeFaceMesh):
    """mediapipe's legacy FaceMesh with ``refine_landmarks=True`` (its attention model): the
    468 points and the irises, 468-472 (the speaker's left: centre, then four round its edge)
    and 473-477 (right). Only ``benchmarks/blinks.py``'s independent gaze reference."""

    scheme = "mediapipe_iris"
    refine = True


class Dlib68:
    """dlib's HOG face detector and its 68-point shape predictor (iBUG 300-W scheme). The
    loop a user would write: the detector on the whole frame when the face is lost, else on
    the previous face's box grown by half its size on each side (faster, the same detector)."""

    scheme = "ibug68"

    def __init__(self, cfg: dict, w: int, h: int) -> None:
        import dlib

        self.dlib = dlib
        self.detector = dlib.get_frontal_face_detector()
        self.predictor = dlib.shape_predictor(cfg["model"])
        self.box = None
        self.w, self.h = w, h

    def _detect(self, grey: np.ndarray):
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            gx, gy = (x1 - x0) // 2, (y1 - y0) // 2
            ox, oy = max(0, x0 - gx), max(0, y0 - gy)
            sub = grey[oy:min(self.h, y1 + gy), ox:min(self.w, x1 + gx)]
            found = self.detector(np.ascontiguousarray(sub), 0)
            if len(found):
                r = max(found, key=lambda r: r.area())
                return self.dlib.rectangle(r.left() + ox, r.top() + oy, r.right() + ox,
                                           r.bottom() + oy)
        found = self.detector(grey, 0)
        return max(found, key=lambda r: r.area()) if len(found) else None

    def __call__(self, frame: np.ndarray) -> np.ndarray | None:
        import cv2

        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        rect = self._detect(grey)
        if rect is None:
            self.box = None
            return None
        self.box = (rect.left(), rect.top(), rect.right(), rect.bottom())
        shape = self.predictor(grey, rect)
        return np.array([[p.x, p.y] for p in shape.parts()], float)


class OpenSeeFace:
    """OpenSeeFace's ``Tracker`` (its own detector, crops and landmark model), one face, one
    thread, gaze off (lips only), otherwise ``facetracker.py``'s defaults. Its 66 points
    (68 with the pupils) follow iBUG's up to 47; the mouth is not iBUG's: 58 and 62 are the
    corners (shared by both contours; its own ``mouth_wide`` feature uses them), 48-52 the
    upper and 53-57 the lower outer lip, 59-61 the upper and 63-65 the lower inner lip
    (checked by drawing the indices on a frame)."""

    scheme = "openseeface"

    def __init__(self, cfg: dict, w: int, h: int) -> None:
        sys.path.insert(0, cfg["source"])
        from tracker import Tracker

        self.tracker = Tracker(w, h, model_type=int(cfg["model_type"]), threshold=None,
                               detection_threshold=0.6, max_threads=1, max_faces=1,
                               discard_after=10, scan_every=3, silent=True,
                               model_dir=cfg["source"] + "/models", no_gaze=True,
                               use_retinaface=0, max_feature_updates=900, static_model=True,
                               try_hard=False)

    def __call__(self, frame: np.ndarray) -> np.ndarray | None:
        faces = self.tracker.predict(frame)
        faces = [f for f in faces if getattr(f, "success", True) and f.lms is not None]
        if not faces:
            return None
        lms = np.asarray(faces[0].lms)[:66]
        return np.column_stack([lms[:, 1], lms[:, 0]]).astype(float)  # (y, x) -> (x, y)


METHODS = {"mediapipe": MediaPipeFaceMesh, "mediapipe_iris": MediaPipeIris, "dlib": Dlib68,
           "openseeface": OpenSeeFace}


def main() -> None:
    method, cfg, out = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3]
    stream = sys.stdin.buffer
    head = json.loads(stream.readline())
    n, h, w = int(head["n"]), int(head["h"]), int(head["w"])
    import cv2

    cv2.setNumThreads(1)
    tracker = METHODS[method](cfg, w, h)
    points, ms, cpu = [], np.zeros(n), np.zeros(n)
    for i in range(n):
        frame = np.frombuffer(read_exactly(stream, h * w * 3), np.uint8).reshape(h, w, 3)
        t0, c0 = time.perf_counter(), time.process_time()
        p = tracker(frame)
        ms[i], cpu[i] = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        points.append(p)
    k = max((len(p) for p in points if p is not None), default=0)
    arr = np.full((n, k, 2), np.nan)
    for i, p in enumerate(points):
        if p is not None:
            arr[i] = p
    np.savez(out, points=arr, ms=ms, cpu_ms=cpu, scheme=tracker.scheme)


if __name__ == "__main__":
    main()

"""FaceFinder: detector + 478-point landmarks, with MediaPipe's real-time policy.

``find`` runs the detector (or takes a given box) and then the landmarks; ``track`` re-crops
from the previous frame's landmarks and runs only the landmarks (the detector runs only when
the face is lost: the caller calls ``find`` again when ``track`` returns ``None``).

The onnxruntime sessions are created once by :meth:`FaceFinder.load` (one intra-op thread
by default) and reused for every frame. Nothing here reads a clock, a camera or a socket.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import InputError, ModelFileError
from articast.core.faces.detector import Detection, DetectorPolicy, detect
from articast.core.faces.landmarks import Roi, landmarks_in_roi, roi_from_landmarks

DETECTOR_FILE = "face_detector.onnx"
LANDMARKS_FILE = "face_landmarks_v2.onnx"
LANDMARK_MODELS = {"v2": LANDMARKS_FILE, "v1": "face_landmarks_v1.onnx"}
"""The bundled landmark networks: FaceLandmarker v2 (478 points, 256 px input: the finder's
default, for finding and enrolment) and FaceMesh v1 (468 points, 192 px input, ~4x cheaper:
the live tracker's per-frame measurement; docs/FACES.md)."""
FINDER_NETWORK = "v2"
"""The network :meth:`FaceFinder.load` reads by default: the finding landmarks."""


def models_dir() -> Path:
    """The folder of the bundled ONNX models and the canonical face (package data)."""
    return Path(str(resources.files("articast.core.faces") / "models"))


@dataclass(frozen=True)
class FinderPolicy:
    """How :class:`FaceFinder` crops and when it gives up.

    detector : thresholds of the face detector.
    scale : ROI side over the face's extent (detection box or landmarks' bounding square).
    min_presence : a face whose landmark presence probability is below this is not a face.
    refine : after a detection (or a given box), re-crop this many times from the landmarks
        found and run the landmarks again, so that ``find`` lands where ``track`` would (on
        a still synthetic desk frame, ``track`` after ``find`` moves the lip points by
        <= 0.9 px with 1 pass, <= 0.55 px with 2).
    keep_roi : ``track`` keeps the previous frame's crop while the crop grown from the
        previous landmarks differs from it by less than this fraction of its side (centre
        shift and side change; angle in rad), so a still face is seen through a still crop:
        on the still segments of two synthetic sequences per rig this cuts the lip-aperture
        jitter (desk 0.21 / 0.46 % -> 0.19 / 0.23 %, head 0.58 / 0.43 % -> 0.15 / 0.12 % of
        the lip width) at the same accuracy. 0 re-crops on every frame (MediaPipe's policy).
    """

    detector: DetectorPolicy = DetectorPolicy()
    scale: float = 1.5
    min_presence: float = 0.5
    refine: int = 2
    keep_roi: float = 0.02


@dataclass(frozen=True, eq=False)
class Face:
    """A face found in one frame.

    box : (4,) float64 px, image frame: x0, y0, x1, y1, the bounds of the landmarks' x, y.
    landmarks : (478, 3) float64: x, y px in the image frame (MediaPipe FaceLandmarker
        topology; points may fall outside the image); z relative depth in the same px scale
        (origin near the face centre, smaller = closer to the camera).
    score : float in [0, 1], the landmark network's face-presence probability.
    roi : the crop the landmarks were found in (``track`` may reuse it), or None.
    """

    box: np.ndarray
    landmarks: np.ndarray
    score: float
    roi: Roi | None = None

    def __post_init__(self) -> None:
        box = np.array(self.box, dtype=np.float64).reshape(-1)
        landmarks = np.array(self.landmarks, dtype=np.float64)
        if box.shape != (4,) or landmarks.ndim != 2 or landmarks.shape[1] != 3:
            raise InputError(f"a face needs box (4,) and landmarks (N, 3), got {box.shape} "
                             f"and {landmarks.shape}")
        for name, value in (("box", box), ("landmarks", landmarks)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "score", float(self.score))


class FaceFinder:
    """Detector and landmark sessions, loaded once.

    Use ``FaceFinder.load()``; then ``find(image)`` on the first frame and after a loss,
    ``track(image, previous)`` on the frames in between.
    """

    def __init__(self, detector_session, landmarks_session,
                 policy: FinderPolicy = FinderPolicy()) -> None:
        self._detector = detector_session
        self._landmarks = landmarks_session
        self.policy = policy

    @classmethod
    def load(cls, models: str | Path | None = None, *, threads: int = 1,
             policy: FinderPolicy = FinderPolicy(), landmarks: str = FINDER_NETWORK,
             detector: Any = None) -> FaceFinder:
        """Create the onnxruntime sessions once.

        models : folder holding ``face_detector.onnx`` and the landmark network (default: the
            bundled ones). threads : intra-op threads of each session. landmarks : which
            landmark network, a key of :data:`LANDMARK_MODELS`. detector : an already loaded
            detector session to share (another finder's ``detector_session``), else loaded.
        """
        if landmarks not in LANDMARK_MODELS:
            raise InputError(f"landmarks must be one of {sorted(LANDMARK_MODELS)}, "
                             f"got {landmarks!r}")
        import onnxruntime as ort

        folder = Path(models) if models is not None else models_dir()
        if int(threads) < 1:
            raise InputError(f"threads must be >= 1, got {threads}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        sessions = []
        for name in (DETECTOR_FILE, LANDMARK_MODELS[landmarks]):
            path = folder / name
            if not path.is_file():
                raise ModelFileError(f"face model not found: {path}")
            if name == DETECTOR_FILE and detector is not None:
                sessions.append(detector)
                continue
            sessions.append(ort.InferenceSession(str(path), opts,
                                                 providers=["CPUExecutionProvider"]))
        return cls(sessions[0], sessions[1], policy)

    def with_policy(self, policy: FinderPolicy) -> FaceFinder:
        """The same sessions (nothing loaded again) under another policy: e.g. the live
        reader's crop (``FusionPolicy.reader_keep_roi``) for a finder loaded with the
        finding one's."""
        return type(self)(self._detector, self._landmarks, policy)

    @property
    def detector_session(self):
        """The detector's onnxruntime session (NHWC 128x128 input)."""
        return self._detector

    @property
    def landmarks_session(self):
        """The landmark model's onnxruntime session (NHWC square input: 256 px v2, 192 v1)."""
        return self._landmarks

    # ------------------------------------------------------------------ per frame
    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        """All faces the detector sees in ``image_bgr`` (H, W, 3) uint8 BGR, best first."""
        return detect(self._detector, image_bgr, self.policy.detector)

    def find(self, image_bgr: np.ndarray, *, box: np.ndarray | None = None) -> Face | None:
        """Find the most confident face, running the detector.

        image_bgr : (H, W, 3) uint8 BGR frame.
        box : optional (4,) px x0, y0, x1, y1 in the image frame. When given, the detector
            is skipped and the landmarks run on the upright square of side max(width,
            height) centred on the box (the box is the crop, not the face: use it for views
            the detector cannot see, or to skip it where the face does not move in the
            frame). Head-mounted camera (the synthetic ``head`` rig, lower face filling the
            frame): the detector does fire there; ``track`` then keeps a still crop (see
            ``keep_roi``), which is as steady as a fixed box such as the 800 px square
            ``(-80, -280, 720, 520)`` above a 640x480 frame with ``FinderPolicy(refine=0)``
            (lip-aperture jitter on still frames 0.12-0.17 % of the lip width for both,
            0.43-0.58 % when re-cropping every frame).

        Returns
        -------
        :class:`Face`, or ``None`` when no face is detected or its presence is too low.
        """
        if box is None:
            roi = self._detection_roi(image_bgr)
            if roi is None:
                return None
        else:
            roi = box_roi(box)
        face = self._landmarks_face(image_bgr, roi)
        for _ in range(int(self.policy.refine)):
            if face is None:
                break
            face = self._landmarks_face(image_bgr, self._recrop(face))
        return face

    def track(self, image_bgr: np.ndarray, previous: Face) -> Face | None:
        """Landmarks in a crop grown from ``previous``'s landmarks, without the detector.

        The crop is ``previous.roi`` while the face has moved less than the policy's
        ``keep_roi`` (see :class:`FinderPolicy`). Returns ``None`` when the presence drops
        below the policy's minimum (face lost).
        """
        roi = self._recrop(previous)
        kept = previous.roi
        if kept is not None and self.policy.keep_roi > 0 and _close(roi, kept,
                                                                    self.policy.keep_roi):
            roi = kept
        return self._landmarks_face(image_bgr, roi)

    # ------------------------------------------------------------------ helpers
    def _detection_roi(self, image_bgr: np.ndarray) -> Roi | None:
        found = self.detect(image_bgr)
        if not found:
            return None
        best = found[0]
        eye = best.keypoints[1] - best.keypoints[0]
        centre = (best.box[:2] + best.box[2:]) / 2.0
        side = float(np.max(best.box[2:] - best.box[:2])) * self.policy.scale
        return Roi(centre, side, float(np.arctan2(eye[1], eye[0])))

    def _recrop(self, face: Face) -> Roi:
        return roi_from_landmarks(face.landmarks, self.policy.scale)

    def _landmarks_face(self, image_bgr: np.ndarray, roi: Roi) -> Face | None:
        landmarks, presence = landmarks_in_roi(self._landmarks, image_bgr, roi)
        if presence < self.policy.min_presence or not np.all(np.isfinite(landmarks)):
            return None
        xy = landmarks[:, :2]
        box = np.concatenate([xy.min(axis=0), xy.max(axis=0)])
        return Face(box, landmarks, presence, roi)


def reader_seed(face: Face) -> Face:
    """A face found by the finding landmarks (v2, 478 points) as the previous reading of the
    live reader (v1, 468 points): the points both networks share, no crop to keep (the
    reader grows its own from them)."""
    return Face(face.box, np.asarray(face.landmarks)[:468], face.score, None)


def read_every_frame(reader: FaceFinder, images, faces,
                     progress: Callable[[], object] | None = None) -> np.ndarray:
    """The reader's landmarks (F, 468, 3) on a sequence of frames, each read in a crop grown
    from its previous reading, seeded from ``faces`` (the finding landmarks' faces, None where
    none was found) after a loss; NaN where no face was read."""
    out = np.full((len(images), 468, 3), np.nan)
    prev = None
    for i, (image, face) in enumerate(zip(images, faces, strict=True)):
        if prev is None and face is not None:
            prev = reader_seed(face)
        got = reader.track(image, prev) if prev is not None else None
        prev = got
        if got is not None:
            out[i] = got.landmarks
        if progress is not None:
            progress()
    return out


def _close(new: Roi, old: Roi, tol: float) -> bool:
    """Whether two crops differ by less than ``tol`` x side (centre, side) and ``tol`` rad."""
    return bool(np.linalg.norm(np.asarray(new.centre) - old.centre) < tol * old.side
                and abs(new.side / old.side - 1.0) < tol
                and abs((new.angle - old.angle + np.pi) % (2.0 * np.pi) - np.pi) < tol)


def box_roi(box: np.ndarray) -> Roi:
    """The upright square ROI of side max(width, height) centred on ``box`` (4,) px."""
    box = np.asarray(box, np.float64).reshape(-1)
    if box.shape != (4,) or not np.all(np.isfinite(box)) or np.any(box[2:] <= box[:2]):
        raise InputError(f"box must be finite x0, y0, x1, y1 with x1 > x0, y1 > y0, got {box}")
    return Roi((box[:2] + box[2:]) / 2.0, float(np.max(box[2:] - box[:2])), 0.0)

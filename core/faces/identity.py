"""Is the tracked face the speaker folder's person? A face-geometry signature (issue 39, row 5).

The landmark networks place their points on the face's own shape: the eye corners, the nose
(bridge, tip, wings), the brows and the face's outline sit where that face has them. The
signature is that shape without what speech, pose and scale change:

1. the :data:`POINTS` only: eye corners, nose, brows, forehead, cheeks and the upper face
   outline (80 of MediaPipe's points; not the lips, jaw or lids, which speech and blinks move);
2. each frame's points, read as a weak-perspective 3D shape in head axes, aligned to the
   canonical face by a similarity (rotation, translation, scale: the distance to the camera
   and the head's turn go, the proportions stay) and scaled to unit size;
3. over frames: the median of each aligned coordinate and its frame-to-frame standard
   deviation (what pose, expression and the network's noise move it by on this face).

The distance of a run of frames to a signature is the root mean square, over the
coordinates, of the difference of their medians in units of the signature's frame-to-frame
spread (floored at :data:`SPREAD_FLOOR` of the face's size). Measured on 22 real clips of
19 people, 40 frames each that no enrolment saw, against every clip's enrolment
(``benchmarks/identity_check.py``, docs/RESULTS.md): a clip's own folder, and another clip of
the same person, read 0.2-1.9; other people's folders 1.0-7 (median 3.2-3.6).

Signatures are per landmark network (FaceMesh v1's and FaceLandmarker v2's points differ a
little): a speaker folder keeps one per network it was enrolled with, and a run of frames is
compared with the signature of the network that read it.

Everything here is pure: arrays in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from articast.core.errors import ModelFileError

EYES = (33, 133, 362, 263, 130, 359, 243, 463)
NOSE = (6, 168, 197, 195, 5, 4, 1, 2, 98, 327, 129, 358, 48, 278, 64, 294, 94, 19)
BROWS = (70, 63, 105, 66, 107, 300, 293, 334, 296, 336, 46, 276, 52, 282, 65, 295, 55, 285)
OUTLINE = (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 109, 67, 103, 54, 21, 162, 127,
           234, 93, 151, 9, 8)
CHEEKS = (116, 345, 50, 280, 205, 425, 123, 352, 117, 346, 111, 340, 143, 372)
POINTS = np.array(EYES + NOSE + BROWS + OUTLINE + CHEEKS, dtype=np.intp)
"""MediaPipe landmark indices of the signature: what speech and blinks do not move."""

WARN_DISTANCE = 2.0
"""A run of :data:`CHECK_FRAMES` frames farther than this from the speaker folder's signature
is warned about. Chosen on half of the people of the real clips and checked on the other
half, then swapped (``benchmarks/identity_check.py``, docs/RESULTS.md): the four choices
(1.2 x the largest own distance of a half, per network) were 1.76, 2.22, 1.92 and 1.94; their
mean, rounded. On all 22 clips of 19 people: no own folder above it (own: at most 1.85 for
FaceMesh v1, 1.62 for v2), 86 % (v1) and 88 % (v2) of other people's folders above it."""
SPREAD_FLOOR = 1e-3
"""The least frame-to-frame spread of a coordinate, in units of the face's size: a still
enrolment does not make every small difference count."""
MIN_FRAMES = 20
"""The fewest frames a signature or a comparison is made from."""

_TO_HEAD = np.diag([1.0, -1.0, -1.0])  # camera axes (y down, z away) -> head axes


def _reference() -> np.ndarray:
    """The canonical face's :data:`POINTS` (head axes), centred, unit RMS size."""
    from articast.core.faces.canonical import canonical_face

    ref = canonical_face().vertices_mm[POINTS]
    ref = ref - ref.mean(axis=0)
    return ref / math.sqrt(float((ref**2).sum(axis=1).mean()))


_REF: np.ndarray | None = None


def aligned_shapes(landmarks: np.ndarray) -> np.ndarray:
    """Landmarks (F, L >= 468, 3) image px + relative depth -> (F, 80, 3) the :data:`POINTS`
    in head axes, each frame aligned to the canonical face by a similarity and scaled to unit
    RMS size. Frames with a non-finite point are dropped."""
    global _REF
    if _REF is None:
        _REF = _reference()
    ref = _REF
    lm = np.asarray(landmarks, np.float64)
    if lm.ndim != 3 or lm.shape[1] < 468 or lm.shape[2] != 3:
        raise ValueError(f"expected landmarks (F, >=468, 3), got {lm.shape}")
    x = lm[:, POINTS] @ _TO_HEAD
    x = x[np.isfinite(x).all(axis=(1, 2))]
    out = np.empty_like(x)
    for f, shape in enumerate(x):
        c = shape - shape.mean(axis=0)
        u, sv, vt = np.linalg.svd(ref.T @ c)
        d = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0
        rot = u @ np.diag([1.0, 1.0, d]) @ vt
        y = c @ rot.T
        out[f] = y / math.sqrt(max(float((y**2).sum(axis=1).mean()), 1e-300))
    return out


@dataclass(frozen=True, eq=False)
class FaceSignature:
    """One face's shape as one landmark network reads it.

    network : the landmark network ("v1" FaceMesh, "v2" FaceLandmarker).
    median : (80, 3) the aligned :data:`POINTS`' median over the frames (unit size).
    spread : (80, 3) their frame-to-frame standard deviation, floored at
        :data:`SPREAD_FLOOR`.
    frames : how many frames it was made from.
    """

    network: str
    median: np.ndarray
    spread: np.ndarray
    frames: int

    def to_dict(self) -> dict[str, Any]:
        return {"network": self.network, "frames": self.frames,
                "median": np.round(self.median, 6).ravel().tolist(),
                "spread": np.round(self.spread, 6).ravel().tolist()}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> FaceSignature:
        try:
            network = str(d["network"])
            frames = int(d["frames"])
            median = np.array(d["median"], np.float64).reshape(len(POINTS), 3)
            spread = np.array(d["spread"], np.float64).reshape(len(POINTS), 3)
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{where}: identity signature is malformed ({exc})") from None
        if (not np.isfinite(median).all() or not np.isfinite(spread).all()
                or (spread < SPREAD_FLOOR).any() or np.abs(median).max() > 10
                or spread.max() > 10 or frames < 1):
            raise ModelFileError(f"{where}: identity signature must hold finite numbers "
                                 f"(spread >= {SPREAD_FLOOR}) from at least one frame")
        return cls(network, median, spread, frames)


def signature(landmarks: np.ndarray, network: str) -> FaceSignature | None:
    """The signature of the face in ``landmarks`` (F, L >= 468, 3) read by ``network``; None
    with fewer than :data:`MIN_FRAMES` usable frames."""
    shapes = aligned_shapes(landmarks)
    if len(shapes) < MIN_FRAMES:
        return None
    return FaceSignature(network, np.median(shapes, axis=0),
                         np.maximum(shapes.std(axis=0), SPREAD_FLOOR), len(shapes))


def distance(sig: FaceSignature, landmarks: np.ndarray) -> float | None:
    """How far the face in ``landmarks`` (F, L >= 468, 3, read by ``sig``'s network) is from
    ``sig``, in its frame-to-frame spreads (RMS over the coordinates); None with fewer than
    :data:`MIN_FRAMES` usable frames."""
    shapes = aligned_shapes(landmarks)
    if len(shapes) < MIN_FRAMES:
        return None
    z = (np.median(shapes, axis=0) - sig.median) / sig.spread
    return float(np.sqrt(np.mean(z**2)))


NETWORK_POINTS = {468: "v1", 478: "v2"}
"""A reading's network by its number of points: FaceMesh v1 468, FaceLandmarker v2 478."""
CHECK_FRAMES = 40
"""Readings of one network compared with the signature: the first ones of a session."""


class IdentityWatch:
    """Gathers a session's first readings and compares them with the speaker folder's
    signatures, once.

    ``add(landmarks)`` with each fresh reading (L, 3) (468 or 478 points, image px); it
    returns the distance the first time :data:`CHECK_FRAMES` readings of a network the
    folder has a signature of are in, and None before and after.
    """

    def __init__(self, signatures: dict[str, FaceSignature], frames: int = CHECK_FRAMES
                 ) -> None:
        self.signatures = dict(signatures)
        self.frames = max(int(frames), MIN_FRAMES)
        self._seen: dict[str, list[np.ndarray]] = {}
        self.distance: float | None = None
        self.network: str | None = None

    @property
    def done(self) -> bool:
        return self.network is not None or not self.signatures

    def add(self, landmarks: np.ndarray) -> float | None:
        if self.done:
            return None
        lm = np.asarray(landmarks, np.float64)
        net = NETWORK_POINTS.get(lm.shape[0]) if lm.ndim == 2 and lm.shape[1] == 3 else None
        if net is None or net not in self.signatures or not np.isfinite(lm).all():
            return None
        seen = self._seen.setdefault(net, [])
        seen.append(lm)
        if len(seen) < self.frames:
            return None
        d = distance(self.signatures[net], np.stack(seen))
        self._seen.clear()
        self.network = net
        self.distance = d
        return d

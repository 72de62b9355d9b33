"""A speaker folder: the one thing a user carries from ``enroll`` to ``track``, ``serve`` and
``export-fap``.

::

    SPEAKER_DIR/
      speaker.json      kind "articast-speaker", version 1: name, rig, landmark scheme,
                        scale assumption, enrolment statistics of the tracking residual,
                        enrolment report
      model.npz         the face model (kind face-model)
      appearance.npz    the appearance model (kind appearance-model)
      camera.json       the camera the speaker was enrolled with (kind articast-camera)
      points_v1.npz     how the live landmark reader (FaceMesh v1) reads this face (kind
                        landmark-observation; optional: without it the model's own points
                        stand in)
      points_v2.npz     how the finding landmarks (FaceLandmarker v2) read it: offline
                        ``track``'s second reader (optional: without it one reader)

speaker.json's optional ``motion`` holds the motion model's process noise learned from the
clip (``q`` per unknown; without it the defaults); its optional ``upper`` the speaker's own
open-eye, closed-eye, neutral-brow and gaze references
(:class:`~articast.core.faces.upper.UpperReference`; without it the eyes and brows are
reported absent, ``not_calibrated``). Its optional ``identity`` holds the face's shape as
each landmark network read it on the enrolment clip (:mod:`articast.core.faces.identity`):
a session warns when the face it tracks does not look like it (without it: not checked).

The residual statistics are what ``ok`` is judged against on live frames: a frame whose
robust residual is far above what the enrolment clip itself produced is not the speaker
(another face, a hand, noise), whatever the running level says.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.appearance.models import AppearanceModel
from articast.core.errors import InputError, ModelFileError
from articast.core.faces.identity import FaceSignature
from articast.core.faces.upper import UpperReference
from articast.core.model.camera import Camera
from articast.core.model.face import FaceModel
from articast.core.tracking.kalman import MotionNoise
from articast.core.tracking.points import PointModel

SPEAKER_KIND = "articast-speaker"
SPEAKER_VERSION = 1
FILES = ("speaker.json", "model.npz", "appearance.npz", "camera.json")


@dataclass(frozen=True)
class ResidualStats:
    """Robust residual of the final models on enrolment frames not used for training.

    median, p95, p99 : per-descriptor residual (the tracker's ``robust_residual``).
    frames : how many frames they summarise.
    """

    median: float
    p95: float
    p99: float
    frames: int

    def to_dict(self) -> dict[str, float | int]:
        return {"median": self.median, "p95": self.p95, "p99": self.p99, "frames": self.frames}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> ResidualStats:
        try:
            vals = [float(d[k]) for k in ("median", "p95", "p99")]
            frames = int(d["frames"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{where}: residual statistics are malformed ({exc})") from None
        if not all(math.isfinite(v) and v > 0 for v in vals) or frames < 1:
            raise ModelFileError(f"{where}: residual statistics must be positive numbers")
        # a p99 of 1e308 judged every frame "ok" (the live tracker compares against it)
        if max(vals) > 1e6 or frames > 10**9 or not vals[0] <= vals[1] <= vals[2]:
            raise ModelFileError(f"{where}: residual statistics must be ordered (median <= "
                                 "p95 <= p99), within 1e6, over at most 1e9 frames")
        return cls(*vals, frames)


@dataclass(frozen=True, eq=False)
class Speaker:
    """An enrolled speaker: model, appearance, camera and enrolment statistics."""

    model: FaceModel
    appearance: AppearanceModel
    camera: Camera
    residual: ResidualStats
    rig: str = "desk"
    scheme: str = "mediapipe-478"
    name: str = "speaker"
    report: dict[str, Any] = field(default_factory=dict)
    points: PointModel | None = None
    motion_noise: MotionNoise | None = None
    upper: UpperReference | None = None
    finder_points: PointModel | None = None
    identity: dict[str, FaceSignature] = field(default_factory=dict)
    """network -> the face's signature as that landmark network read it (empty: a folder
    enrolled before the identity check)"""

    def save(self, folder: str | os.PathLike[str]) -> None:
        """Write the folder (created if needed); speaker.json last, so a folder with it is
        complete."""
        d = Path(folder)
        if d.exists() and not d.is_dir():
            raise InputError(f"{d}: exists and is not a folder")
        d.mkdir(parents=True, exist_ok=True)
        self.model.save(d / "model.npz")
        self.appearance.save(d / "appearance.npz")
        self.camera.save(d / "camera.json")
        if self.points is not None:
            self.points.save(d / f"points_{self.points.network}.npz")
        if self.finder_points is not None:
            self.finder_points.save(d / f"points_{self.finder_points.network}.npz")
        meta = {"kind": SPEAKER_KIND, "version": SPEAKER_VERSION, "name": self.name,
                "rig": self.rig, "scheme": self.scheme, "residual": self.residual.to_dict(),
                "report": self.report}
        if self.motion_noise is not None:
            meta["motion"] = {"q": [float(x) for x in self.motion_noise.q],
                              "v0": [float(x) for x in self.motion_noise.initial_velocity_sd]}
        if self.upper is not None:
            meta["upper"] = self.upper.to_dict()
        if self.identity:
            meta["identity"] = [sig.to_dict() for _, sig in sorted(self.identity.items())]
        tmp = d / "speaker.json.tmp"
        tmp.write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, d / "speaker.json")

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> Speaker:
        """Load a speaker folder; one clear error naming the folder and what is wrong."""
        d = Path(folder)
        if not d.is_dir():
            raise InputError(f"{d}: not a speaker folder (make one with 'articast enroll')")
        missing = [f for f in FILES if not os.path.lexists(d / f)]
        if missing:
            raise ModelFileError(f"{d}: not a complete speaker folder, missing "
                                 f"{', '.join(missing)} (make one with 'articast enroll')")
        where = str(d / "speaker.json")
        from articast.core.safe_io import read_regular_bytes

        try:
            meta = json.loads(read_regular_bytes(d / "speaker.json", 16 << 20))
        except InputError as exc:
            raise ModelFileError(str(exc)) from None
        except RecursionError:
            raise ModelFileError(f"{where}: JSON nested too deeply") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelFileError(f"{where}: not readable JSON ({exc})") from None
        if not isinstance(meta, dict) or meta.get("kind") != SPEAKER_KIND:
            raise ModelFileError(f"{where}: not an articast speaker file")
        if meta.get("version") != SPEAKER_VERSION:
            raise ModelFileError(f"{where}: version {meta.get('version')!r} is not supported "
                                 f"(this articast reads version {SPEAKER_VERSION})")
        rig = meta.get("rig")
        if rig not in ("desk", "head"):
            raise ModelFileError(f"{where}: rig must be 'desk' or 'head', got {rig!r}")
        model = FaceModel.load(d / "model.npz")
        points = None
        if os.path.lexists(d / "points_v1.npz"):  # there: it must load (a FIFO, a folder
            # or a dangling link was skipped silently, the speaker tracked without its points)
            points = PointModel.load(d / "points_v1.npz", model.n_params)
        finder_points = None
        if os.path.lexists(d / "points_v2.npz"):
            finder_points = PointModel.load(d / "points_v2.npz", model.n_params)
            if finder_points.network != "v2":
                raise ModelFileError(f"{d / 'points_v2.npz'}: an observation model of the "
                                     f"{finder_points.network!r} landmarks, not 'v2'")
        return cls(model, AppearanceModel.load(d / "appearance.npz", model),
                   Camera.load(d / "camera.json"),
                   ResidualStats.from_dict(meta.get("residual") or {}, where), rig,
                   str(meta.get("scheme", "")), str(meta.get("name", "speaker")),
                   meta.get("report") if isinstance(meta.get("report"), dict) else {},
                   points, _motion_noise(meta.get("motion"), model.n_params, where),
                   None if meta.get("upper") is None
                   else UpperReference.from_dict(meta["upper"], where), finder_points,
                   _identity(meta.get("identity"), where))


def _identity(d: Any, where: str) -> dict[str, FaceSignature]:
    """speaker.json's ``identity`` list, checked (empty when absent)."""
    if d is None:
        return {}
    if not isinstance(d, list) or len(d) > 8:
        raise ModelFileError(f"{where}: identity must be a list of at most 8 signatures")
    sigs = [FaceSignature.from_dict(x, where) for x in d]
    return {s.network: s for s in sigs}


def _motion_noise(d: Any, k: int, where: str) -> MotionNoise | None:
    """speaker.json's ``motion`` block, checked (None when absent)."""
    if d is None:
        return None
    try:
        q = np.array(d["q"], np.float64)
        v0 = np.array(d["v0"], np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(f"{where}: motion block is malformed ({exc})") from None
    if (q.shape != (k + 6,) or v0.shape != (k + 6,) or not np.isfinite(q).all()
            or not np.isfinite(v0).all() or (q <= 0).any() or (v0 <= 0).any()
            or (q > 1e12).any() or (v0 > 1e6).any()):
        raise ModelFileError(f"{where}: motion block must hold {k + 6} positive finite numbers "
                             "in q and in v0")
    return MotionNoise(q, v0)

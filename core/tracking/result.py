"""What the tracker produces per frame: the record every consumer (CLI, service, FAP) reads."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from articast.core.model.camera import Pose

MAX_T = 1e9
"""A record's time stamp, s: media time from the start (31 years is no recording)."""
MAX_ALPHA = 1e3
"""|alpha| in training standard deviations: real frames stay within ~10."""
MAX_FRAME = 1e12
"""|frame number| of a record (a day at 1000 fps is 8.6e7)."""


@dataclass(frozen=True, eq=False)
class TrackResult:
    """One tracked frame.

    alpha : (K,) articulatory parameters (units of training s.d.).
    pose : head pose, head -> camera.
    ok : False when the frame could not be tracked (occlusion, divergence, lost face); then
        ``reason`` says why and alpha/pose hold the last good state, not a guess. The reason
        starts with a code word: ``blank``, ``no_face``, ``diverged``, ``occluded``,
        ``left_image``, ``not_started``, then ``:`` and a sentence for people.
    residual : cost per descriptor value at the solution (lower is better).
    evals : cost evaluations spent; iterations : optimiser iterations; ms : wall time spent
        (measured by the caller and passed in: core never reads a clock).
    """

    frame: int
    t: float
    alpha: np.ndarray
    pose: Pose
    ok: bool = True
    reason: str = ""
    residual: float = 0.0
    evals: int = 0
    iterations: int = 0
    ms: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    lips: dict[str, float] | None = None
    upper: Any = None  # an articast.core.faces.upper.UpperFace (live tracking), or None

    def to_dict(self, param_names: tuple[str, ...]) -> dict[str, Any]:
        """The JSON-lines record of ``articast track`` (and of ground truth files); with the
        upper face (live tracking) its ``eyes`` and ``brows`` blocks."""
        out = {
            "frame": int(self.frame),
            "t": float(self.t),
            "alpha": {n: float(v) for n, v in zip(param_names, self.alpha, strict=True)},
            "pose": self.pose.to_dict(),
            "lips": None if self.lips is None else dict(self.lips),
            "quality": {
                "ok": bool(self.ok),
                "reason": self.reason,
                "residual": float(self.residual),
                "evals": int(self.evals),
                "iterations": int(self.iterations),
                "ms": float(self.ms),
            },
        }
        if self.upper is not None:
            out["eyes"] = self.upper.eyes_dict()
            out["brows"] = self.upper.brows_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], param_names: tuple[str, ...]) -> TrackResult:
        q = d.get("quality", {})
        alpha = np.array([float(d["alpha"].get(n, 0.0)) for n in param_names])
        t = float(d["t"])
        if not abs(t) <= MAX_T:  # NaN included
            raise ValueError(f"time stamp {t} is not a finite number within {MAX_T:g} s")
        if not np.all(np.abs(alpha) <= MAX_ALPHA):
            raise ValueError(f"alpha values must be finite numbers within ±{MAX_ALPHA:g}")
        frame = d["frame"]  # 1e308 became a 309-digit frame number on the wire
        if isinstance(frame, bool) or not isinstance(frame, int | float) or not (
                abs(frame) <= MAX_FRAME and frame == int(frame)):
            raise ValueError(f"frame {str(frame)[:40]} is not a whole number within "
                             f"{MAX_FRAME:g}")
        return cls(
            frame=int(frame), t=t, alpha=alpha, pose=Pose.from_dict(d["pose"]),
            ok=bool(q.get("ok", True)), reason=str(q.get("reason", "")),
            residual=float(q["residual"]) if q.get("residual") is not None else float("nan"),
            evals=int(q.get("evals", 0)),
            iterations=int(q.get("iterations", 0)), ms=float(q.get("ms", 0.0)),
            lips=d.get("lips"), upper=_upper(d),
        )


def _upper(d: dict[str, Any]) -> Any:
    """A record's ``eyes`` / ``brows`` blocks back as an UpperFace (None without them)."""
    if "eyes" not in d:
        return None
    from articast.core.faces.upper import UpperFace

    return UpperFace.from_dicts(d.get("eyes"), d.get("brows"))

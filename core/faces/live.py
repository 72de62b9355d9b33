"""Tracking an enrolled speaker in real video: the analysis-by-synthesis tracker per frame,
the face finder to start, to verify and to recover (ARCHITECTURE.md, "Real speakers").

Per frame the cost is the tracker's, plus a sparse optical flow of the face's rigid points
(:mod:`articast.core.faces.motion`, ~1 ms): the head's translation it implies is where the
fit starts and centres its pose prior, so that a head coming closer or going away between
two landmark calls is followed (the appearance alone hardly sees the distance).
The landmark model runs

- on the first frame and after every loss: detector + landmarks, then the articulation and
  pose are read off the landmarks (:func:`~articast.core.faces.enrol.state_from_landmarks`)
  and the tracker starts there;
- every ``verify_every`` frames, and on any frame the tracker doubts: landmarks only, in a crop
  grown from the previous landmarks (no detector). No face there -> ``no_face``, and the next
  frame starts over with the detector. A tracked head whose depth is far from the landmarks'
  -> restarted from them (keeping the running residual levels).

The streamed articulation passes a One Euro filter (the fit itself does not).

``ok`` must mean ok. A frame is not ok, with a reason code first in ``reason``:
``blank`` (no contrast), ``no_face`` (the finder sees none), ``diverged`` (the tracker's
robust residual is far above its running level *or* above what the speaker's own enrolment
clip produced: ``residual_factor`` x its 99th percentile), ``occluded`` (a part of the face
the articulation moves, e.g. the chin or the mouth, fits far worse than usual: a hand; the
tracker keeps tracking through it, see ``TrackingPolicy.occlusion_factor``), ``left_image``
(the face left the frame), ``not_started``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from articast.core.faces.enrol import LandmarkScheme
from articast.core.faces.fit import state_from_landmarks
from articast.core.faces.motion import FaceMotion, MotionPolicy
from articast.core.faces.speaker import Speaker
from articast.core.model.camera import Pose
from articast.core.outputs.lips import lips_dict
from articast.core.tracking.filters import OneEuroFilter, OneEuroPolicy
from articast.core.tracking.result import TrackResult
from articast.core.tracking.tracker import Tracker, TrackingPolicy


class FinderLike(Protocol):
    """What the live tracker needs of :class:`articast.core.faces.finder.FaceFinder`."""

    def find(self, image_bgr: np.ndarray) -> Any: ...  # a Face (.landmarks (L, 3)) or None

    def track(self, image_bgr: np.ndarray, previous: Any) -> Any: ...


@dataclass(frozen=True)
class LivePolicy:
    """How often the face finder checks on the tracker, and what the enrolment allows.

    verify_every : frames between two presence checks (landmarks in the previous crop).
    residual_factor : a frame whose robust residual exceeds this many times the enrolment's
        99th percentile is ``diverged``, whatever the running level.
    max_depth_drift : the tracked head is farther or nearer than the landmarks say by more
        than this fraction -> restart from the landmarks (keeping the running levels). On a
        desk camera the depth of a face is weakly observed by its appearance (the mouth's
        size trades with lips1 and jaw2): without this check it drifted by 50 % on a 28 s
        webcam clip, its residual low. The landmarks' own depth is off by up to 28 % on wide
        open mouths, hence the margin. (Their lip aperture, read through the model, is biased
        by several mm on some faces: it is not used to judge the tracker.)
    smoothing : One Euro filter of the articulation streamed (None: the raw fits). The fit
        itself is not filtered: the next frame starts from the raw state, which
        ``extra["alpha_raw"]`` keeps. Reset after any frame that is not ok.
    motion : sparse optical flow of the face's rigid points from the previous frame, and the
        head pose it implies by PnP (:mod:`articast.core.faces.motion`; None: off): its
        translation (the change of distance above all, which the appearance fit hardly sees)
        is where each frame's fit starts and centres its pose prior. Without it, on cap12 the
        head came 30 % closer between two checks, the tracked depth moved 5 % and the lips
        "opened" by 7 mm. Not used with a pose anchor (a head-mounted camera).
    """

    verify_every: int = 10
    residual_factor: float = 3.0
    max_depth_drift: float = 0.3
    smoothing: OneEuroPolicy | None = field(default_factory=OneEuroPolicy)
    motion: MotionPolicy | None = field(default_factory=MotionPolicy)


LIVE_ALPHA_SIGMA = 0.5
"""Motion prior of live tracking (training s.d. per frame, see ``FitPolicy.alpha_sigma``): on
a 31 s webcam clip it brought the still-mouth jitter of the lip aperture from 0.25 to 0.18 %
of the mouth width (the landmark model: 0.21 %) at the same agreement with the landmarks."""


def live_policy(rig: str, **changes: Any) -> TrackingPolicy:
    """The tracking policy of a live speaker on ``rig``: the rig's, plus the motion prior."""
    pol = TrackingPolicy.for_rig(rig, **changes)
    if pol.fit.alpha_sigma is None:
        pol = replace(pol, fit=replace(pol.fit, alpha_sigma=LIVE_ALPHA_SIGMA))
    return pol


class LiveTracker:
    """Tracks an enrolled speaker frame by frame, judging ``ok`` honestly."""

    def __init__(self, speaker: Speaker, finder: FinderLike, scheme: LandmarkScheme,
                 policy: LivePolicy | None = None, tracking: TrackingPolicy | None = None,
                 clock: Callable[[], float] | None = None) -> None:
        self.speaker, self.finder, self.scheme = speaker, finder, scheme
        self.policy = policy or LivePolicy()
        self.tracker = Tracker(speaker.model, speaker.appearance, speaker.camera,
                               tracking or live_policy(speaker.rig), clock=clock)
        self.clock = clock
        self._face: Any = None
        self._since_check = 0
        self._started = False
        self._frame = -1
        self._last: TrackResult | None = None
        sm = self.policy.smoothing
        self._filter = OneEuroFilter(sm) if sm is not None else None
        mo = self.policy.motion  # (not on a head-mounted camera: its pose is anchored)
        self._motion = (FaceMotion(speaker.model, speaker.camera, mo)
                        if mo is not None and self.tracker.policy.pose_anchor_rate is None
                        else None)
        self.finder_calls = 0
        self.restarts = 0  # tracker (re-)starts from landmarks
        self._limit = self.policy.residual_factor * speaker.residual.p99

    # ------------------------------------------------------------------ helpers
    def _finder(self, image: np.ndarray, previous: Any = None) -> Any:
        self.finder_calls += 1
        if previous is not None:
            return self.finder.track(image, previous)
        return self.finder.find(image)

    def _start(self, face: Any, keep_levels: bool = False) -> bool:
        state = state_from_landmarks(self.speaker.model, self.scheme, self.speaker.camera,
                                     face.landmarks)
        if state is None:
            return False
        alpha, pose = state
        self.restarts += 1
        if keep_levels:
            self.tracker.restart(pose, alpha)
        else:
            self.tracker.reset(pose, alpha)
        self._started = True
        self._face = face
        self._since_check = 0
        return True

    def depth_drift(self, result: TrackResult, face: Any) -> float | None:
        """Relative difference between the tracked head's depth and the depth read off the
        landmarks; None if the landmarks give none."""
        state = state_from_landmarks(self.speaker.model, self.scheme, self.speaker.camera,
                                     face.landmarks)
        if state is None:
            return None
        return float(result.pose.translation[2] / state[1].translation[2] - 1.0)

    def _not_ok(self, result: TrackResult, reason: str) -> TrackResult:
        return replace(result, ok=False, reason=reason)

    def _lost(self, t: float, reason: str) -> TrackResult:
        """A not-ok frame holding the last good state (neutral before any)."""
        self._started = False
        self._face = None
        if self._motion is not None:
            self._motion.reset()
        last = self._last
        m = self.speaker.model
        alpha = np.zeros(m.n_params) if last is None else last.alpha
        pose = Pose() if last is None else last.pose
        return TrackResult(self._frame, t, alpha, pose, False, reason,
                           lips=lips_dict(m, alpha))

    # ------------------------------------------------------------------ per frame
    def track(self, image: np.ndarray, t: float) -> TrackResult:
        """Fit one frame (BGR uint8) taken at time ``t`` (s)."""
        self._frame += 1
        t0 = self.clock() if self.clock else 0.0
        result = self._track(image, t)
        ms = (self.clock() - t0) * 1000.0 if self.clock else result.ms
        result = replace(result, frame=self._frame, ms=ms)
        if self._filter is not None:
            if result.ok:
                smooth = self._filter(result.alpha, t)
                result = replace(result, alpha=smooth, lips=lips_dict(self.speaker.model, smooth),
                                 extra={**result.extra, "alpha_raw": result.alpha})
            else:
                self._filter.reset()
        if result.ok:
            self._last = result
        return result

    def _track(self, image: np.ndarray, t: float) -> TrackResult:
        if float(image[::8, ::8].std()) < self.tracker.policy.min_contrast:
            return self._lost(t, "blank: the frame has no contrast")
        hint = None
        if self._motion is not None:  # from the last fit, before any (re)start
            state = self.tracker.state if self._started else None
            moved = self._motion.step(image, *(state or (None, None)))
            hint = None if moved is None else moved.translation
        if not self._started:
            face = self._finder(image)
            if face is None:
                return self._lost(t, "no_face: the face finder sees no face")
            if not self._start(face):
                return self._lost(t, "no_face: the landmarks do not fit the speaker")
        result = self.tracker.track(image, t, translation_hint=hint)
        result = self._judge(result)
        self._since_check += 1
        # an occluded frame is tracked through (robust fit, no restart): the landmarks of a
        # face behind a hand are no better than the fit, and restarting from them every
        # frame would cost a landmark call per frame for as long as the hand stays
        doubt = not result.ok and not result.reason.startswith("occluded")
        if doubt or self._since_check >= self.policy.verify_every:
            self._since_check = 0
            face = self._finder(image, self._face)
            if face is None and self._face is not None:
                face = self._finder(image)  # the crop may have lost it: one full search
            if face is None:
                return self._lost(t, "no_face: the face finder sees no face")
            self._face = face
            drift = self.depth_drift(result, face)
            far = drift is not None and abs(drift) > self.policy.max_depth_drift
            if doubt or far:
                if self._start(face, keep_levels=True):
                    again = self._judge(self.tracker.track(image, t))
                    if again.ok or not result.ok:
                        result = again
        return result

    def _judge(self, result: TrackResult) -> TrackResult:
        if not result.ok:
            return result
        robust = result.extra.get("robust_residual")
        if robust is not None and robust > self._limit:
            return self._not_ok(result, f"diverged: residual {robust:.3g} is above "
                                        f"{self.policy.residual_factor:g} x the enrolment's "
                                        f"99th percentile ({self.speaker.residual.p99:.3g})")
        return result

"""A recorded clip tracked offline: the live tracker's frames smoothed with the frames after.

:class:`~articast.core.faces.live.LiveTracker` streams each frame's estimate as soon as the
frame is fitted; ``articast track`` on a file need not. :class:`OfflineSmoother` takes the
live results in order (:meth:`~OfflineSmoother.add`: bounded memory, the last
:data:`~articast.core.tracking.smoother.LAG` frames' motion steps and a few numbers per
frame) and gives at the end (:meth:`~OfflineSmoother.finish`) every frame's articulation
and head pose smoothed (core/tracking/smoother.py: the motion model's fixed-lag RTS
smoother, the cadence canceller; the One Euro filter forward and back for a clip read by
one tracker, :data:`ONE_EURO_READERS`); :func:`smoothed`
makes the frame's result from them. Frames that are not ok, and frames without a motion
step (a tracker without the fused motion model), are kept as tracked.

A recording may also be read twice (:func:`second_reader`): a second live tracker reads the
finding landmarks (FaceLandmarker v2) on every frame through the speaker's model, with
their own observation model learned at enrolment, and :func:`averaged` takes the mean of the
two smoothed articulations where both trackers have the frame. Two readers through the same
speaker's model, each with its own errors about the lips (no landmark network reads every
face best: docs/history/REAL_SPEAKERS_LOG.md), and the mean of two articulations of a
linear model is one of the model's too; the first tracker's verdicts, head pose and upper face
stand.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from articast.core.faces.live import FusionPolicy, LivePolicy
from articast.core.faces.speaker import Speaker
from articast.core.model.camera import Pose, axis_angle
from articast.core.model.face import FaceModel
from articast.core.outputs.lips import lips_dict
from articast.core.tracking.filters import OneEuroPolicy
from articast.core.tracking.result import TrackResult
from articast.core.tracking.smoother import LAG, FixedLag, State, offline_articulation

ONE_EURO_READERS = 1
""":meth:`OfflineSmoother.for_live` runs the live tracker's One Euro filter forward and back
over the smoothed fits when the clip is read by at most this many trackers: with one
(``track --single-reader``, or a speaker enrolled without the second reader's model) it
does, as sessions 6-8 did with two as well; with two it does not, since session 9. Run twice,
the filter smooths more than live's single pass and rounded fast openings off, and the mean
of two readers' trackers already has less of the noise it takes out. Over the 22 clips
(chosen on half A of the people, checked on half B), two readers without it read the
opening r +0.006 (A) / +0.005 (B) closer to the judge of the other model families, no clip
lower by more than 0.002, the rendered speaker's truth r 0.983 -> 0.984; the still mouth's
jitter rises (docs/TRACKING.md, "Offline without the One Euro filter"). One reader without
it was further from the rendered speaker's truth in mm than the live stream
(tests/test_enroll.py), so one reader keeps it."""


@dataclass(frozen=True)
class Smoothed:
    """One frame's smoothed articulation (K,) and head pose."""

    alpha: np.ndarray
    pose: Pose


class OfflineSmoother:
    """Collects a live tracker's results frame by frame; :meth:`finish` smooths them.

    read_every : the live tracker's reading period (its cadence canceller's; None: none).
    policy : the constants of a One Euro filter run forward and back over the smoothed fits
        (None: no such filter)."""

    def __init__(self, read_every: int | None, lag: int = LAG,
                 policy: OneEuroPolicy | None = None, cadence_rate: float | None = 0.1
                 ) -> None:
        self.read_every, self.policy, self.cadence_rate = read_every, policy, cadence_rate
        self._lag = FixedLag(lag)
        self._t: list[float] = []
        self._ok: list[bool] = []
        self._phase: list[int] = []
        self._start: list[bool] = []
        self._states: list[np.ndarray | None] = []  # per frame: smoothed alpha, rotation, t

    @classmethod
    def for_live(cls, live: Any, readers: int = 1, one_euro: bool | None = None
                 ) -> OfflineSmoother:
        """The smoother of a :class:`~articast.core.faces.live.LiveTracker`'s results, with its
        reading period and cadence canceller (its fusion policy needed). ``readers``: how
        many trackers' articulations of the clip are averaged (1 or 2); its One Euro
        constants are used with ``one_euro``, by default when ``readers`` <=
        :data:`ONE_EURO_READERS`."""
        fu = live.fusion
        use = readers <= ONE_EURO_READERS if one_euro is None else one_euro
        policy = (live.policy.smoothing or OneEuroPolicy()) if use else None
        return cls(fu.read_every, policy=policy, cadence_rate=fu.cadence)

    def add(self, result: TrackResult) -> None:
        """The next frame's live result (its ``extra["motion"]`` and ``extra["phase"]``)."""
        step = result.extra.get("motion") if result.ok else None
        self._t.append(float(result.t))
        self._ok.append(bool(result.ok and step is not None))
        self._phase.append(int(result.extra.get("phase", 0)))
        self._start.append(step is None or not step.linked or bool(result.extra.get("recovered")))
        self._states.extend(_compact(s) for s in self._lag.push(step))

    def finish(self) -> list[Smoothed | None]:
        """Every frame's smoothed articulation and pose, in order (None: keep the frame as
        tracked); the smoother is empty again after."""
        states = [*self._states, *(_compact(s) for s in self._lag.flush())]
        times, phase, starts = np.array(self._t), np.array(self._phase), np.array(self._start, bool)
        ok = np.array(self._ok, bool) & np.array([s is not None for s in states], bool)
        self._t, self._ok, self._phase, self._start, self._states = [], [], [], [], []
        if not ok.any():
            return [None] * len(states)
        k = len(next(s for s in states if s is not None)) - 6
        alpha = np.zeros((len(states), k))
        for i, s in enumerate(states):
            if s is not None:
                alpha[i] = s[:k]
        out_alpha = offline_articulation(alpha, times, ok, phase, starts, self.read_every,
                                         self.cadence_rate, self.policy)
        return [Smoothed(out_alpha[i], Pose(s[k:k + 3], s[k + 3:]))
                if ok[i] and s is not None else None for i, s in enumerate(states)]


def _compact(state: State | None) -> np.ndarray | None:
    """A smoothed state kept per frame: alpha, the rotation's axis-angle, the translation."""
    return None if state is None else np.concatenate([state[0], axis_angle(state[1]), state[2]])


def smoothed(result: TrackResult, frame: Smoothed | None, model: FaceModel) -> TrackResult:
    """``result`` with the smoothed articulation, lips and head pose (as it is for None)."""
    if frame is None:
        return result
    return replace(result, alpha=frame.alpha, pose=frame.pose,
                   lips=lips_dict(model, frame.alpha),
                   extra={**result.extra, "alpha_live": result.alpha})


SECOND_READER = LivePolicy(fusion=FusionPolicy(reader="v2", read_every=1, cadence=None,
                                               reader_gap=None))
"""The second tracker's policy: the finding landmarks read on every frame (no cadence to
cancel), the rest the live tracker's; its raw fits are smoothed (the streamed opening's mix
with the reader's gap, ``FusionPolicy.reader_gap``, would be lost there: not computed)."""


def second_reader(speaker: Speaker) -> Speaker | None:
    """The speaker as the second tracker sees it (:data:`SECOND_READER`): the finding
    landmarks' observation model as its reader's, no upper face (the first tracker's stands);
    None when the enrolment learned none (enrolled before it was, or on a head-mounted
    camera)."""
    if speaker.finder_points is None or speaker.points is None:
        return None
    return replace(speaker, points=speaker.finder_points, upper=None)


def averaged(first: list[Smoothed | None], second: list[Smoothed | None]
             ) -> list[Smoothed | None]:
    """The frames of two trackers of the same clip (each :meth:`OfflineSmoother.finish`):
    the mean articulation where both have the frame, with the first's head pose; the first's
    frame where the second has none; None (kept as tracked) where the first has none."""
    if len(first) != len(second):
        raise ValueError(f"{len(first)} frames against {len(second)}")
    return [a if a is None or b is None else Smoothed(0.5 * (a.alpha + b.alpha), a.pose)
            for a, b in zip(first, second, strict=True)]


READER_GAP = 0.5
"""Offline, the opening is this share of the readers' own lip gap and the rest the smoothed
fit's, as live (``FusionPolicy.reader_gap``): the readers' gap, the mean of both trackers'
readers (FaceMesh v1 and FaceLandmarker v2) on the frame, smoothed over the frame and its two
neighbours (offline has the frame after; no lag)."""


def reader_ratio_of(result: TrackResult) -> float:
    """The result's reader lip-gap ratio (``extra["reader_ratio"]``, set by
    :class:`~articast.core.faces.live.LiveTracker`), NaN where the frame was not read or
    not ok."""
    return float(result.extra.get("reader_ratio", np.nan)) if result.ok else float("nan")


def reader_ratios(results: list[TrackResult]) -> np.ndarray:
    """(F,) :func:`reader_ratio_of` each result."""
    return np.array([reader_ratio_of(r) for r in results], np.float64)


def with_reader_gap(frames: list[Smoothed | None], ratios: list[np.ndarray], model: FaceModel,
                    camera: Any, share: float = READER_GAP) -> list[Smoothed | None]:
    """The smoothed frames with the opening moved to ``share`` x the readers' lip gap +
    (1 - share) x the frame's own projected gap (:func:`~articast.core.faces.lipgap.matched`:
    the smallest step of the articulation that gives it, the width kept). ``ratios``: each
    reader's (F,) series (:func:`reader_ratios`); their mean where finite, then a centred
    [1, 2, 1] / 4 filter over the frames that have one. A frame without a reading keeps
    its smoothed articulation."""
    from articast.core.faces.lipgap import matched, model_ratios

    if share <= 0.0 or not ratios:
        return frames
    stack = np.vstack([np.asarray(r, np.float64) for r in ratios])
    seen = np.isfinite(stack)
    n = seen.sum(axis=0)
    read = np.where(n > 0, np.where(seen, stack, 0.0).sum(axis=0) / np.maximum(n, 1), np.nan)
    ok = np.isfinite(read)
    smooth = read.copy()
    for i in np.flatnonzero(ok):
        w = [(1.0, read[j]) for j in (i - 1, i + 1) if 0 <= j < len(read) and ok[j]]
        smooth[i] = (2.0 * read[i] + sum(v for _, v in w)) / (2.0 + len(w))
    out: list[Smoothed | None] = []
    for f, r in zip(frames, smooth, strict=True):
        if f is None or not np.isfinite(r):
            out.append(f)
            continue
        target = float(r)
        if share < 1.0:
            own = float(model_ratios(model, camera, f.alpha[None], f.pose)[0])
            if not np.isfinite(own):
                out.append(f)
                continue
            target = share * float(r) + (1.0 - share) * own
        out.append(Smoothed(matched(model, camera, f.alpha, f.pose, target), f.pose))
    return out

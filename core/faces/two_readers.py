"""Live tracking with two readers: an opt-in stream that reads lips better, at ~3x the CPU.

The product's live stream (:class:`~articast.core.faces.live.LiveTracker`) reads one landmark
network, FaceMesh v1, on every frame, within issue 38's budget (the whole live face at
<= 2.0x the FaceMesh v1 loop). :class:`TwoReaderTracker` runs a second live tracker on the
same frames that reads FaceLandmarker v2 (the finding landmarks, 478 points) on every frame
through the speaker's own v2 observation model, learned at enrolment (the model ``articast
track``'s offline second reader uses: :func:`~articast.core.faces.offline.second_reader`), and
streams each frame with the mean of the two articulations. No frame after is waited for:
the stream is as late as the slower tracker's frame, no later.

Why the mean: the two networks read lips differently, face by face (they agree at r 0.81-0.97
on enrolment frames, and each is the better on some faces), and the mean of two articulations
of the speaker's linear model is one of the model's. It is the rule offline ``track`` has
used since session 6, carried live unchanged: nothing in it was chosen on the corpus
(docs/RESULTS.md, "Two readers live").

What stays the first tracker's: the verdicts (``ok``, ``occluded``, ``diverged``), the head
pose, the eyes and brows (``upper``), and a frame the second has no estimate for. The second
tracker shares the first's finder (the detector and FaceLandmarker v2: no network loaded
twice); its time is added to the frame's ``ms``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from articast.core.faces.finder import FaceFinder
from articast.core.faces.live import LiveTracker, live_policy
from articast.core.faces.offline import second_reader
from articast.core.faces.scheme import mediapipe_scheme
from articast.core.faces.speaker import Speaker
from articast.core.outputs.lips import lips_dict
from articast.core.tracking.result import TrackResult
from articast.core.tracking.tracker import TrackingPolicy

READERS = (1, 2)
"""How many landmark readers a live stream may read with (1: the product's default)."""


NO_SECOND_MODEL = ("this speaker has no FaceLandmarker v2 observation model (enrolled before "
                   "it was learned, or on a head-mounted camera): enrol again with 'articast "
                   "enroll' to track with two readers")

NOT_FUSED = ("two readers need fused live tracking (a speaker enrolled with the live reader's "
             "observation model)")


def readers_problem(speaker: Speaker, readers: int) -> str:
    """Why ``speaker`` cannot be tracked live with ``readers`` readers ("" if it can): one
    line, for the command or request that asked."""
    if readers not in READERS:
        return f"readers must be 1 or 2, got {readers!r}"
    if readers == 2 and second_reader(speaker) is None:
        return NO_SECOND_MODEL
    return ""


def paired(first: TrackResult, second: TrackResult) -> TrackResult:
    """The frame as :class:`TwoReaderTracker` streams it: ``first`` with the mean of the two
    articulations where both are ok, else ``first`` as it is. Each tracker's own
    articulation is kept in ``extra`` (``alpha_first``, ``alpha_second``); ``lips`` are still
    the first's (no model here: :meth:`TwoReaderTracker.track` measures them on the mean)."""
    if not (first.ok and second.ok):
        return first
    a, b = np.asarray(first.alpha, float), np.asarray(second.alpha, float)
    if a.shape != b.shape:
        raise ValueError(f"articulations of {a.shape} and {b.shape} parameters")
    return replace(first, alpha=0.5 * (a + b),
                   extra={**first.extra, "alpha_first": a, "alpha_second": b})


class TwoReaderTracker:
    """One speaker tracked live by two :class:`~articast.core.faces.live.LiveTracker` s:
    ``first`` (the product's, FaceMesh v1) and ``second`` (FaceLandmarker v2, no upper face),
    each frame the mean of their articulations (:func:`paired`).

    ``first`` is the tracker a caller would use alone: its attributes (``speaker``,
    ``fusion``, ``finder_calls``, ``restarts`` ...) stay the stream's."""

    def __init__(self, first: LiveTracker, second: LiveTracker) -> None:
        if first.fusion is None or second.fusion is None:
            raise ValueError(NOT_FUSED)
        if first.speaker.model.n_params != second.speaker.model.n_params:
            raise ValueError("the two trackers track different models")
        self.first, self.second = first, second

    @classmethod
    def of(cls, first: LiveTracker, tracking: TrackingPolicy | None = None,
           clock: Callable[[], float] | None = None) -> TwoReaderTracker:
        """The pair around ``first``: the second tracker reads FaceLandmarker v2 through the
        speaker's v2 observation model with ``first``'s live policy, ``tracking`` (the
        tracker's policy ``first`` was given; default :func:`live_policy` of the speaker's
        rig) and ``first``'s clock, through ``first``'s finder (the same sessions; the
        reading crops as the policy's reader does). ValueError, one line, for a speaker
        enrolled without that model."""
        if first.fusion is None:
            raise ValueError(NOT_FUSED)
        speaker = second_reader(first.speaker)
        if speaker is None:
            raise ValueError(NO_SECOND_MODEL)
        assert speaker.points is not None
        fusion = replace(first.fusion, reader=speaker.points.network)
        policy = replace(first.policy, fusion=fusion)
        if not isinstance(first.finder, FaceFinder):
            raise ValueError("two readers need the bundled face finder (FaceFinder.load())")
        reader = first.finder.with_policy(fusion.reader_policy())
        second = LiveTracker(speaker, first.finder, mediapipe_scheme(speaker.rig), policy,
                             tracking=tracking or live_policy(speaker.rig),
                             clock=clock or first.clock, reader=reader)
        return cls(first, second)

    @property
    def speaker(self) -> Speaker:
        """The speaker (the first tracker's: its upper face too)."""
        return self.first.speaker

    @property
    def reading(self) -> np.ndarray | None:
        """The first tracker's last reading (its landmarks), as a LiveTracker's."""
        return self.first.reading

    def track(self, image: np.ndarray, t: float) -> TrackResult:
        """Both trackers on the frame (BGR uint8) taken at ``t`` (s); the streamed frame
        (:func:`paired`), its ``ms`` the two trackers' together."""
        a = self.first.track(image, t)
        b = self.second.track(image, t)
        out = paired(a, b)
        lips = out.lips if out is a else lips_dict(self.first.speaker.model, out.alpha)
        return replace(out, lips=lips, ms=a.ms + b.ms)

"""Tracking an enrolled speaker in real video: the analysis-by-synthesis tracker per frame,
the face finder to start, to verify and to recover (ARCHITECTURE.md, "Real speakers").

Per frame the cost is the tracker's, plus a sparse optical flow of the face's rigid points
(:mod:`articast.core.faces.motion`, ~1 ms): the head's translation it implies is where the
fit starts and centres its pose prior, so that a head coming closer or going away between
two landmark calls is followed (the appearance alone hardly sees the distance).
The landmark model runs

- on the first frame and after every loss: detector + landmarks, then the articulation and
  pose are read off the landmarks (:func:`~articast.core.faces.enrol.state_from_landmarks`)
  and the tracker starts there (fused tracking: the reader's landmarks, and after a
  ``diverged`` fit without the detector: ``FusionPolicy.start``, ``.resume``);
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
(the face left the frame), ``not_started``. In fused tracking (``FusionPolicy``) the
landmarks judge: a frame read by the reader is ``diverged`` when its points are far from the
fitted face (``FusionPolicy.agreement``), whatever the appearance residual; an appearance
``occluded`` on lips opened or stretched beyond the enrolment's range, or on a head turned
beyond the rotations its appearance was trained on, is dropped when the landmarks confirm the
fit (:meth:`LiveTracker._unfamiliar`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any, Protocol

import numpy as np

from articast.core.faces import kernels as faces_kernels
from articast.core.faces import lipgap
from articast.core.faces.enrol import LandmarkScheme
from articast.core.faces.finder import FaceFinder, FinderPolicy, reader_seed
from articast.core.faces.fit import fit_pose, state_from_landmarks
from articast.core.faces.lipgap import matched, model_ratios, reader_ratio
from articast.core.faces.motion import FaceMotion, MotionPolicy
from articast.core.faces.speaker import Speaker
from articast.core.faces.upper import UpperTracker
from articast.core.model.camera import Pose, axis_angle, rotation_matrix
from articast.core.outputs.lips import lip_measures, lips_dict
from articast.core.tracking import kernels
from articast.core.tracking.filters import CadenceCanceller, OneEuroFilter, OneEuroPolicy
from articast.core.tracking.fitting import StatePrior
from articast.core.tracking.kalman import ConstantVelocity
from articast.core.tracking.points import PointTerm, state_offset
from articast.core.tracking.result import TrackResult
from articast.core.tracking.tracker import Evidence, Tracker, TrackingPolicy, pixel_spread


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
        "opened" by 7 mm. Not used with a pose anchor (a head-mounted camera), nor with fused
        tracking (the reader's landmarks give the head's distance every frame).
    fusion : fused tracking (:class:`FusionPolicy`; None: the appearance fit alone, the
        landmarks only to find, check and restart). Used for speakers enrolled with an
        observation model of the reader (``Speaker.points``: every desk-camera ``articast
        enroll`` of this version); a speaker enrolled before is tracked without it, and so is
        a head-mounted camera's (seen from below the nose, the reader's lips are 12-17 px off
        on the rendered head rig, docs/FACES.md: its fits were not ok on half the frames).
    """

    verify_every: int = 10
    residual_factor: float = 3.0
    max_depth_drift: float = 0.3
    smoothing: OneEuroPolicy | None = field(default_factory=OneEuroPolicy)
    motion: MotionPolicy | None = field(default_factory=MotionPolicy)
    fusion: FusionPolicy | None = field(default_factory=lambda: FusionPolicy())


@dataclass(frozen=True)
class FusionPolicy:
    """One estimate per frame from all the evidence (the reader's landmarks, the local
    appearance, the speaker's model, a motion model); see :meth:`LiveTracker._track_fused`.

    reader : the landmark network read on every frame (a key of
        :data:`~articast.core.faces.finder.LANDMARK_MODELS`; it must be the one the speaker's
        observation model was learned for).
    appearance_weight, points_weight : weights of the local-appearance and landmark terms,
        each already whitened by the speaker's own enrolment statistics (the appearance by
        its held-out residual s.d. per feature, the landmarks by their residual covariance:
        each point's own s.d. and the error modes they share). appearance 0: the landmarks
        through the model alone (the appearance is then not sampled). The landmarks' 0.3 was
        chosen by the ablation over every real clip (docs/TRACKING.md, "Fused tracking"):
        the reader's errors stay correlated beyond the modes it is whitened by.
    kalman : the constant-velocity motion model's prediction as the fit's prior (False: the
        tracker's own prediction and priors).
    points_scale : Cauchy scale of a landmark's whitened residual norm.
    levels : pyramid levels fitted per frame (the landmarks put the start in the basin of the
        finest level).
    max_iterations : Gauss-Newton iterations per frame.
    tolerance : a factor on the fit's stopping steps (``FitPolicy.tol_alpha``,
        ``tol_rotation``, ``tol_translation_mm``: a fit stops after an accepted step smaller
        than all three).
    read_every : the reader runs on every n-th frame; the frames between are fitted on the
        appearance and the motion model alone (the reader is most of a frame's cost). 3,
        with ``adapt``, against every 2nd frame with fixed weights (benchmarks/peers.py, one
        run each, docs/history/REAL_SPEAKERS_LOG.md): r against the consensus
        0.957 / 0.566 / 0.981 /
        0.862 vs 0.956 / 0.529 / 0.982 / 0.849 (franck, cap12, cap13, pexels_woman), still-mouth
        jitter 0.131 / 0.080 / 0.323 / 0.293 vs 0.139 / 0.067 / 0.271 / 0.346, at 1.08-1.31x
        the FaceMesh v1 loop's CPU instead of 1.22-1.30x. (Every frame read cost 1.8-2.0x and
        read no better.)
    gate : a reading whose median point is further from the prediction than this fraction
        of the face's size in the image restarts the motion model at the prediction (zero
        velocity, a wide covariance) and lets every point pull that frame (least squares): the
        robust loss would otherwise ignore every point of a reading that far, and the state
        could drift off the face (on franck 40 % of the frames were lost that way without
        it). A frame whose fit is still not ok is found again by the face finder.
    reread : a reading further from the motion model's prediction than this many times
        ``PointModel.offset_p99`` (the face moves faster than the model foresaw) makes the
        next frame read too (None: never).
    adapt : the appearance term's weight follows its own residual level: x min(1, the
        enrolment's median / a running mean of this clip's robust residual, updated at this
        rate per frame, occluded frames left out). A face the appearance no longer predicts
        (an expression, a light, a resolution the enrolment never showed) leans on the
        landmarks and the motion model; one like the enrolment keeps the full weight (the
        terms are whitened by the enrolment's statistics, which held-out frames of another
        kind do not follow). pexels_woman (laughing after an enrolment of crying): r 0.782
        -> 0.862 reading every 3rd frame; franck 0.957 either way, cap13 0.988 -> 0.981.
        None: the fixed weights.
    agreement : a fitted frame with a reading is ``diverged`` when the reading's median point
        is further from the fitted face than this many times the enrolment's 99th percentile
        of that distance (:attr:`~articast.core.tracking.points.PointModel.offset_p99`, both
        as fractions of the face's size). The landmarks judge the fit, not the appearance
        residual: an opening wider than any in the enrolment, a face under other light,
        raise the appearance residual of fits the landmarks confirm (10 s of cap13 enrolled:
        58 of 515 held-out frames were "diverged" by the residual while their apertures
        followed FaceLandmarker v2 at r 0.978). Frames between two readings are judged by
        the tracker's own tests (a residual far above its running level). A speaker whose
        observation model predates ``offset_p99`` is judged by the residual as before.
    speaker_prior : the speaker's own distribution of articulations, N(0, I / w) on alpha
        (the enrolment's, in the model's s.d. units), is a term of every frame's fit with this
        weight w (:meth:`~articast.core.tracking.fitting.StatePrior.with_speaker`; None:
        none): the estimate is the speaker's most probable articulation given the frame, not
        merely one that explains it. The reader's 300 points leave some directions of the 7
        parameters nearly free: through the model alone, on cap13's still mouth, lips1,
        lips4 and jaw2 wandered by 4-6 s.d. in 7 frames (still-mouth jitter 0.83 % of the
        width, r 0.953 against the consensus; with the term 0.31 and 0.981). Fused, the
        appearance pins most of them: r +0.002 on franck, +0.06 on cap12 (both outside
        their bootstrap intervals), within noise on the others, the synthetic speaker's
        truth r unchanged (docs/history/REAL_SPEAKERS_LOG.md, the ablation). 1 is the distribution
        itself, not a tuned weight. It is not fed back into the motion model's covariance
        (it would count the same knowledge again every frame).
    cadence : the streamed articulation loses the periodic component that reading every
        ``read_every``-th frame imprints on it
        (:class:`~articast.core.tracking.filters.CadenceCanceller`, this rate per update;
        None: kept), before the One Euro filter. The readings and the appearance disagree by
        a slowly varying bias, so the raw fit steps at each reading and drifts back between
        (cap13's still mouth: 1.4 % of the mouth's width RMS); the filter's 3 Hz passes a
        third of that 8-10 Hz sawtooth. Per phase (frames since the reading) a running mean
        of the frame's deviation from the last ``read_every`` frames is taken off (each
        update clipped at 3x the phase's running spread, none while a jump settles, each
        phase's offset shrunk by how well it is known). ``peers.py`` with and without
        (``--variant no_cadence``): still-mouth jitter franck 0.117 -> 0.092, cap12 0.094 ->
        0.087, cap13 0.303 -> 0.219, pexels_woman 0.344 -> 0.267, r within 0.002, lag
        unchanged (offline on the same raw fits, rates 0.05-0.3 did alike; 0.1: about ten
        readings, ~1 s, the bias's time scale). The fit itself is not changed.
    start : which landmarks a (re)start reads. "reader": the reader's own, found as the
        finder finds (the detector, then the reader in its box and twice more in the crop
        grown from what it read: ~3 FaceMesh v1 calls); the start's state and the frame's
        reading are the same landmarks (the scheme reads none of the finding network's iris
        points, the only ones FaceMesh v1 lacks). "finder": the finding landmarks
        (FaceLandmarker v2, three calls), then the reader seeded from them: ~40 ms more CPU
        per start, which on a 2 s clip is most of articast's excess over the FaceMesh v1 loop.
        On the rendered speaker (the knock test's clip), 25 starts 3 frames apart: the first
        frame's aperture 0.54 vs 0.65 mm from the tracked one (MAE), r with the truth 0.992 vs
        0.990; recovery after eight knocks r 0.900 vs 0.899 (docs/history/REAL_SPEAKERS_LOG.md).
    resume : after a ``diverged`` frame (the fit, not the face, was lost: the reader read the
        face this frame or within ``read_every``), the restart reads the landmarks in the
        crop grown from that last reading instead of running the detector (which still runs
        when that reading finds no face, or when the start it resumed diverges at once).
    eye_reads : a frame between readings is read too when an eye the upper face cannot follow
        from its pixels changed more than the speaker's open eye does between frames
        (:meth:`~articast.core.faces.upper.UpperTracker.wants_reading`: a blink of two frames
        falls between readings every 3rd frame one time in three otherwise), unless the last
        reading was one such (at most every other reading is one); that reading's time is
        counted as the upper face's (docs/UPPER_FACE.md).
    lag_check : a frame between readings whose appearance residual starts to look like an
        occlusion (:meth:`~articast.core.tracking.tracker.Tracker.occlusion`, its first
        frames) is read: a reading further from the fit than ``reread`` x the reader's 99th
        percentile says the fit lags a motion (the mispredicted points are its own), and the
        frame is not ``occluded`` (the next is read); one that agrees leaves the verdict to
        the appearance (a hand: the reader reads a face under it where the fit is).
        franck's laugh, the mouth flung open between two readings: readings 2.3 and 4.5 x
        the 99th percentile from the fit on the two frames the appearance suspected; cap12's
        hand at his chin: 0.5-1.1 x on every frame it suspected.
    regression : on a frame with a reading, the articulation the enrolment's regression
        reads off the reader's points (:class:`~articast.core.tracking.points.
        ReadingRegression`, with the error its cross-validation measured) is a measurement
        of the articulation beside the landmark term (the prior times it, and the motion
        model's update takes its information). Through the observation model the fit is the
        articulation that best explains all ~300 points, a compromise in which the lips'
        few points weigh little: each reading fitted alone read the aperture at r 0.905
        against the consensus on franck where the reader's own lip points gave 0.959; the
        regression, which learned at enrolment what each point tells of the articulation,
        read 0.964 from the same readings (``benchmarks/landmark_term.py``). Both are kept:
        live and alone, the landmark term read faces the enrolment never showed
        (pexels_woman laughing after crying) better than the regression; the two count the
        same reading twice, as the term's 0.3 weight already allows for. Five enrolments of
        each clip (``benchmarks/enrolment_spread.py``, with and without): r against the
        consensus higher on every clip in five of five but carphone (three of five), the
        still-mouth jitter within the enrolments' spread (docs/history/REAL_SPEAKERS_LOG.md);
        it reads more frames where the face moves fast (carphone's CPU: the same log).
    recover : a fit that diverges on a started track is started again from the frame's own
        reading (read then, in the crop grown from the last reading, on a frame between
        readings) and fitted again within the frame; only if that fit diverges too is the
        frame ``diverged`` (and the next frame starts as ``resume`` says). Without it, a fit
        that lagged a fast move (carphone's shaking camera, the first reading after a start;
        single_face turning away at its end) lost that frame and restarted on the next one.
        The output filter forgets the frames before (they were of the lost fit), and the
        next frame is read (the motion model restarted at rest, as after a reading it
        mispredicted: single_face's last frame, between readings, diverged by the
        appearance again and needed a second start without it). peers.py with and without
        (``--variant no_recover``): see docs/history/REAL_SPEAKERS_LOG.md.
    reader_gap : the streamed opening is this share of the reader's own lip gap and the rest
        the raw fused fit's (both the inner gap over the mouth width in the image; the
        streamed articulation moved by the smallest step that gives it,
        :mod:`articast.core.faces.lipgap`), on every frame the reader read; None: the
        filtered fit's alone. Issue 38, on 16 clips of 14 people the enrolment never saw
        (``benchmarks/peers.py`` then ``benchmarks/corpus_summary.py``, judged by the
        networks outside the FaceMesh family): the fused estimate read the lips worse than
        its own reader on 7 clips and a frame late on 13 (the One Euro filter); the
        reader's gap alone, carried through the 3D model, read slightly worse than the
        reader (pooled -0.012); the two mixed read better than both, with no lag: the fit's
        appearance and the reader's points err apart. Shares 0.35 / 0.5 / 0.65 chosen on
        one half of the people (pooled gap to the reader +0.019 / +0.020 / +0.018, one clip
        worse each) and checked on the other (+0.046 / +0.042 / +0.032, none worse); an
        adaptive share from each source's roughness read less well (+0.013 / +0.027).
        Needs ``read_every`` 1 (a frame without a reading keeps the filtered fit's).
    eyes_every : the upper face measures the eyes on the reader's landmarks of every
        n-th reading, and of any reading whose eye pixels changed more than the speaker's
        open eye does (:meth:`~articast.core.faces.upper.UpperTracker.wants_reading`);
        between, from that reading's lids alone and their pixels (the ``lids`` of
        :meth:`~articast.core.faces.upper.UpperTracker.step`). The eyes' measures (the iris fit
        above all) cost ~0.3x a FaceMesh v1 call: measured on every frame the whole live
        face cost 2.4x the FaceMesh v1 loop, every 3rd 2.0-2.2x (the issue's budget: 2.0).
    realign : on a frame the ``gate`` restarts the motion model, restart it at the head's pose
        the reading shows (the observation model's mean points aligned rigidly to the
        reading: PnP from the prediction, ~0.5 ms) instead of the predicted pose the reading
        contradicts, so that the fit starts there and the ``regression`` is read there (it is
        left out at a pose that far off: its features take out only a small move of the
        head, and the rest would be read as articulation). On by default since session 8 of
        issue 38: it is what brings lia_vox_driving3 (a hand-held camera gating 81 of 179
        frames) up to its reader's floor, r against the judge 0.945 -> 0.967 (gap to the
        reader -0.029, 95 % -0.071..-0.012, -> -0.007, -0.032..+0.004); the price is
        liveportrait_d10 0.918 -> 0.912 (paired 95 % -0.010..-0.0002: a fit 14 frames after
        its one changed gated frame lands at 3.00 instead of 3.01 x the enrolment's 99th
        percentile from its reading, no longer ``diverged``, so it is not started again from
        the reading), which stays above its own floor (-0.015, -0.041..+0.009); every other
        clip of the corpus within 0.002 (docs/TRACKING.md, "Where the streamed lips fall
        short of the reader").
    still_mouth : the raw fit's half of the streamed opening (``reader_gap``) follows the fit
        by the share of its change that the mouth's pixels allow: the mean absolute change of
        the grey mouth patch (the box of the last frame's reading's outer lips grown 30 %, in
        this frame and in that one; or the last frame's own change where larger: the fit
        follows the image up to a frame late) over this many grey levels, between
        :data:`~articast.core.faces.lipgap.STILL_MIN_GAIN` and 1
        (:func:`~articast.core.faces.lipgap.still_gain`; None: the raw fit's opening as it
        is). A mouth whose pixels did not change did not open or close: what the fit's
        opening does there is its own noise, which the reader's half does not share. The
        reader's half is streamed as read and a moving mouth passes the fit's change whole,
        so no lag is added. Issue 38's still-mouth floor on cap13 (a compressed webcam clip):
        jitter 0.186 -> 0.109 % of the mouth's width, the reader's 0.129 (gap -0.019, 95 %
        -0.038..+0.004; franck 0.235 -> 0.155, cap12 0.167 -> 0.084), no clip's r worse
        (the paired 95 % interval reaches zero on each of the 20 real clips long enough for
        one, lowest edtalk_mouth_source -0.0002, -0.0004..0.0000; carphone, single_face
        within 0.0001), the rendered speaker's truth r 0.977 as before, lag 0.
        2 grey levels chosen on half A of the people (4 read edtalk_pose_source2 worse),
        checked on half B. Gated on this frame's change alone, styletalk_andrew_clip_2 read
        worse at every scale: its fit jumps a frame after the pixels do (docs/TRACKING.md,
        "cap13's still mouth").
    reader_keep_roi : the reader's crop: it keeps the previous reading's crop while the crop
        grown from that reading differs from it by less than this fraction of its side
        (:attr:`~articast.core.faces.finder.FinderPolicy.keep_roi`; 0: a new crop on every
        frame, as MediaPipe's own loop does). The same crop reads the enrolment's frames
        (:func:`reader_finder`; the speaker records it, ``report["reader"]["keep_roi"]``),
        so the observation model is learned from readings made as the live ones are; and it
        is the second tracker's (``articast track``, ``SECOND_READER``) for its reader.
        See docs/TRACKING.md, "The reader's crop".
    """

    reader: str = "v1"
    appearance_weight: float = 1.0
    kalman: bool = True
    points_scale: float | None = 3.0
    levels: tuple[int, ...] = (0,)
    max_iterations: int = 3
    tolerance: float = 1.0
    points_weight: float = 0.3
    read_every: int = 1
    gate: float = 0.15
    agreement: float = 3.0
    reread: float | None = 2.0
    adapt: float | None = 0.1
    speaker_prior: float | None = 1.0
    cadence: float | None = None
    start: str = "reader"
    resume: bool = True
    eye_reads: bool = True
    lag_check: bool = True
    regression: bool = True
    recover: bool = True
    reader_gap: float | None = 0.5
    eyes_every: int = 3
    realign: bool = True
    still_mouth: float | None = 2.0
    reader_keep_roi: float = 0.02

    def __post_init__(self) -> None:
        if self.start not in ("reader", "finder"):
            raise ValueError(f"start must be 'reader' or 'finder', got {self.start!r}")
        if not 0.0 <= self.reader_keep_roi < 1.0:
            raise ValueError(f"reader_keep_roi must be in [0, 1), got {self.reader_keep_roi!r}")

    def reader_policy(self) -> FinderPolicy:
        """The reader's :class:`~articast.core.faces.finder.FinderPolicy`: the finder's, with
        this policy's crop (``reader_keep_roi``)."""
        return FinderPolicy(keep_roi=self.reader_keep_roi)


def reader_finder(fusion: FusionPolicy | None = None, *, threads: int = 1,
                  detector: Any = None) -> FaceFinder:
    """The live reader ``fusion`` names (default :class:`FusionPolicy`'s), cropping as it
    says: what :class:`LiveTracker` reads every frame with, and what an enrolment reads its
    frames with (``read_every_frame``), so that the observation model learns the readings
    the live tracker will make. ``detector``: a loaded detector session to share."""
    fu = fusion or FusionPolicy()
    return FaceFinder.load(threads=threads, landmarks=fu.reader, policy=fu.reader_policy(),
                           detector=detector)


LIVE_ALPHA_SIGMA = 0.5
"""Motion prior of live tracking (training s.d. per frame, see ``FitPolicy.alpha_sigma``): on
a 31 s webcam clip it brought the still-mouth jitter of the lip aperture from 0.25 to 0.18 %
of the mouth width (the landmark model: 0.21 %) at the same agreement with the landmarks."""


def _blank(image: np.ndarray, least: float) -> bool:
    """Whether a frame has no contrast: ``pixel_spread(image[::8, ::8]) < least``, the same
    answer on every frame. Its every 32nd pixel is read first: a sixteenth (at least) of
    those samples, whose s.d. is at most four times theirs (n var_all >= n_part var_part,
    each about its own mean), so where that s.d. reaches 4 x ``least`` the frame has
    contrast and the every-8th sample is not read (a real frame's s.d. is tens of grey
    levels; a frame read cold from memory: ~20 against ~70 us in the live loop); below, the
    every-8th sample decides as before."""
    if pixel_spread(image[::32, ::32]) >= 4.0 * least + 1e-6:
        return False
    return pixel_spread(image[::8, ::8]) < least


_PLAIN_RESULT = (not hasattr(TrackResult, "__post_init__")
                 and all(f.init for f in fields(TrackResult)))


def _with(result: TrackResult, **changes: Any) -> TrackResult:
    """``dataclasses.replace(result, **changes)`` for the per-frame records: the same record
    (a :class:`TrackResult` has no ``__post_init__`` and every field is an ``__init__``
    argument) made by copying its fields instead of calling its frozen ``__init__`` (~1.5
    against ~5.5 us a call; four a frame)."""
    if not _PLAIN_RESULT or type(result) is not TrackResult:
        return replace(result, **changes)
    out = object.__new__(TrackResult)
    state = out.__dict__
    state.update(result.__dict__)
    for name in changes:
        if name not in state:
            raise TypeError(f"TrackResult has no field {name!r}")
    state.update(changes)
    return out


def live_policy(rig: str, **changes: Any) -> TrackingPolicy:
    """The tracking policy of a live speaker on ``rig``: the rig's, plus the motion prior."""
    pol = TrackingPolicy.for_rig(rig, **changes)
    if pol.fit.alpha_sigma is None:
        pol = replace(pol, fit=replace(pol.fit, alpha_sigma=LIVE_ALPHA_SIGMA))
    return pol


def turn_range(report: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The enrolment's reference head rotation (3, 3) and the range (3, 2) deg of its
    appearance's training frames' rotations away from it, from a speaker's ``report``
    (:func:`~articast.core.faces.build.turn_coverage`; None: enrolled before they were kept)."""
    cov = report.get("coverage") or {}
    if "rotation_ref" not in cov or "rotation_deg" not in cov:
        return None
    return (rotation_matrix(np.asarray(cov["rotation_ref"], np.float64)),
            np.asarray(cov["rotation_deg"], np.float64))


class LiveTracker:
    """Tracks an enrolled speaker frame by frame, judging ``ok`` honestly."""

    def __init__(self, speaker: Speaker, finder: FinderLike, scheme: LandmarkScheme,
                 policy: LivePolicy | None = None, tracking: TrackingPolicy | None = None,
                 clock: Callable[[], float] | None = None,
                 reader: FinderLike | None = None) -> None:
        """reader : the landmark network read every frame in fused tracking (default: the
        bundled one the policy names, loaded here with its crop, :func:`reader_finder`; a
        reader given is used as it is: its own policy crops)."""
        self.speaker, self.finder, self.scheme = speaker, finder, scheme
        self.policy = policy or LivePolicy()
        tracking = tracking or live_policy(speaker.rig)
        if self.policy.fusion is not None and speaker.points is not None:
            # the landmarks start each fit in the basin
            tol = self.policy.fusion.tolerance
            tracking = replace(tracking, fit=replace(
                tracking.fit, max_iterations=self.policy.fusion.max_iterations,
                max_rejections=2, tol_alpha=tracking.fit.tol_alpha * tol,
                tol_rotation=tracking.fit.tol_rotation * tol,
                tol_translation_mm=tracking.fit.tol_translation_mm * tol))
        # the lips are measured once a frame, on the state streamed (track)
        self.tracker = Tracker(speaker.model, speaker.appearance, speaker.camera, tracking,
                               clock=clock, measure_lips=False)
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
        # fused tracking needs the speaker's observation model of the reader (enrolled by
        # this version); a speaker enrolled before is tracked as before
        fu = self.policy.fusion if speaker.points is not None else None
        self.fusion = fu
        self.reader = reader
        self._reading: Any = None
        self._seen_of: Any = None  # (the reading whose points _seen indexed last, and those)
        self._seen_points: np.ndarray | None = None
        self._resume: Any = None  # the last reading, after a frame whose fit diverged
        self._resumed = -1  # the last frame started from it
        self._since_read = 0
        self.regated = 0  # readings far from the prediction (the motion model restarted)
        self.realigned = 0  # of those, restarted at the head's pose the reading shows
        self.rereads = 0  # readings that asked for the next frame to be read too
        self._turns = turn_range(speaker.report)  # (_unfamiliar)
        self.lag_reads = 0  # frames read to tell a fit's lag from an occluder (_fit_lags)
        self.recover_reads = 0  # frames read to start a diverged fit again (_recover)
        self.recovered = 0  # diverged fits started again within their frame and then ok
        self.eye_reads = 0  # frames between readings read for the eyes (FusionPolicy.eye_reads)
        self._eyes_read = False  # the last reading was one of those
        self._last_anchor: np.ndarray | None = None  # the head's point at the last ok frame
        self._t_last: float | None = None
        self._phase = 0  # frames since the last reading (fused tracking)
        self._mouth: tuple[np.ndarray, np.ndarray] | None = None  # last ok frame's lip box, patch
        self._mouth_was = float("nan")  # the mouth's pixel change the frame before (still_mouth)
        self._fit_gap: float | None = None  # the fit's opening as streamed (still_mouth)
        self._cadence = (CadenceCanceller(fu.read_every, fu.cadence)
                         if fu is not None and fu.cadence is not None and fu.read_every >= 2
                         else None)
        # the upper face (eyes, brows) from this frame's landmarks, or between readings
        # from the eyes' pixels (core/faces/upper.py)
        self.upper = UpperTracker(speaker.upper, speaker.rig, clock=clock)
        faces_kernels.warm_up()  # (its compiled iris fit loaded before the first frame, not in it)
        self._fresh: Any = None  # the landmarks read in this frame, if any
        self._eyes_frame = -(10**9)  # the last frame whose reading the eyes were measured on
        self._head_point = speaker.model.shape(np.zeros(speaker.model.n_params)).mean(axis=0)
        cam = speaker.camera  # (the lips' compiled gap: an undistorted camera's intrinsics)
        self._pinhole = cam.pinhole
        self._intrinsics = cam.intrinsics
        if fu is not None:
            if reader is None:  # the bundled one, on one thread, cropping as the policy
                # says (it runs no detector: the finder's session is shared, not loaded again)
                self.reader = reader_finder(fu, detector=getattr(finder, "detector_session",
                                                                 None))
            assert speaker.points is not None
            if speaker.points.network != fu.reader:
                raise ValueError(f"the speaker's observation model is of the "
                                 f"{speaker.points.network!r} landmarks, not {fu.reader!r}")
            self.point_model = speaker.points
            self.kalman = ConstantVelocity(speaker.model.n_params, speaker.motion_noise,
                                           speaker=fu.speaker_prior)
            self.weights = (fu.points_weight, fu.appearance_weight)
            self._app_level = speaker.residual.median
            self._motion = None  # the landmarks give the head's translation every frame

    # ------------------------------------------------------------------ helpers
    def _finder(self, image: np.ndarray, previous: Any = None, network: Any = None) -> Any:
        """A landmark call (counted; the frame's fresh landmarks): ``network`` (default the
        finder) tracks from ``previous``, or finds with the detector."""
        net = self.finder if network is None else network
        self.finder_calls += 1
        face = net.track(image, previous) if previous is not None else net.find(image)
        self._fresh = face
        return face

    def _start(self, face: Any, keep_levels: bool = False) -> bool:
        marks = np.asarray(face.landmarks)
        n = self.scheme.n_landmarks
        if len(marks) < n and len(marks) > int(np.max(self.scheme.points)):
            # the reader's (FaceMesh v1, 468 points): the finding network's topology without
            # its iris points, none of which the scheme reads
            marks = np.concatenate([marks, np.repeat(marks[-1:], n - len(marks), 0)])
        state = state_from_landmarks(self.speaker.model, self.scheme, self.speaker.camera,
                                     marks)
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

    @property
    def reading(self) -> np.ndarray | None:
        """The landmarks (L, 3) a network read in the last frame tracked (the reader's 468
        or the finder's 478 points, image px), or None where none was read."""
        return None if self._fresh is None else np.asarray(self._fresh.landmarks)

    def depth_drift(self, result: TrackResult, face: Any) -> float | None:
        """Relative difference between the tracked head's depth and the depth read off the
        landmarks; None if the landmarks give none."""
        state = state_from_landmarks(self.speaker.model, self.scheme, self.speaker.camera,
                                     face.landmarks)
        if state is None:
            return None
        return float(result.pose.translation[2] / state[1].translation[2] - 1.0)

    def _not_ok(self, result: TrackResult, reason: str) -> TrackResult:
        return _with(result, ok=False, reason=reason)

    def _lost(self, t: float, reason: str) -> TrackResult:
        """A not-ok frame holding the last good state (neutral before any)."""
        self._started = False
        self._face = None
        self._reading = None
        self._resume = None
        self._mouth = self._fit_gap = None
        self._mouth_was = float("nan")
        if self._cadence is not None:
            self._cadence.forget()
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
        self._fresh = None
        result = self._track(image, t)
        upper = self._upper_face(image, result)
        ms = (self.clock() - t0) * 1000.0 if self.clock else result.ms
        extra = result.extra
        if self.fusion is not None:  # what an offline smoother needs (core/tracking/smoother.py)
            extra = {**extra, "motion": self.kalman.step, "phase": self._phase}
            if self._fresh is not None:  # (and the offline mix with the readers' lip gaps)
                extra["reader_ratio"] = reader_ratio(np.asarray(self._fresh.landmarks)[:, :2])
        result = _with(result, upper=upper, frame=self._frame, ms=ms, extra=extra)
        gap = self.fusion is not None and self.fusion.reader_gap is not None
        if result.ok and (self._filter is not None or self._cadence is not None or gap):
            if result.extra.get("recovered") and self._filter is not None:
                self._filter.reset()
            out = result.alpha
            if self._cadence is not None:
                out = self._cadence(out, self._phase)
            if self._filter is not None:
                out = self._filter(out, t)
            change = self._mouth_change(image, result)
            out = self._lip_gap(result, out, change)
            extra = {**result.extra, "alpha_raw": result.alpha}
            if np.isfinite(change):  # (FusionPolicy.still_mouth)
                extra["mouth_change"] = change
            result = _with(result, alpha=out, lips=lips_dict(self.speaker.model, out),
                             extra=extra)
        else:
            self._mouth = self._fit_gap = None
            self._mouth_was = float("nan")
            if not result.ok:
                if self._filter is not None:
                    self._filter.reset()
                if self._cadence is not None:
                    self._cadence.reset()
            if result.lips is None:  # the tracker's result (its lips not measured)
                result = _with(result, lips=lips_dict(self.speaker.model, result.alpha))
        if result.ok:
            self._last = result
        return result

    def _mouth_change(self, image: np.ndarray, result: TrackResult) -> float:
        """How much the mouth's pixels changed (``FusionPolicy.still_mouth``): the mean
        absolute grey change of the mouth's patch since the last ok frame, both taken in that
        frame's lip box (its reading's outer lips), or the last frame's own change where that
        was larger (the fit
        follows the image up to a frame late: its motion prior); NaN after a frame not ok, or
        without ``still_mouth``. Keeps this frame's box, patch and change for the next."""
        fu = self.fusion
        if fu is None or fu.still_mouth is None or fu.reader_gap is None:
            return float("nan")
        change = float("nan")
        if self._mouth is not None:
            box, patch = self._mouth
            change = lipgap.patch_change(lipgap.mouth_patch(image, box), patch)
        box = (np.full(4, np.nan) if self._fresh is None
               else lipgap.lip_box(np.asarray(self._fresh.landmarks)))
        self._mouth = ((box, lipgap.mouth_patch(image, box))
                       if all(map(math.isfinite, box.tolist())) else None)
        was, self._mouth_was = self._mouth_was, change
        return was if not np.isfinite(change) or was > change else change

    def _lip_gap(self, result: TrackResult, alpha: np.ndarray,
                 change: float = float("nan")) -> np.ndarray:
        """The streamed ``alpha`` whose projected opening is this frame's mix of the reader's
        own lip gap and the fused fit's (:mod:`articast.core.faces.lipgap`,
        ``FusionPolicy.reader_gap``; the fit's as ``FusionPolicy.still_mouth`` lets it follow
        the mouth's pixel ``change`` since the last frame); unchanged on a frame the reader
        did not read."""
        fu = self.fusion
        if fu is None or fu.reader_gap is None or self._fresh is None:
            self._fit_gap = None
            return alpha
        read = result.extra.get("reader_ratio", float("nan"))
        if not math.isfinite(read):
            self._fit_gap = None
            return alpha
        m, cam = self.speaker.model, self.speaker.camera
        w = fu.reader_gap
        compiled = kernels.AVAILABLE and self._pinhole
        if compiled:  # (the compiled calls' arguments, each made once a frame)
            mean, basis = lipgap.lip_points(m)
            rot, t = result.pose.matrix, np.array(result.pose.translation)
            fit = np.array(result.alpha, np.float64)
        if fu.still_mouth is not None and w < 1.0:
            if compiled:
                fitted = float(kernels.lip_ratio(mean, basis, rot, t, self._intrinsics, fit))
            else:
                fitted = float(model_ratios(m, cam, result.alpha[None], result.pose)[0])
            if not np.isfinite(fitted):
                self._fit_gap = None
            else:
                if self._fit_gap is None or result.extra.get("recovered"):
                    self._fit_gap = fitted
                else:
                    self._fit_gap += lipgap.still_gain(change, fu.still_mouth) * (
                        fitted - self._fit_gap)
                read, w = w * read + (1.0 - w) * self._fit_gap, 1.0  # (the target)
        if compiled:  # the same below, in one compiled call
            return kernels.lip_gap(mean, basis, rot, t, self._intrinsics,
                                   np.array(alpha, np.float64), fit, float(read), float(w),
                                   lipgap.PROBE_STEP, lipgap.MAX_CHANGE, lipgap.TOLERANCE)
        target = read
        if w < 1.0:  # the fit's own opening, raw (before the output filter: no lag)
            fitted = float(model_ratios(m, cam, result.alpha[None], result.pose)[0])
            if np.isfinite(fitted):
                target = w * read + (1.0 - w) * fitted
        return matched(m, cam, alpha, result.pose, target, iterations=1)

    def _upper_face(self, image: np.ndarray, result: TrackResult) -> Any:
        """The eyes and brows of this frame (:class:`~articast.core.faces.upper.UpperFace`)."""
        fresh = self._fresh
        fu = self.fusion
        lids = None
        if (fresh is not None and fu is not None and fu.eyes_every > 1 and self._started
                and self._frame - self._eyes_frame < fu.eyes_every
                and not self._eyes_changed(image)):
            # the eyes measured in full on every eyes_every-th reading, and on any frame whose
            # eye pixels changed more than the speaker's open eye does; between, this
            # reading's lids alone and their pixels (UpperTracker.step's lids)
            lids, fresh = np.asarray(fresh.landmarks), None
        marks = None if fresh is None else np.asarray(fresh.landmarks)
        if fresh is not None:
            self._eyes_frame = self._frame
        anchor = None
        if result.ok or result.reason.startswith("occluded"):
            anchor = self._head_in_image(result.pose)
        if result.ok:  # (where the next frame's eyes are looked for, :meth:`_eyes_changed`)
            self._last_anchor = anchor
        return self.upper.step(image, marks, anchor,
                               result.ok or result.reason.startswith("occluded"), lids)

    def _head_in_image(self, pose: Pose) -> np.ndarray:
        """(2,) px: the head's point at ``pose`` (``Camera.project_head``, the point alone:
        :meth:`~articast.core.model.camera.Camera.project_one`)."""
        return self.speaker.camera.project_one(
            (self._head_point[None] @ pose.matrix.T + pose.translation)[0])

    def _eyes_changed(self, image: np.ndarray) -> bool:
        """Whether the upper face asks for this frame between readings to be read (the head's
        point placed at the last tracked pose: this frame's is not fitted yet)."""
        if self._last is None or self._last_anchor is None or not self.upper.watched():
            return False
        return self.upper.wants_reading(image, self._last_anchor)

    def _track(self, image: np.ndarray, t: float) -> TrackResult:
        if _blank(image, self.tracker.policy.min_contrast):
            return self._lost(t, "blank: the frame has no contrast")
        if self.fusion is not None:
            return self._track_fused(image, t, self.fusion)
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

    def _track_fused(self, image: np.ndarray, t: float, fu: FusionPolicy) -> TrackResult:
        """One frame from all the evidence: the motion model predicts the state; the reader's
        landmarks, read in a crop grown from its last reading, and the local appearance are
        fitted together from the prediction, in the speaker's model, with the prediction as
        the prior; the fit updates the motion model."""
        assert self.reader is not None
        self.kalman.step = None  # (this frame's, if the motion model is updated or held)
        dt = 1.0 / 25.0 if self._t_last is None else t - self._t_last
        self._t_last = t
        reading = None
        self._since_read += 1
        skip = self._started and self._since_read < fu.read_every
        # (one frame read for the eyes between two others: an eye that changes on every
        # frame, a glint on glasses, costs a reading in two at worst, not one per frame)
        for_eyes = (skip and fu.eye_reads and not self._eyes_read
                    and self._eyes_changed(image))
        if self._started and self._reading is not None and (for_eyes or not skip):
            t0 = self.clock() if for_eyes and self.clock else 0.0
            reading = self._finder(image, self._reading, self.reader)
            self._since_read = 0
            self._eyes_read = for_eyes
            skip = False
            if for_eyes:
                self.eye_reads += 1
                if self.clock:  # (the upper face's cost: it asked for the reading)
                    self.upper.spent_s += self.clock() - t0
        restart = not self._started or (reading is None and not skip)
        prior = None
        scale = fu.points_scale
        gated = False  # the prior's pose is not where this frame's reading puts the head
        if not restart and fu.kalman:
            prior = self.kalman.predict(dt)
            # how far the prediction is from the reading, as a fraction of the face's size
            missed = (self._offset(prior.alpha, prior.rotation, prior.translation,
                                   self._seen(reading))
                      if reading is not None else 0.0)
            p99 = self.point_model.offset_p99
            if fu.reread is not None and np.isfinite(p99) and missed > fu.reread * p99:
                # the prediction missed the reading by more than the reader's own spread: the
                # face moves faster than the motion model foresaw, read the next frame too
                self._since_read = fu.read_every - 1
                self.rereads += 1
            if not np.isfinite(missed) or missed > fu.gate:
                # the reading is far from the prediction (a motion it did not foresee, or a
                # state drifting off the face): the prediction is forgotten (zero velocity,
                # wide covariance) and every landmark pulls (least squares) this frame; with
                # FusionPolicy.realign the motion model restarts at the head's pose the
                # reading shows, and the regression is read there, instead of at the
                # predicted pose the reading just contradicted
                at = self._reading_pose(reading, prior) if fu.realign else None
                rvec, trans = ((axis_angle(prior.rotation), prior.translation) if at is None
                               else (at.rotation, at.translation))
                self.kalman.start(prior.alpha, rvec, trans)
                prior = self.kalman.predict(dt)
                scale = None
                gated = at is None
                self.regated += 1
                self.realigned += int(at is not None)
                if self._cadence is not None:  # a jump, not the cadence's steady component
                    self._cadence.reset()
        if restart:  # (re)start from landmarks (FusionPolicy.start, .resume)
            if self._cadence is not None:
                self._cadence.forget()
            was = self._started
            self._started = False
            reading = self._restart(image, fu, keep_levels=was)
            if isinstance(reading, str):
                return self._lost(t, reading)
            self._since_read = 0
            self._eyes_read = False
            prior = self._motion_at_rest(fu)
        if prior is not None and fu.speaker_prior is not None:
            prior = prior.with_speaker(fu.speaker_prior)
        self._phase = 0 if reading is not None else self._phase + 1
        result = self._fit_frame(image, t, fu, reading, prior, scale, gated)
        if fu.recover and not restart and result.reason.startswith("diverged"):
            result = self._recover(image, t, fu, reading, result)
        if not result.ok and not result.reason.startswith("occluded"):
            self._started = False  # diverged, left the image, blank: find the face again
            # a diverged fit: the face was read (this frame or within the last read_every),
            # the fit was lost; unless it was a resumed start's (the reading is suspect)
            self._resume = (self._reading if fu.resume and result.reason.startswith("diverged")
                            and self._resumed != self._frame else None)
        return result

    def _recover(self, image: np.ndarray, t: float, fu: FusionPolicy, reading: Any,
                 lost: TrackResult) -> TrackResult:
        """A fit that diverged from a started track: start again from this frame's reading
        (read now, in the crop grown from the last one, when the frame had none) and fit the
        frame again (:attr:`FusionPolicy.recover`). Returns ``lost`` when the reader finds no
        face, its landmarks do not fit the speaker, or the new fit diverges as well."""
        if reading is None:
            if self._reading is None:
                return lost
            reading = self._finder(image, self._reading, self.reader)
            self.recover_reads += 1
            if reading is None:
                return lost
            self._since_read = 0
            self._eyes_read = False
            self._phase = 0
        if not self._start(reading, keep_levels=True):
            return lost
        self._resumed = self._frame  # (diverging again, the reading is suspect: no resume)
        prior = self._motion_at_rest(fu)
        if prior is not None and fu.speaker_prior is not None:
            prior = prior.with_speaker(fu.speaker_prior)
        if self._cadence is not None:  # a jump, not the cadence's steady component
            self._cadence.reset()
        again = self._fit_frame(image, t, fu, reading, prior, fu.points_scale, False)
        if again.ok:
            self.recovered += 1
            self._since_read = fu.read_every - 1  # (read the next frame: no velocity known)
            # (the frames streamed before were of the lost fit: the output filter forgets them)
            return _with(again, extra={**again.extra, "recovered": True})
        return lost

    def _motion_at_rest(self, fu: FusionPolicy) -> StatePrior | None:
        """The motion model started at rest at the tracker's (re)started state; its
        prediction one frame on (None: no motion model in the fit)."""
        alpha, pose = self.tracker.state or (None, None)
        assert alpha is not None and pose is not None
        self.kalman.start(alpha, pose.rotation, pose.translation)
        return self.kalman.predict(1.0 / 25.0) if fu.kalman else None

    def _fit_frame(self, image: np.ndarray, t: float, fu: FusionPolicy, reading: Any,
                   prior: StatePrior | None, scale: float | None, gated: bool) -> TrackResult:
        """The fused fit of one frame from ``prior`` (with this frame's ``reading``, if any),
        judged, and the motion model updated with it."""
        term = None
        measured = None  # the information of the articulation read off the reading, if any
        seen = None if reading is None else self._seen(reading)
        if reading is not None:
            assert seen is not None
            self._reading = reading
            reg = self.point_model.regression
            if (fu.regression and reg is not None and prior is not None and not gated
                    and np.all(np.isfinite(seen))):
                # the articulation the enrolment's regression reads off the same points, a
                # measurement beside the term (FusionPolicy.regression); not where the gate
                # found the prediction far off the reading and no pose of the head that agrees
                # with it: the head is placed at the prior's pose, and one that far off would
                # be read as articulation
                read = reg.alpha(reg.features(self.point_model.mean, self.speaker.camera,
                                              seen, prior.rotation, prior.translation))
                prior = prior.with_measurement(read, reg.information)
                measured = reg.information
            term = self._term(reading, prior, self.weights[0], scale)
        confirm = None
        if seen is not None and np.isfinite(self.point_model.offset_p99):
            read_points = seen

            def confirm(alpha: np.ndarray, pose: Pose) -> bool:
                return self._unfamiliar(alpha, pose) and self._offset(
                    alpha, pose.matrix, pose.translation, read_points) <= (
                    fu.agreement * self.point_model.offset_p99)
        elif (fu.lag_check and fu.reread is not None
              and np.isfinite(self.point_model.offset_p99) and self._reading is not None):

            def confirm(alpha: np.ndarray, pose: Pose) -> bool:
                return self._fit_lags(image, alpha, pose, fu)
        wa = self.weights[1]
        if fu.adapt is not None:
            wa *= min(1.0, self.speaker.residual.median / max(self._app_level, 1e-12))
        ev = Evidence(term, prior, wa, fu.levels, confirm)
        result = self.tracker.track(image, t, evidence=ev)
        result = _with(result, extra={**result.extra, "appearance_weight": wa})
        rr = result.extra.get("robust_residual")
        if (fu.adapt is not None and rr is not None and np.isfinite(rr)
                and not result.reason.startswith("occluded")):
            self._app_level += fu.adapt * (float(rr) - self._app_level)
        if not np.isfinite(self.point_model.offset_p99):
            result = self._judge(result)  # an observation model saved before offset_p99
        elif reading is not None:
            result = self._agrees(result, reading, fu)
        if prior is not None:
            fitted = result.extra.get("theta_fit")
            k = self.speaker.model.n_params
            if result.ok or fitted is not None:
                info = result.extra.get("information")
                if measured is not None and info is not None:
                    info = np.array(info, np.float64)
                    info[:k, :k] += measured
                if result.ok:  # (the state's own arrays: the values of its theta's parts)
                    self.kalman.update(result.alpha, result.pose.rotation,
                                       result.pose.translation, info)
                else:
                    th = np.asarray(fitted)
                    self.kalman.update(th[:k], th[k:k + 3], th[k + 3:], info)
            else:
                self.kalman.hold()
        return result

    def _restart(self, image: np.ndarray, fu: FusionPolicy, keep_levels: bool) -> Any:
        """Start the tracker from landmarks of this frame (:attr:`FusionPolicy.start`,
        :attr:`FusionPolicy.resume`); returns the frame's reading, or the reason (a str) of a
        lost frame."""
        assert self.reader is not None
        seed, self._resume = self._resume, None
        reader_start = fu.start == "reader"
        net = self.reader if reader_start else self.finder
        face = None
        if seed is not None:  # last frame's fit diverged from its reading: no detector
            face = self._finder(image, seed, net)
            self._resumed = self._frame if face is not None else -1
        if face is None:
            face = self._finder(image, None, net)
        if face is None:
            return "no_face: the face finder sees no face"
        if not self._start(face, keep_levels=keep_levels):
            return "no_face: the landmarks do not fit the speaker"
        if reader_start:
            return face
        reading = self._finder(image, reader_seed(face), self.reader)
        if reading is None:
            return "no_face: the landmarks lost the face"
        return reading

    def _term(self, reading: Any, prior: StatePrior | None, weight: float = 1.0,
              scale: float | None = None) -> PointTerm:
        """The reading as the fit's landmark term (the head's predicted depth turns the
        observation model's mm into px)."""
        depth = float(prior.translation[2]) if prior is not None else float(
            (self.tracker.state or (None, Pose()))[1].translation[2])
        return PointTerm(self.point_model, self.speaker.camera, self._seen(reading), depth,
                         scale, weight)

    def _seen(self, reading: Any) -> np.ndarray:
        """(M, 2) px: ``reading``'s points of the observation model
        (:attr:`~articast.core.tracking.points.PointModel.landmarks`), indexed once a reading
        (a frame asks for them up to four times; no caller writes to them)."""
        if self._seen_of is not reading or self._seen_points is None:
            self._seen_of = reading
            self._seen_points = reading.landmarks[self.point_model.landmarks, :2]
        return self._seen_points

    def _reading_pose(self, reading: Any, prior: StatePrior) -> Pose | None:
        """The head's pose that puts the observation model's mean points where ``reading``
        read them (PnP from the prior's pose: a rigid alignment, ~0.5 ms); None without a
        reading, with a point not read, or where the solver fails."""
        if reading is None:
            return None
        seen = reading.landmarks[self.point_model.landmarks, :2]
        if not np.all(np.isfinite(seen)):
            return None
        return fit_pose(self.point_model.mean, seen, self.speaker.camera,
                        Pose(axis_angle(prior.rotation), prior.translation))

    def _offset(self, alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                seen: np.ndarray) -> float:
        """:func:`~articast.core.tracking.points.offset_fraction` of a reading's points
        ``seen`` (M, 2) px from the state (alpha, rotation matrix, translation mm)."""
        return state_offset(self.point_model, self.speaker.camera, alpha, rotation,
                            translation, seen)

    def _fit_lags(self, image: np.ndarray, alpha: np.ndarray, pose: Pose,
                  fu: FusionPolicy) -> bool:
        """A fit between readings that the appearance suspects of an occlusion (its first
        frames, not inside one): read this frame. Where the reader finds the face further
        from the fit than the motion model is allowed to miss it (``FusionPolicy.reread`` x
        the reader's own 99th percentile), the mispredicted points are the fit's, lagging a
        motion between readings, not an occluder's: True (not ``occluded``), and the next
        frame is read. Where the reading agrees with the fit, the suspicion stands (a hand
        under which the reader reads a face where the fit is)."""
        assert fu.reread is not None  # (the caller's condition)
        if self.tracker.occluding:
            return False
        late = self._finder(image, self._reading, self.reader)
        self.lag_reads += 1
        if late is None:
            return False
        self._reading = late
        seen = late.landmarks[self.point_model.landmarks, :2]
        missed = self._offset(alpha, pose.matrix, pose.translation, seen)
        if not np.isfinite(missed) or missed <= fu.reread * self.point_model.offset_p99:
            return False
        self._since_read = fu.read_every - 1
        self.rereads += 1
        return True

    def _unfamiliar(self, alpha: np.ndarray, pose: Pose | None = None) -> bool:
        """Whether the lips at ``alpha`` open or stretch beyond what the enrolment showed
        (its 2nd-98th percentiles of aperture and width), or the head at ``pose`` is turned
        beyond the rotations its appearance was trained on (each component's 2nd-98th
        percentile, :func:`~articast.core.faces.build.turn_coverage`; a speaker enrolled
        before has none): the appearance was not trained there, and mispredicts without
        anything in front of the mouth. Issue 38: every frame flagged ``occluded`` on
        metricaltracker_wojtek_video (11, the head bowed 8-13 deg further than its enrolment's
        training frames, turned 14-26 deg where they reached 15) and liveportrait_d10 (2,
        tilted up to 3.6 deg in roll where they reached 1.8) was beyond them; none of cap12's
        96 frames with his hands at his chin was."""
        cov = self.speaker.report.get("coverage") or {}
        ap, wd = (float(x[0]) for x in lip_measures(self.speaker.model,
                                                    np.asarray(alpha)[None]))
        for value, key in ((ap, "aperture_mm"), (wd, "width_mm")):
            lo_hi = cov.get(key)
            if lo_hi and not lo_hi[0] <= value <= lo_hi[1]:
                return True
        turn = self._turns
        if pose is not None and turn is not None:
            away = np.degrees(axis_angle(pose.matrix @ turn[0].T))
            if np.any((away < turn[1][:, 0]) | (away > turn[1][:, 1])):
                return True
        return False

    def _agrees(self, result: TrackResult, reading: Any, fu: FusionPolicy) -> TrackResult:
        """An ok fit judged by the frame's landmark reading (``FusionPolicy.agreement``)."""
        if not result.ok:
            return result
        pm = self.point_model
        off = self._offset(result.alpha, result.pose.matrix, result.pose.translation,
                           self._seen(reading))
        limit = fu.agreement * pm.offset_p99
        result = _with(result, extra={**result.extra, "landmark_offset": off})
        if np.isfinite(off) and off <= limit:
            return result
        return self._not_ok(result, f"diverged: the landmarks are {100 * off:.1f} % of the "
                                    f"face's size from the fitted face (limit {100 * limit:.1f} "
                                    f"%: {fu.agreement:g} x the enrolment's 99th percentile)")

    def _judge(self, result: TrackResult) -> TrackResult:
        if not result.ok:
            return result
        robust = result.extra.get("robust_residual")
        if robust is not None and robust > self._limit:
            return self._not_ok(result, f"diverged: residual {robust:.3g} is above "
                                        f"{self.policy.residual_factor:g} x the enrolment's "
                                        f"99th percentile ({self.speaker.residual.p99:.3g})")
        return result



"""The per-sequence tracker: warm start, motion prediction, divergence detection and
re-initialisation around the single-frame fit of :mod:`articast.core.tracking.fitting`
(METHOD.md §3).

Core never reads a clock: pass ``clock`` (e.g. ``time.perf_counter``) to get ms per frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from articast.core.appearance.maps import (
    ImageMaps,
    MapBuffers,
    image_maps,
    image_pyramid,
    roi_of,
)
from articast.core.appearance.models import AppearanceModel, sample_normals
from articast.core.model.camera import Camera, Pose, axis_angle, rotation_matrix
from articast.core.model.face import FaceModel, range_motion
from articast.core.outputs.lips import lips_dict
from articast.core.tracking import kernels
from articast.core.tracking.fitting import (
    FitPolicy,
    FitResult,
    Problem,
    StatePrior,
    fit_gauss_newton,
    fit_nelder_mead,
)
from articast.core.tracking.points import PointTerm
from articast.core.tracking.result import TrackResult

OPTIMISERS = ("gauss-newton", "nelder-mead")
_EYE = np.eye(3)
_ZERO3 = np.zeros(3)


def pixel_spread(pixels: np.ndarray) -> float:
    """``pixels.std()`` (any shape, every channel together), by OpenCV's one pass over a
    contiguous copy instead of numpy's float64 conversion and two passes (the contrast checks
    of a frame and of the face: ~5x cheaper). A uint8 view, (h, w) or (h, w, 3) (a channel's
    or the frame's every n-th pixel), is read in place by the compiled kernel, the same number
    without the copy, column by column: its sums are exact integers, the same in any order,
    and a column's pixels lie on as many rows, whose cache lines a frame just decoded must all
    fetch from memory: fetched together they arrive in about half the time (a cold 640 x 640
    frame's every 8th pixel: 34 against 70 us)."""
    if kernels.AVAILABLE and pixels.dtype == np.uint8:
        if pixels.ndim == 2:
            return float(kernels.pixels_sd2(pixels.T))
        if pixels.ndim == 3 and pixels.shape[2] == 3:
            return float(kernels.pixels_sd3(pixels.transpose(1, 0, 2)))
    return float(cv2.meanStdDev(np.ascontiguousarray(pixels).reshape(-1, 1))[1][0, 0])


# s.d. of the head's motion between frames, (rad, mm), per camera rig: the fit's pose prior,
# and the pose uncertainty the la point selection plans for (train_appearance(pose_sigma=)).
POSE_SIGMA: dict[str, tuple[float, float]] = {"head": (0.001, 0.1), "desk": (0.003, 0.5)}


def appearance_options(rig: str, kind: str) -> dict[str, Any]:
    """``train_appearance`` options for a camera rig: the head-pose uncertainty the point
    selection plans for (:data:`POSE_SIGMA`), and, on a desk camera, rotation terms for la_lin
    and la_quad (a head turning under a light fixed to the room changes its shading)."""
    if rig not in POSE_SIGMA:
        raise ValueError(f"rig must be one of {sorted(POSE_SIGMA)}, got {rig!r}")
    return {"pose_sigma": POSE_SIGMA[rig],
            "rotation_terms": rig == "desk" and kind in ("la_lin", "la_quad")}


@dataclass(frozen=True, eq=False)
class Evidence:
    """What a frame's fit uses besides the image's local appearance (all optional).

    points : the frame's landmark readings as a fit term
        (:class:`~articast.core.tracking.points.PointTerm`).
    prior : a motion model's prediction of the whole state
        (:class:`~articast.core.tracking.fitting.StatePrior`); it replaces the tracker's own
        constant-velocity prediction, pose prior and articulation prior.
    appearance_weight : the appearance term's weight (0: not sampled).
    levels : pyramid levels to fit (None: the policy's, with its fast path).
    confirm : a second opinion on a fit the appearance finds ``occluded``: called with its
        articulation (K,) and head pose; True drops the verdict (the caller knows the
        appearance is not to be trusted there, and other evidence confirms the fit).
    """

    points: PointTerm | None = None
    prior: StatePrior | None = None
    appearance_weight: float = 1.0
    levels: tuple[int, ...] | None = None
    confirm: Callable[[np.ndarray, Pose], bool] | None = None


@dataclass(frozen=True)
class TrackingPolicy:
    """How a sequence is tracked.

    optimiser : "gauss-newton" (default) or "nelder-mead" (the paper's baseline).
    levels : pyramid levels fitted every frame, coarse first; reinit_levels on re-initialisation
        after a bad frame; init_levels on the first frame (from the neutral articulation,
        which can be far from the speaker's: two octaves coarser widens the basin).
    predict : constant-velocity prediction of the state from the two last good frames,
        scaled by ``velocity_gain``.
    divergence_factor : a frame whose residual exceeds this many times the running residual
        level (and ``residual_floor``) is not trusted: the tracker retries from the last good
        state and from the neutral articulation; if that fails the frame is marked not ok.
        This test uses the robust residual (its own running level): judged on raw squares,
        4 % of the teleconference frames (articulations beyond the enrolment's range, fitted
        within 0.2-0.9 mm) were flagged for a few mispredicted points; a hand over the mouth
        still raises it 7x.
    level_rate, level_clip : the running residual levels follow accepted frames at this rate;
        with a robust la fit the divergence level moves towards at most ``level_clip`` times
        itself per frame, so a hand sliding in over several frames cannot raise the bar it is
        judged by (it crept 2.5x and let 9 mm-wrong frames through as ok before the clip).
    fast_path_factor : first fit the full-resolution level alone from the prediction, and keep
        it if its residual is within this factor of the running level (0 = always run every
        level).
    coarse_iterations : per-frame iteration cap on the coarse levels (they only need to bring
        the state into the fine level's basin); 0 = the fit policy's own.
    pose_anchor_rate : None: the pose prior is centred on the previous frame's pose. A
        number r: on an anchor, the running average of the accepted poses updated at rate r
        per frame (0 = the first frame's pose). A head-mounted camera does not move on the
        head, but a prior on frame-to-frame motion alone lets the pose random-walk (several
        mrad of pitch over 3 s), and the articulation absorbs the drift; the anchor stops it.
    occlusion_q : the occlusion test (None: off). A sample point is an outlier when the
        squared norm of its weighted residual (``FitResult.point_q``, over its 8 la values,
        each whitened by the enrolment's leave-one-out residual s.d. of that feature, so ~8
        where the model is right) exceeds this (250: ~5.6 s.d. per value; the fit's Cauchy
        weight of such a point is below 0.13, it is all but ignored) and
        ``occlusion_factor`` x the point's own running level (points the model always
        predicts badly need more). A frame with ``occlusion_points`` outliers within
        ``occlusion_span_mm`` of one of them (head frame; 60 mm: a palm over part of the
        face, not mispredictions scattered over all of it) is not ok, ``occluded``, and the
        tracker keeps its robust fit (no re-initialisation, the running levels are left
        alone): a hand sliding over the mouth or chin is tracked through, and its frames
        are sent with ok false and the last good state held. Only the points the
        articulation moves (``occlusion_moving`` x the largest displacement over the
        training range, or more: lips, jaw line, chin) are judged:
        rigid points (eyes, brows, nose) mispredict whenever the head turns (judged, they
        made 13-22 % of the clean clip cap13 "occluded"), and hiding them does not bias the
        articulation. Measured and left out: requiring the outliers to be next to each
        other (Delaunay edges) -- a hand from below spoils both lip corners first, across
        the mouth, and frames 2-4 mm wrong passed; scaling the threshold by the frame's
        median residual ratio -- a hand raises that too (1.5-2x), and hid frames 3.5 mm
        wrong. Neither changed the clean clips.
    occlusion_frames : frames in a row that must show the outliers before they are flagged
        (the first ones are streamed ok, their levels left alone). 2: an inner-lip point
        mispredicted for one frame as the mouth opens fast (teeth appearing) reached q = 816
        with three others above 250 on a clean rendered clip, the fit within 1 mm; a hand
        stays. The cost: a hand's first frame is streamed (on ``hand_slide`` its error is the
        tracker's own just before the hand: 0.3 and 1.5 mm).
    occlusion_stay_q : once flagged, a frame stays ``occluded`` (until a frame is ok) while one
        judged point is above this: after a diverged frame under the hand, fits 3.7 mm
        wrong with a single point at q = 200-260 were streamed ok.
    occlusion_rate : the per-point running levels follow frames that are ok at this rate
        (moving towards at most ``level_clip`` x themselves per frame).
    occlusion_facing : only the points that face the camera this frame vote: the cosine of
        the angle between the point's surface normal (the mean face's) and its direction to
        the camera at least this (None: all vote). A point seen at a grazing angle (the jaw
        line of a frontal face, the chin of a face bowed down) samples the background or
        the neck beside the face, which the appearance never learned: two such points
        flagged 14-21 talking frames "occluded" on latentsync_demo3 and wojtek (their
        outliers faced the camera at 0.1-0.39) where a hand at cap12's chin covered points
        facing it at 0.45-0.65. 0.34 (70 deg) and 0.42 cleared the same frames on half A
        of the people (latentsync_demo3 14 to 0, wojtek 21 to 11, liveportrait_d10 2 to 2);
        0.5 cleared one more there but none of cap12's hand: 0.34 keeps the margin on the
        side of a real occluder (docs/RESULTS.md).
    min_valid_fraction : below this fraction of sample points inside the image: not ok.
    min_contrast : luminance s.d. of the face region below which the frame is blank.
    """

    optimiser: str = "gauss-newton"
    fit: FitPolicy = field(default_factory=FitPolicy)
    reinit_fit: FitPolicy = field(default_factory=lambda: FitPolicy(max_iterations=30))
    levels: tuple[int, ...] = (2, 1, 0)
    reinit_levels: tuple[int, ...] = (1, 0)
    init_levels: tuple[int, ...] = (2, 1, 0)
    coarse_iterations: int = 2
    fast_path_factor: float = 1.5
    predict: bool = True
    velocity_gain: float = 0.8
    divergence_factor: float = 4.0
    residual_floor: float = 0.5
    level_rate: float = 0.05
    level_clip: float = 1.5
    min_valid_fraction: float = 0.8
    min_contrast: float = 3.0
    roi_margin_px: float = 24.0
    search_step_mm: float = 8.0
    search_radius_mm: float = 40.0
    pose_anchor_rate: float | None = None
    occlusion_q: float | None = 250.0
    occlusion_factor: float = 30.0
    occlusion_floor: float = 4.0
    occlusion_points: int = 2
    occlusion_span_mm: float = 60.0
    occlusion_frames: int = 2
    occlusion_stay_q: float = 150.0
    occlusion_moving: float = 0.2
    occlusion_rate: float = 0.05
    occlusion_facing: float | None = 0.34

    def __post_init__(self) -> None:
        if self.optimiser not in OPTIMISERS:
            raise ValueError(f"optimiser must be one of {OPTIMISERS}, got {self.optimiser!r}")

    @classmethod
    def for_rig(cls, rig: str, **changes) -> TrackingPolicy:
        """The policy for a camera rig: "head" (camera fixed to the head: the pose moves by
        at most ~0.1 mm / 1 mrad between frames) or "desk" (free head motion)."""
        if rig not in POSE_SIGMA:
            raise ValueError(f"rig must be one of {sorted(POSE_SIGMA)}, got {rig!r}")
        sr, st = POSE_SIGMA[rig]
        fit = changes.pop("fit", FitPolicy(pose_sigma_rad=sr, pose_sigma_mm=st))
        changes.setdefault("pose_anchor_rate", 0.02 if rig == "head" else None)
        return cls(fit=fit, **changes)


class Tracker:
    """Tracks one face through one sequence of frames."""

    def __init__(self, model: FaceModel, appearance: AppearanceModel, camera: Camera,
                 policy: TrackingPolicy | None = None, initial_pose: Pose | None = None,
                 clock: Callable[[], float] | None = None, measure_lips: bool = True) -> None:
        """measure_lips : False leaves ``TrackResult.lips`` None (a caller that measures
        the lips of the state it streams, e.g. a smoothed one, once a frame)."""
        self.policy = policy or TrackingPolicy()
        self.measure_lips = measure_lips
        pol = self.policy
        fitted = {}
        for name in ("levels", "reinit_levels", "init_levels"):
            usable = tuple(lv for lv in getattr(pol, name) if lv in appearance.levels)
            if not usable:
                raise ValueError(f"the appearance model (levels {appearance.levels}) has none "
                                 f"of the policy's {name} {getattr(pol, name)}")
            fitted[name] = usable
        self.policy = pol = replace(pol, **fitted)  # e.g. a model trained on levels (0, 1)
        self.problem = Problem(model, appearance, camera, self.policy.fit.prior)
        self._robust = self.problem.loss_scale(self.policy.fit.robust_scale) is not None
        self.model, self.camera = model, camera
        self.initial_pose = initial_pose
        self.clock = clock
        self.k = model.n_params
        # the occlusion test's points: those the articulation moves
        motion = range_motion(self.problem.s_basis, model.stats).max(0)
        self._judged = motion >= pol.occlusion_moving * motion.max()
        pts = self.problem.s_mean
        self._span = np.linalg.norm(pts[:, None] - pts[None], axis=2) <= pol.occlusion_span_mm
        self._normals = sample_normals(model, appearance)
        # each frame's lazy full-resolution maps go to the same memory (one image_pyramid
        # call a frame makes them; a frame's maps are dropped before the next frame's)
        self._map_buffers = MapBuffers()
        self._alpha_limit = (self.problem.bound + 3.0).tolist()  # _good's range test
        self.reset()

    def reset(self, pose: Pose | None = None, alpha: np.ndarray | None = None) -> None:
        """Forget the sequence; the next frame starts from ``pose`` (or a search)."""
        self._frame = -1
        self._theta: np.ndarray | None = None
        self._prev: np.ndarray | None = None
        self._level: float | None = None  # running raw residual (fast path)
        self._rlevel: float | None = None  # running robust residual (divergence)
        self._qlevel: np.ndarray | None = None  # running residual per sample point (occlusion)
        self._suspect = 0  # frames in a row with outliers (occlusion)
        self._occluding = False  # inside an occlusion: flagged since the last ok frame
        self._held: tuple[np.ndarray, Pose] | None = None  # last state streamed as ok
        self._gain = 1.0
        self._gap = False
        self._anchor: np.ndarray | None = None
        if pose is not None:
            a = np.zeros(self.k) if alpha is None else np.asarray(alpha, np.float64)
            self._theta = np.concatenate([a, pose.as_vector()])

    def restart(self, pose: Pose, alpha: np.ndarray) -> None:
        """Continue the sequence from another state (e.g. read off face landmarks): no
        velocity across it, but the running residual levels are kept, so the next frame is
        judged as every other frame (:meth:`reset` forgets them)."""
        if self._level is None:
            self.reset(pose, alpha)
            return
        self._theta = np.concatenate([np.asarray(alpha, np.float64), pose.as_vector()])
        self._prev = None
        if self._anchor is not None:
            self._anchor = pose.as_vector()

    @property
    def state(self) -> tuple[np.ndarray, Pose] | None:
        """The articulation (K,) and head pose the next frame starts from (the last fit, or
        the state of a reset), None before a start."""
        if self._theta is None:
            return None
        return self._theta[:self.k].copy(), Pose.from_vector(self._theta[self.k:])

    @property
    def occluding(self) -> bool:
        """Whether the last frame was ``occluded`` (an occlusion is being tracked through)."""
        return self._occluding

    @property
    def pose_prior_centre(self) -> np.ndarray | None:
        """Pose (6,) the next frame's pose prior is centred on (None before a start)."""
        if self._anchor is not None:
            return self._anchor.copy()
        return None if self._theta is None else self._theta[self.k:].copy()

    # ------------------------------------------------------------------ fitting
    def _fit(self, image: np.ndarray, theta0: np.ndarray, levels: tuple[int, ...],
             cache: dict[int, ImageMaps], policy: FitPolicy | None = None,
             pose_ref: np.ndarray | None = None, refine_gain: bool = True,
             alpha_ref: np.ndarray | None = None, evidence: Evidence | None = None,
             uv0: np.ndarray | None = None, rot0: np.ndarray | None = None) -> FitResult:
        """uv0 : the sample points projected at theta0, if the caller has them; rot0 : theta0's
        rotation as a matrix, if the caller has it."""
        pol = self.policy
        ev = evidence or Evidence()
        theta = theta0
        result: FitResult | None = None
        evals = 0
        if any(lv not in cache for lv in levels):  # one ROI and colour conversion per frame
            uv = self.problem.project(theta0) if uv0 is None else uv0
            sig = self.problem.appearance.sigma
            margin = pol.roi_margin_px + 4 * sig * 2 ** max(levels)
            # lazy level 0 (compiled kernel) smooths only what the fit samples: no need to
            # shrink its ROI; otherwise a tighter ROI for the costly full-resolution blur
            lazy = self.problem.jit
            fine = None if lazy else roi_of(uv, pol.roi_margin_px + 4 * sig)
            cache.update(image_pyramid(image, roi_of(uv, margin), sig,
                                       tuple(lv for lv in levels if lv not in cache), fine,
                                       lazy=lazy, buffers=self._map_buffers))
        for level in levels:
            fit_pol = policy or pol.fit
            if policy is None and level > 0 and pol.coarse_iterations:
                fit_pol = replace(fit_pol, max_iterations=pol.coarse_iterations)
            args = (self.problem, cache[level], level, theta[:self.k],
                    theta[self.k:self.k + 3], theta[self.k + 3:], fit_pol)
            if pol.optimiser == "nelder-mead":
                result = fit_nelder_mead(*args)
            else:
                ref = None if pose_ref is None else (pose_ref[:3], pose_ref[3:])
                result = fit_gauss_newton(*args, pose_ref=ref, gain0=self._gain,
                                          estimate_gain=(level == 0 and refine_gain),
                                          alpha_ref=alpha_ref, points=ev.points,
                                          state_prior=ev.prior,
                                          appearance_weight=ev.appearance_weight,
                                          rot0=rot0 if theta is theta0 else None)
            evals += result.evals
            theta = result.theta
        assert result is not None
        if len(levels) == 1:  # (a live frame's: the record as it is, its evals the same)
            return result
        return FitResult(result.alpha, result.rotation, result.translation, result.cost,
                         result.residual, evals, result.iterations, result.converged,
                         result.valid_fraction, result.costs, result.gain,
                         result.robust_residual, result.point_q, result.information)

    def _search(self, image: np.ndarray, pose: Pose) -> np.ndarray:
        """Coarse grid search of the translation around ``pose`` at the coarsest level."""
        pol = self.policy
        level = max(pol.init_levels)
        li = self.problem.appearance.level_index(level)
        sig = self.problem.appearance.sigma
        h, w = image.shape[:2]
        maps = image_maps(image, (0, 0, w, h), sig, level)
        steps = np.arange(-pol.search_radius_mm, pol.search_radius_mm + 1e-9, pol.search_step_mm)
        rot = pose.matrix
        best, best_cost = None, np.inf
        for dx in steps:
            for dy in steps:
                t = pose.translation + [dx, dy, 0.0]
                r, _, vf = self.problem.residuals(maps, li, np.zeros(self.k), rot, t, False)
                if vf < pol.min_valid_fraction:
                    continue  # samples outside the image cost nothing: never prefer them
                c = float(r @ r) / vf
                if c < best_cost:
                    best, best_cost = np.concatenate([np.zeros(self.k), pose.rotation, t]), c
        if best is None:
            return np.concatenate([np.zeros(self.k), pose.as_vector()])
        return best

    # ------------------------------------------------------------------ per frame
    def track(self, image: np.ndarray, t: float,
              translation_hint: np.ndarray | None = None,
              evidence: Evidence | None = None) -> TrackResult:
        """Fit one frame (BGR uint8) taken at time ``t`` (s).

        translation_hint : the head's translation (3,) mm on this frame as measured by other
            means (the face's image motion since the last frame,
            :mod:`articast.core.faces.motion`): the fit starts there, and the pose prior's
            translation is centred there instead of on the last pose. Ignored with a pose
            anchor (``pose_anchor_rate``: a head-mounted camera).
        evidence : the frame's landmark readings and a motion model's prediction
            (:class:`Evidence`): the fit starts at the prediction and uses both."""
        t0 = self.clock() if self.clock else 0.0
        ev = evidence
        self._frame += 1
        pol = self.policy
        cache: dict[int, ImageMaps] = {}
        if self._theta is None:
            if self.initial_pose is None:
                return self._lost(t, t0, "not_started: no initial pose: give one or call "
                                         "reset(pose)", 0)
            self._theta = self._search(image, self.initial_pose)
            first = self._fit(image, self._theta, pol.init_levels, cache, pol.reinit_fit,
                              refine_gain=False)
            return self._accept(first, t, t0, first.evals, force=True)
        theta0 = self._theta
        if pol.predict and self._prev is not None:
            theta0 = self._theta + pol.velocity_gain * (self._theta - self._prev)
        if pol.pose_anchor_rate is not None:
            translation_hint = None  # a head-mounted camera: the pose is held to its anchor
        if translation_hint is not None:
            theta0 = theta0.copy()
            theta0[self.k + 3:] = translation_hint
        if ev is not None and ev.prior is not None:
            pr = ev.prior
            theta0 = np.concatenate([pr.alpha, axis_angle(pr.rotation), pr.translation])
        rot0 = rotation_matrix(theta0[self.k:self.k + 3])  # (the projection's and the fit's)
        uv = self.problem.project(theta0, rot0)
        roi = roi_of(uv, pol.roi_margin_px)
        x0, y0, x1, y1 = (max(0, roi[0]), max(0, roi[1]), roi[2], roi[3])
        patch = image[y0:y1:4, x0:x1:4, 1]  # green, every 4th pixel: contrast is coarse
        if patch.size == 0 or pixel_spread(patch) < pol.min_contrast:
            return self._lost(t, t0, "blank: no contrast where the face should be", 0)
        ref: np.ndarray | None = None
        a_ref: np.ndarray | None = None
        if ev is None or ev.prior is None:  # (else the motion model's prior replaces both)
            ref = self.pose_prior_centre
            if translation_hint is not None and ref is not None:
                ref[3:] = translation_hint
            a_ref = theta0[:self.k]
        fit = None
        evals = 0
        levels = pol.levels if ev is None or ev.levels is None else ev.levels
        landmarks = ev is not None and ev.points is not None
        if (pol.fast_path_factor and self._level is not None and self._prev is not None
                and levels != (0,)):
            # most frames are easy: try the full-resolution fit from the prediction alone, and
            # pay for coarse-to-fine only when its residual says the motion was not predicted
            quick = self._fit(image, theta0, (0,), cache, pose_ref=ref, alpha_ref=a_ref,
                              evidence=ev, uv0=uv, rot0=rot0)
            evals += quick.evals
            if self._good(quick) and quick.residual <= pol.fast_path_factor * self._level:
                fit = quick
        if fit is None:
            fit = self._fit(image, theta0, levels, cache, pose_ref=ref, alpha_ref=a_ref,
                            evidence=ev, uv0=uv, rot0=rot0)
            evals += fit.evals
        if self._gap and self._good(fit, landmarks):
            # first frame after a gap: the last good state may be far from the face that
            # reappears (the mouth moved behind the hand); re-initialise too, keep the best
            again = self._fit_from_neutral(image, cache, ref, ev)
            evals += again.evals
            if self._good(again, landmarks) and again.cost < fit.cost:
                fit = again
        if not self._good(fit, landmarks):
            tries = [fit]
            # (with landmark readings every start lands where they put it: no retry)
            if pol.predict and self._prev is not None and not landmarks:
                tries.append(self._fit(image, self._theta, pol.levels, cache, pose_ref=ref,
                                       evidence=ev))
            if not landmarks:
                tries.append(self._fit_from_neutral(image, cache, ref, ev))
            evals += sum(f.evals for f in tries[1:])
            fit = min(tries, key=lambda f: f.cost)
            if not self._good(fit, landmarks):
                why = ("left_image: points left the image"
                       if fit.valid_fraction < pol.min_valid_fraction
                       else f"diverged: residual {fit.robust_residual:.3g} is far above its "
                            f"running level {self._rlevel or 0:.3g} (occlusion or lost face)")
                return self._lost(t, t0, why, evals, fit)
        fit_pose = Pose(fit.rotation, fit.translation)
        occluded = self.occlusion(fit.point_q, fit.gain, staying=self._occluding, pose=fit_pose)
        if (occluded is not None and ev is not None and ev.confirm is not None
                and ev.confirm(fit.alpha, fit_pose)):
            occluded = None
        self._suspect = self._suspect + 1 if occluded else 0
        if occluded and not self._occluding and self._suspect < self.policy.occlusion_frames:
            return self._accept(fit, t, t0, evals, keep_point_levels=True, pose=fit_pose)
        self._occluding = occluded is not None
        return self._accept(fit, t, t0, evals, occluded=occluded, pose=fit_pose)

    def _fit_from_neutral(self, image: np.ndarray, cache: dict[int, ImageMaps],
                          ref: np.ndarray | None, evidence: Evidence | None = None
                          ) -> FitResult:
        """Re-initialisation during a sequence: the last pose with the neutral articulation,
        more iterations, but the same pose prior as every frame, so that its cost compares
        with the regular fit's."""
        assert self._theta is not None
        pol = self.policy
        neutral = self._theta.copy()
        neutral[:self.k] = 0.0
        retry = replace(pol.reinit_fit, pose_sigma_rad=pol.fit.pose_sigma_rad,
                        pose_sigma_mm=pol.fit.pose_sigma_mm)
        return self._fit(image, neutral, pol.reinit_levels, cache, retry, pose_ref=ref,
                         evidence=evidence)

    def _good(self, fit: FitResult, landmarks: bool = False) -> bool:
        """Whether a fit is usable: in the image, finite, inside the model's range and, fitted
        on the appearance alone, with a residual not far above its running level. A fit with
        landmark readings in it is not judged by its appearance residual here: the caller
        judges it by the landmarks (an articulation the enrolment never showed, a wide-open
        mouth, raises the appearance residual of a fit that the landmarks confirm)."""
        pol = self.policy
        # (Python floats: the same tests as numpy's isfinite and abs(alpha) > bound + 3,
        # a few times cheaper on K + 6 numbers)
        alpha = fit.alpha.tolist()
        if fit.valid_fraction < pol.min_valid_fraction or not all(
                map(math.isfinite, alpha + fit.rotation.tolist() + fit.translation.tolist())):
            return False
        if any(abs(a) > b for a, b in zip(alpha, self._alpha_limit, strict=True)):
            return False
        if self._level is None or landmarks:
            return True
        assert self._rlevel is not None and fit.robust_residual is not None
        return fit.robust_residual <= max(pol.divergence_factor * self._rlevel,
                                          pol.residual_floor)

    def occlusion(self, q: np.ndarray | None, gain: float = 1.0,
                  staying: bool = False, pose: Pose | None = None) -> str | None:
        """The ``occluded`` reason for a fit whose per-point residuals ``q`` (S,) show that
        the part of the face the articulation moves no longer looks like the speaker, else
        None (see ``TrackingPolicy.occlusion_q``). Cheap: one compiled call over S
        (:meth:`occlusion_numpy`: the reference).

        gain : the fit's image gain. The model's mispredictions grow with it (the weights
        whiten residuals at the enrolment's exposure), so q is judged divided by gain^2
        when the image is brighter: at gain 1.2 a clean frame's worst lip points crossed
        the threshold.
        staying : inside an occlusion (the previous frames occluded, or lost since): one
        point above ``occlusion_stay_q`` keeps the frame occluded.
        pose : the fit's head pose, for ``occlusion_facing`` (None: every point votes)."""
        pol = self.policy
        if (pol.occlusion_q is None or q is None or self._qlevel is None
                or not self.problem.appearance.kind.startswith("la")):
            return None  # (tex: one z-scored value per point, another scale)
        out, n_out, n_judged = self._votes(q, gain, staying, pose)
        if staying and n_out:
            return (f"occluded: still {n_out} of {n_judged} sample points on the lips, "
                    f"jaw and chin unlike the face; tracked through; last good state held")
        if n_out < pol.occlusion_points or (
                self._span[np.ix_(out, out)].sum(1).max() < pol.occlusion_points):
            return None
        return (f"occluded: {n_out} of {n_judged} sample points on the lips, jaw and "
                f"chin no longer look like the face (a hand or an object over them, or the fit "
                f"is wrong there); tracked through; last good state held")

    def _votes(self, q: np.ndarray, gain: float, staying: bool, pose: Pose | None
               ) -> tuple[np.ndarray, int, int]:
        """:meth:`occlusion_numpy` in one compiled call
        (:func:`~articast.core.tracking.kernels.occlusion_votes`, the same tests)."""
        pol = self.policy
        if not kernels.AVAILABLE or q.dtype != np.float64:
            return self.occlusion_numpy(q, gain, staying, pose)
        assert self._qlevel is not None and pol.occlusion_q is not None
        normals, rot, t, min_facing = self.problem.s_mean, _EYE, _ZERO3, math.nan
        if pol.occlusion_facing is not None and pose is not None and self._normals is not None:
            normals, rot, min_facing = self._normals, pose.matrix, pol.occlusion_facing
            t = np.array(pose.translation, np.float64)
        return kernels.occlusion_votes(
            q, self._judged, self.problem.s_mean, normals, rot, t, float(min_facing),
            float(max(1.0, gain) ** 2),
            float(pol.occlusion_stay_q if staying else pol.occlusion_q),
            float(pol.occlusion_factor), self._qlevel, float(pol.occlusion_floor))

    def occlusion_numpy(self, q: np.ndarray, gain: float = 1.0, staying: bool = False,
                        pose: Pose | None = None) -> tuple[np.ndarray, int, int]:
        """:meth:`occlusion`'s per-point test in numpy (the reference of
        :func:`~articast.core.tracking.kernels.occlusion_votes`): the points above their
        limit (S,) bool, their count and the count of points judged."""
        pol = self.policy
        assert self._qlevel is not None
        judged = self._judged & (q > 0)  # q = 0: outside the image
        if pol.occlusion_facing is not None and pose is not None and self._normals is not None:
            judged = judged & (self.facing(pose) >= pol.occlusion_facing)
        q = q / max(1.0, gain) ** 2
        limit = np.maximum(pol.occlusion_stay_q if staying else pol.occlusion_q,
                           pol.occlusion_factor * np.maximum(self._qlevel, pol.occlusion_floor))
        out = judged & (q > limit)
        return out, int(np.count_nonzero(out)), int(judged.sum())

    def facing(self, pose: Pose) -> np.ndarray:
        """(S,) how squarely each sample point faces the camera at ``pose``: the cosine of
        the angle between its surface normal (the mean face's) and its direction to the
        camera's centre (1: head on; 0: at the silhouette; < 0: turned away)."""
        assert self._normals is not None
        if kernels.AVAILABLE:  # the same sums in one compiled call (the numpy below: the
            # reference; a frame's occlusion test runs them in kernels.occlusion_votes)
            return kernels.facing_cos(self.problem.s_mean, self._normals, pose.matrix,
                                      np.array(pose.translation, np.float64))
        return self.facing_numpy(pose)

    def facing_numpy(self, pose: Pose) -> np.ndarray:
        """:meth:`facing` in numpy (the reference of
        :func:`~articast.core.tracking.kernels.facing_cos`)."""
        assert self._normals is not None
        rot = pose.matrix
        p = self.problem.s_mean @ rot.T + pose.translation
        n = self._normals @ rot.T
        return -(n * p).sum(1) / np.maximum(np.linalg.norm(p, axis=1), 1e-9)

    def _update_point_levels(self, q: np.ndarray | None) -> None:
        if q is None:
            return
        if self._qlevel is None:
            self._qlevel = np.maximum(q, self.policy.occlusion_floor)
            return
        pol = self.policy
        lv = self._qlevel
        # lv[q > 0] += rate * (min(q, clip * lv) - lv)[q > 0]: the same sums on every point,
        # written where seen (q = 0: outside the image; fewer calls than boolean indexing)
        np.add(lv, pol.occlusion_rate * (np.minimum(q, pol.level_clip * lv) - lv), out=lv,
               where=q > 0)

    def _accept(self, fit: FitResult, t: float, t0: float, evals: int,
                force: bool = False, occluded: str | None = None,
                keep_point_levels: bool = False, pose: Pose | None = None) -> TrackResult:
        """``pose``: the fit's (``Pose(fit.rotation, fit.translation)``), if the caller made it
        already (immutable: the held state and the result share it)."""
        pol = self.policy
        if occluded is not None:
            # keep tracking from the robust fit (its state seeds the next frame), but judge
            # nothing by it: no level, anchor or gain update; the last good state is streamed
            self._prev, self._theta = self._theta, fit.theta
            alpha, held = self._held if self._held is not None else (
                fit.alpha, pose if pose is not None else Pose(fit.rotation, fit.translation))
            return TrackResult(self._frame, t, alpha.copy(), held, False, occluded,
                               fit.residual, evals, fit.iterations, self._ms(t0),
                               {"converged": fit.converged, "robust_residual":
                                fit.robust_residual, "point_q": fit.point_q,
                                "alpha_fit": fit.alpha.copy(), "theta_fit": fit.theta,
                                "information": fit.information},
                               self._lips(alpha))
        if force and self._level is None and fit.valid_fraction < pol.min_valid_fraction:
            return self._lost(t, t0, "no_face: the initial search did not find the face",
                              evals, fit)
        self._prev = self._theta if not force else None
        self._theta = fit.theta
        rate = pol.pose_anchor_rate
        if rate is not None:
            pose_vec = fit.theta[self.k:]
            self._anchor = (pose_vec.copy() if self._anchor is None
                            else (1 - rate) * self._anchor + rate * pose_vec)
        self._gain = fit.gain
        self._gap = False
        lvl, rlvl = fit.residual, fit.robust_residual
        if self._level is None or self._rlevel is None:
            self._level, self._rlevel = lvl, rlvl
        else:
            self._level += pol.level_rate * (lvl - self._level)
            # the divergence level moves towards at most level_clip x itself (la only: tex
            # residuals are least squares and jumpier; clipped, tex_lin flagged 6 % more
            # teleconference frames)
            if self._robust:
                rlvl = min(rlvl, pol.level_clip * self._rlevel)
            self._rlevel += pol.level_rate * (rlvl - self._rlevel)
        if not keep_point_levels:
            self._update_point_levels(fit.point_q)
        fit_pose = pose if pose is not None else Pose(fit.rotation, fit.translation)
        self._held = (fit.alpha.copy(), fit_pose)
        return TrackResult(self._frame, t, fit.alpha.copy(), fit_pose,
                           True, "", fit.residual, evals, fit.iterations, self._ms(t0),
                           {"converged": fit.converged, "valid_fraction": fit.valid_fraction,
                            "gain": fit.gain, "robust_residual": fit.robust_residual,
                            "point_q": fit.point_q, "information": fit.information},
                           self._lips(fit.alpha))

    def _lost(self, t: float, t0: float, reason: str, evals: int,
              fit: FitResult | None = None) -> TrackResult:
        self._prev = None  # no velocity across a gap
        self._gap = True
        if self._held is not None:
            alpha, pose = self._held[0].copy(), self._held[1]
        elif self._theta is None:
            alpha, pose = np.zeros(self.k), self.initial_pose or Pose()
        else:
            alpha = self._theta[:self.k].copy()
            pose = Pose(self._theta[self.k:self.k + 3], self._theta[self.k + 3:])
        return TrackResult(self._frame, t, alpha, pose, False, reason,
                           fit.residual if fit else float("nan"), evals,
                           fit.iterations if fit else 0, self._ms(t0),
                           {"robust_residual": fit.robust_residual} if fit else {},
                           self._lips(alpha))

    def _lips(self, alpha: np.ndarray) -> dict[str, float] | None:
        return lips_dict(self.model, alpha) if self.measure_lips else None

    def _ms(self, t0: float) -> float:
        return (self.clock() - t0) * 1000.0 if self.clock else 0.0


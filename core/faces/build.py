"""From an enrolment clip's frames and landmarks to a :class:`~articast.core.faces.speaker.Speaker`.

1. :func:`~articast.core.faces.enrol.enrol_geometry`: pose removal, scale, guided PCA.
2. Each kept frame's head pose from the model shape at its landmark articulation and the
   landmarks' pixels (PnP).
3. Training frames chosen for **coverage**: farthest-point sampling in the articulation space,
   so the appearance model sees the extremes of the clip, not its most common posture (the
   tracker's p95 tail was articulation beyond the enrolment's range).
4. la appearance trained at the landmark states, then **refined**: every training frame is
   fitted by analysis-by-synthesis from its landmark state with that first model (it sees
   finer than the landmarks), and the appearance is trained again at the fitted states.
5. The robust residual of the final models on held-out frames: what a live frame of this
   speaker should look like to the tracker (its 99th percentile bounds ``ok``).
6. With the live reader's landmarks of the same frames (``readings``): how that network reads
   this face, with the errors its points share
   (:func:`~articast.core.tracking.points.learn_point_model`), the articulation read straight
   off its points (:func:`~articast.core.tracking.points.learn_reading_regression`), and the
   motion model's process noise from the clip's states
   (:func:`~articast.core.tracking.kalman.process_noise`).
7. With the same readings on a desk camera: the speaker's own upper-face references
   (:mod:`articast.core.faces.upper`: open and closed eye, neutral brows, iris radius).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from articast.core.appearance.models import (
    AppearanceModel,
    TrainingFrame,
    mean_rotation,
    train_appearance,
)
from articast.core.errors import InputError
from articast.core.faces.canonical import canonical_face
from articast.core.faces.enrol import EnrolOptions, LandmarkScheme, enrol_geometry
from articast.core.faces.finder import FINDER_NETWORK
from articast.core.faces.fit import fit_pose
from articast.core.faces.flow import default_for, refine_pixels
from articast.core.faces.identity import FaceSignature, signature
from articast.core.faces.speaker import ResidualStats, Speaker
from articast.core.faces.upper import (
    PHOTO_MIN_R,
    Measures,
    UpperReference,
    calibrate,
    change_limits,
)
from articast.core.faces.upper import measure as measure_upper
from articast.core.model.camera import Camera, axis_angle, rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.outputs.lips import lip_measures
from articast.core.tracking.kalman import MotionNoise, process_noise
from articast.core.tracking.points import (
    PointModel,
    learn_point_model,
    learn_reading_regression,
)
from articast.core.tracking.tracker import Tracker, TrackingPolicy, appearance_options


@dataclass(frozen=True)
class BuildOptions:
    """kind : appearance model; train_frames : at most this many training frames; stats_frames
    : at most this many held-out frames for the residual statistics; refine : refinement
    rounds (0 = landmark states only); flow : the model points' pixels refined by optical flow
    before the geometry (:func:`~articast.core.faces.flow.refine_pixels`); None: the rig's
    default (:data:`~articast.core.faces.flow.BY_RIG`: on for a head-mounted camera);
    coverage_seed : None: the training frames' farthest-point sampling starts at the frame
    nearest the clip's median posture (deterministic); a number: at a frame drawn with that
    seed, another equally valid choice of training frames (benchmarks/enrolment_spread.py
    measures how much the tracking depends on that choice)."""

    kind: str = "la_quad"
    train_frames: int = 90
    stats_frames: int = 60
    refine: int = 1
    # filter scale, px. Not train_appearance's face_sigma (0.7 mm on the face, 1.25 px on a
    # webcam face): real video is compressed, and on cap13 filters that small took the
    # still-mouth jitter from 0.43 to 2.85 % of the mouth width (franck 0.067 -> 0.107).
    sigma: float | None = 2.5
    flow: bool | None = None
    coverage_seed: int | None = None


CONSECUTIVE_RUN = 100
"""Consecutive frames an enrolment analyses besides the strided ones (4 s at 25 fps): the
motion model learns from frame-to-frame motion (:func:`~articast.core.tracking.kalman.
process_noise` needs frames at most 50 ms apart)."""


def analysed_frames(total: int, max_frames: int, run: int = CONSECUTIVE_RUN) -> np.ndarray:
    """Indices of the frames of a ``total``-frame clip an enrolment analyses: every
    ceil(total / max_frames)-th, and, when that skips frames, ``run`` consecutive ones from
    the clip's middle. Sorted, unique."""
    total = int(total)
    stride = max(1, int(np.ceil(total / max_frames))) if max_frames > 0 else 1
    idx = np.arange(0, total, stride)
    if stride > 1:
        mid = total // 2
        idx = np.union1d(idx, np.arange(mid, min(total, mid + run)))
    return idx


def coverage_order(alpha: np.ndarray, n: int, start: int | None = None) -> np.ndarray:
    """Indices of ``n`` rows of alpha (F, K) by farthest-point sampling (first: the row
    nearest the median posture unless ``start``)."""
    a = np.asarray(alpha, np.float64)
    n = min(int(n), len(a))
    if start is None:
        start = int(np.argmin(np.linalg.norm(a - np.median(a, 0), axis=1)))
    chosen = [start]
    dist = np.linalg.norm(a - a[start], axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(a - a[nxt], axis=1))
    return np.array(chosen)


def training_order(alpha: np.ndarray, seed: int | None = None) -> np.ndarray:
    """Every row of alpha (F, K) in the order the enrolment takes training frames
    (:func:`coverage_order`): from the median posture, or with ``seed`` from a row drawn with
    it (``BuildOptions.coverage_seed``)."""
    start = None if seed is None else int(np.random.default_rng(seed).integers(len(alpha)))
    return coverage_order(alpha, len(alpha), start)


def fit_states(model: FaceModel, appearance: AppearanceModel, camera: Camera, rig: str,
               frames: Sequence[TrainingFrame]) -> list[tuple[TrainingFrame, float] | None]:
    """Analysis-by-synthesis fit of each frame from its given state (independently).

    Returns, per frame, the frame at its fitted state and its robust residual, or None where
    the fit was not ok.
    """
    tracker = Tracker(model, appearance, camera, TrackingPolicy.for_rig(rig))
    out: list[tuple[TrainingFrame, float] | None] = []
    for fr in frames:
        tracker.reset(fr.pose, fr.alpha)
        res = tracker.track(fr.image, 0.0)
        robust = res.extra.get("robust_residual")
        if not res.ok or robust is None or not np.isfinite(robust):
            out.append(None)
            continue
        out.append((TrainingFrame(fr.image, res.alpha, res.pose), float(robust)))
    return out


def build_speaker(images: Sequence[np.ndarray], landmarks: np.ndarray, found: np.ndarray,
                  scheme: LandmarkScheme, camera: Camera, rig: str = "desk",
                  enrol: EnrolOptions | None = None, options: BuildOptions | None = None,
                  name: str = "speaker",
                  progress: Callable[[str], None] | None = None,
                  readings: np.ndarray | None = None, reader: str = "v1",
                  times: np.ndarray | None = None,
                  reader_keep_roi: float | None = None) -> Speaker:
    """The speaker enrolled from ``images`` (F BGR uint8 frames) and their ``landmarks``
    (F, L, 3) (``found`` (F,) False where the finder saw no face). The returned speaker's
    ``report`` lists what was measured, rejected and assumed.

    readings : (F, >=468, 2+) the live reader's landmarks on the same frames (NaN where it
        found none): learns the observation model, the evidence weights and the motion noise
        of fused live tracking (step 6). reader : its network's name. times : (F,) s, when
        each frame was taken (for the motion noise; default: 25 frames a second).
        reader_keep_roi : the crop the readings were made with (``FusionPolicy.
        reader_keep_roi``), recorded in ``report["reader"]["keep_roi"]`` (None: not known,
        not recorded)."""
    opts = options or BuildOptions()
    say = progress or (lambda _msg: None)
    enrol = enrol or EnrolOptions(fixed_pose=(rig == "head"))
    flow = default_for(rig) if opts.flow is None else opts.flow
    # the face's shape as each network reads it, for a session to tell whether the face it
    # tracks is this one (core/faces/identity.py): on the networks' own points, as live;
    # a head-mounted camera sees no eyes, brows or forehead to tell a face by
    identity = _signatures(landmarks, found, readings, reader) if rig == "desk" else {}
    if flow:
        say("refining the landmarks' pixels by optical flow")
        landmarks = refine_pixels(images, landmarks, found, scheme.points)
    geo = enrol_geometry(landmarks, found, scheme, camera, enrol, name)
    model = geo.model
    rejected = dict(geo.rejected)
    states: list[TrainingFrame] = []
    kept: list[int] = []
    for j, f in enumerate(geo.frames):
        uv = np.asarray(landmarks[f][scheme.points, :2], np.float64)
        pose = fit_pose(model.shape(geo.alpha[j]), uv, camera)
        if pose is None:
            rejected[int(f)] = "head pose could not be solved from the landmarks"
            continue
        states.append(TrainingFrame(images[f], geo.alpha[j], pose))
        kept.append(j)
    if len(states) < 2 * (model.n_params + 1):
        raise InputError(f"only {len(states)} usable frames: enrol from a longer clip "
                         "(20-60 s of reading aloud)")
    alpha = geo.alpha[kept]
    order = training_order(alpha, opts.coverage_seed)
    n_train = min(opts.train_frames, max(2 * (model.n_params + 1), int(0.6 * len(order))))
    train = [states[i] for i in order[:n_train]]
    held = [states[i] for i in order[n_train:n_train + opts.stats_frames]]
    say(f"training {opts.kind} on {len(train)} frames at their landmark states")
    rig_opts = appearance_options(rig, opts.kind)
    app = train_appearance(model, camera, train, opts.kind, sigma=opts.sigma, **rig_opts)
    for r in range(opts.refine):
        fitted = fit_states(model, app, camera, rig, train)
        good = [f for f, _ in (x for x in fitted if x is not None)]
        say(f"refinement {r + 1}: {len(good)} of {len(train)} frames fitted; retraining")
        if len(good) >= 2 * (model.n_params + 1):
            train = good
            app = train_appearance(model, camera, train, opts.kind, sigma=opts.sigma,
                                   **rig_opts)
    check = held or train
    resid = [x[1] for x in fit_states(model, app, camera, rig, check) if x is not None]
    if not resid:
        raise InputError("the trained appearance does not fit any held-out enrolment frame: "
                         "is the same face in the whole clip?")
    ap, wd = lip_measures(model, geo.alpha)
    coverage = {"aperture_mm": [float(np.percentile(ap, 2)), float(np.percentile(ap, 98))],
                "width_mm": [float(np.percentile(wd, 2)), float(np.percentile(wd, 98))],
                **turn_coverage(app, train)}
    held_resid = np.array(resid)
    stats = ResidualStats(float(np.median(held_resid)), float(np.percentile(held_resid, 95)),
                          float(np.percentile(held_resid, 99)), len(held_resid))
    report = {
        "frames": int(len(images)),
        "frames_used": int(len(states)),
        "training_frames": len(train),
        "held_out_frames": len(check) if held else 0,
        "held_out_fitted": len(resid),
        "rejected": {str(k): v for k, v in sorted(rejected.items())},
        "variance_pct": dict(zip(geo.table.names, map(float, geo.table.variance_pct),
                                 strict=True)),
        "scale": geo.scale_source,
        "depth": enrol.depth,
        "pixels": "landmarks refined by optical flow" if flow else "landmarks",
        "coverage": coverage,
        "unobserved": ["lar1"],
        "appearance": {"kind": app.kind, "sample_points": int(app.n_samples)},
    }
    points = motion = finder_points = None
    if readings is not None:
        say("learning how the live landmark reader sees this face, and the motion model")
        idx = np.asarray(geo.frames)[kept]
        at = np.arange(len(images)) / 25.0 if times is None else np.asarray(times, float)
        points, motion = fusion_model(model, camera, scheme, states, idx,
                                      np.asarray(readings), reader, at)
        if reader != FINDER_NETWORK:  # the finding landmarks, read on every frame already:
            # offline track's second reader (docs/TRACKING.md, "Offline")
            finder_points, _ = fusion_model(model, camera, scheme, states, idx,
                                            np.asarray(landmarks), FINDER_NETWORK, at)
        reg = points.regression
        report["reader"] = {
            "network": reader, "shared_error_modes": int(len(points.modes)),
            "sigma_mm_median": round(float(np.median(points.sigma_mm)), 3),
            # the articulation read straight off a reading: its ridge and the error s.d. its
            # cross-validation measured per parameter (training s.d.; None: not moved)
            "regression": None if reg is None else {
                "ridge": reg.ridge,
                "error_sd": [round(float(1 / np.sqrt(d)), 3) if d > 0 else None
                             for d in np.diag(reg.information)]},
            # the crop its readings were made with (FusionPolicy.reader_keep_roi)
            **({} if reader_keep_roi is None else {"keep_roi": float(reader_keep_roi)})}
        if finder_points is not None:  # offline track's second reader
            report["second_reader"] = {
                "network": finder_points.network,
                "shared_error_modes": int(len(finder_points.modes)),
                "sigma_mm_median": round(float(np.median(finder_points.sigma_mm)), 3)}
    upper = None
    if readings is not None and rig == "desk":
        say("calibrating the eyes and brows (open eye, closed eye, neutral brows, gaze)")
        upper = upper_reference(images, np.asarray(readings))
        report["upper"] = upper_report(upper)
    report["identity"] = {net: sig.frames for net, sig in sorted(identity.items())}
    return Speaker(model, app, camera, stats, rig, scheme.name, name, report, points, motion,
                   upper, finder_points, identity)


def turn_coverage(app: AppearanceModel, train: Sequence[TrainingFrame]) -> dict:
    """The head rotations the appearance was trained on: ``rotation_ref`` (axis-angle, rad),
    the reference they are taken from (the appearance's own, else the frames' mean), and
    ``rotation_deg`` (3, 2), the 2nd-98th percentiles of each component of the training
    frames' rotation away from it (camera axes: x pitch, y yaw, z roll), as the lips'
    aperture and width ranges. Beyond them the appearance extrapolates: a head bowed further
    than the enrolment ever was mispredicts the lips and chin with nothing in front of them
    (:meth:`~articast.core.faces.live.LiveTracker._unfamiliar`)."""
    ref = (np.asarray(app.rotation_ref, np.float64) if app.rotation_ref is not None
           else mean_rotation([f.pose.matrix for f in train]))
    ref_m = rotation_matrix(ref)
    turns = np.degrees(np.stack([axis_angle(f.pose.matrix @ ref_m.T) for f in train]))
    return {"rotation_ref": [float(x) for x in ref],
            "rotation_deg": [[float(np.percentile(turns[:, i], 2)),
                              float(np.percentile(turns[:, i], 98))] for i in range(3)]}


def _signatures(landmarks: np.ndarray, found: np.ndarray, readings: np.ndarray | None,
                reader: str) -> dict[str, FaceSignature]:
    """The enrolment's identity signatures: the finding landmarks' (frames where a face was
    found) and the live reader's (frames it read), where each has enough frames and
    depth."""
    out: dict[str, FaceSignature] = {}
    lm = np.asarray(landmarks)
    sets = [(FINDER_NETWORK, lm[np.asarray(found, bool)])]
    if readings is not None:
        sets.append((reader, np.asarray(readings)))
    for net, marks in sets:
        if marks.ndim != 3 or marks.shape[1] < 468 or marks.shape[2] != 3:
            continue
        sig = signature(marks, net)
        if sig is not None:
            out[net] = sig
    return out


def upper_reference(images: Sequence[np.ndarray], readings: np.ndarray) -> UpperReference | None:
    """Step 7: the speaker's open-eye, closed-eye, neutral-brow and gaze references, and the
    photometric eye measure's line to the reader's closure, from the reader's landmarks of
    the enrolment frames (:func:`~articast.core.faces.upper.calibrate`)."""
    import cv2

    canon = canonical_face()
    greys = [img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img in images]
    seen = [lm if np.all(np.isfinite(lm[:468, :2])) else None for lm in readings]
    ms: list[Measures | None] = [None if lm is None else measure_upper(g, lm, canon)
                                 for g, lm in zip(greys, seen, strict=True)]
    first = calibrate(ms)
    if first is None:
        return None
    # the measures again at the speaker's open eye, iris radius and open-eye grey levels (as
    # live: a closed eye's lid gap needs the open eye's levels)
    ms = [None if m is None or lm is None else measure_upper(
        g, lm, canon, first.open_mm, first.iris_radius_mm,
        (first.eye_levels(0), first.eye_levels(1)))
        for m, g, lm in zip(ms, greys, seen, strict=True)]
    ref = calibrate(ms)
    if ref is None:
        return None
    return replace(ref, change_limit=change_limits(greys, seen, ms, ref))


def upper_report(ref: UpperReference | None) -> dict:
    """What ``enroll`` reports of the upper face (and warns about)."""
    if ref is None:
        return {"eyes_visible": False}
    return {"eyes_visible": True, "frames": ref.frames, "blinks": ref.blinks,
            "open_eye_mm": [round(v, 2) for v in ref.open_mm],
            "closed_eye_mm": [round(v, 2) for v in ref.closed_mm],
            "neutral_brows_mm": [round(v, 2) for v in ref.brows_mm],
            "iris_radius_mm": [round(v, 2) for v in ref.iris_radius_mm],
            "brow_band_mm": [round(v, 2) for v in ref.brow_band_mm],
            "photometric_kind": list(ref.photo_kind),
            "photometric_r": [round(v, 3) for v in ref.photo_r],
            # (left, right) eyes no photometric measure follows: read when they change
            "watched": [bool(ref.change_limit[i] > 0 and abs(ref.photo_r[i]) < PHOTO_MIN_R)
                        for i in range(2)]}


def fusion_model(model: FaceModel, camera: Camera, scheme: LandmarkScheme,
                 states: list[TrainingFrame], frames: np.ndarray, readings: np.ndarray,
                 reader: str, times: np.ndarray) -> tuple[PointModel, MotionNoise]:
    """Step 6 of the module docstring. states : the enrolment's frames at their landmark
    states; frames : their indices into ``readings`` (F, >=468, 2+) and ``times`` (F,) s."""
    uv = readings[frames][:, scheme.points, :2]
    pm = learn_point_model(model, camera, [(s.alpha, s.pose) for s in states], uv,
                           np.arange(len(scheme.points)), scheme.points, reader)
    reg = learn_reading_regression(pm.mean, camera, [s.pose for s in states],
                                   np.array([s.alpha for s in states]), uv,
                                   np.asarray(times)[np.asarray(frames)])
    pm = replace(pm, regression=reg)
    order = np.argsort(frames)
    rot = np.array([s.pose.rotation for s in states])[order]
    trans = np.array([s.pose.translation for s in states])[order]
    alpha = np.array([s.alpha for s in states])[order]
    motion = process_noise(alpha, rot, trans, np.asarray(times)[np.asarray(frames)[order]])
    return pm, motion

"""The upper face against ground truth (issue 19; docs/UPPER_FACE.md).

The built-in speaker on the desk rig blinks, looks and raises its brows
(:mod:`articast.core.synthetic.upper`). It is enrolled as ``articast enroll`` enrols a clip
(the finding landmarks on every frame, the live reader's landmarks, ``build_speaker`` with the
upper face's references) on one sentence with its own blinks, then tracked live
(:class:`~articast.core.faces.live.LiveTracker`, the product's policy) on another, and scored:

- ``blink_f1`` (``blink_precision``, ``blink_recall``): events are runs of frames whose mean
  closure (left, right) is above 0.5, runs apart by a gap of at most ``REOPEN_S`` one event
  (:func:`blink_events`, the count of ``benchmarks/blinks.py`` too), in the truth and in the
  tracked; a tracked and a true event match when they overlap, one to one
  (:func:`match_events`); ``onset_within_1``: the
  fraction of matched blinks whose tracked onset is within one frame of the true one
  (``onset_frames``: each difference);
- ``closure_r``: correlation of each eye's tracked closure with the true one;
- ``gaze_median_error_deg``: median over open-eyed frames (true closure < 0.2) of the distance
  between the tracked and the true (yaw, pitch); ``gaze_yaw_r``, ``gaze_pitch_r``;
- ``brow_r``: correlation of each side's tracked raise (inner and outer mean) with the truth;
- ``lips``: the lip aperture's correlation with the truth and mean absolute error (mm) on the
  same frames (the lips' figures, to compare with the same sentence without the upper face);
- ``upper_ms``: the upper face's own time per frame inside the live run (``clock``), and
  ``frame_ms`` the whole frame's.

No files here; ``clock`` (e.g. time.perf_counter) is passed in for the times.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from articast.core.errors import InputError
from articast.core.synthetic.upper import UpperTruth


@dataclass(frozen=True)
class UpperEvalConfig:
    """seed : speaker; seconds, fps : the test sentence; enrol_frames, enrol_fps : the
    enrolment sentence (all its frames analysed)."""

    seed: int = 0
    seconds: float = 60.0
    fps: float = 30.0
    enrol_frames: int = 300
    enrol_fps: float = 12.0


def events(flags: np.ndarray, merge: int = 0) -> list[tuple[int, int]]:
    """(start, end exclusive) runs of True; runs apart by <= ``merge`` frames are merged."""
    f = np.concatenate([[False], np.asarray(flags, bool), [False]])
    d = np.flatnonzero(np.diff(f.astype(int)))
    out: list[tuple[int, int]] = []
    for s, e in zip(d[::2].tolist(), d[1::2].tolist(), strict=True):
        if out and s - out[-1][1] <= merge:
            out[-1] = (out[-1][0], e)
        else:
            out.append((s, e))
    return out


BLINK_CLOSURE = 0.5
"""A blink frame: the mean closure of both eyes above this (issue 19)."""
REOPEN_S = 0.05
"""Runs of blink frames apart by a gap this short (or shorter) are one event: an eye does not
reopen and close again within it (a blink's reopening alone takes ~100 ms or more), so the gap
is the measurement's. At 20-39 fps a gap of one frame, at 60 fps three."""


def blink_events(flags: np.ndarray, fps: float) -> list[tuple[int, int]]:
    """(start, end exclusive) of each blink: runs of blink frames (``flags``, e.g. the mean
    closure > :data:`BLINK_CLOSURE`), those apart by at most :data:`REOPEN_S` merged."""
    if not fps > 0:
        raise InputError(f"blink events need a frame rate > 0, got {fps}")
    return events(flags, merge=int(math.floor(REOPEN_S * fps + 1e-9)))


def match_events(ours: list[tuple[int, int]], ref: list[tuple[int, int]], tol: int = 0,
                 one_to_one: bool = True) -> tuple[float | None, float | None, list[int]]:
    """Precision, recall and the onsets (ours - ref, frames) of two event lists, an event of
    one matching an event of the other that it overlaps (within ``tol`` frames).

    one_to_one: each reference event takes the first of ours that overlaps it and is not
    taken yet, so a blink read as several short events (a closure flickering about the
    threshold) matches once and the rest are false events; against a truth that does not
    flicker (the synthetic speaker) this is the honest count. Else overlap alone (the usual
    count against another detector whose own events fragment too: an event of ours covering
    three pieces of the reference's is one true event, and each piece is found)."""
    def hit(a: tuple[int, int], b: tuple[int, int]) -> bool:
        return a[0] < b[1] + tol and b[0] < a[1] + tol

    onsets: list[int] = []
    if not one_to_one:
        hits = [a for a in ours if any(hit(a, b) for b in ref)]
        for b in ref:
            a = next((a for a in ours if hit(a, b)), None)
            if a is not None:
                onsets.append(a[0] - b[0])
        return (len(hits) / len(ours) if ours else None,
                len(onsets) / len(ref) if ref else None, onsets)
    taken: set[int] = set()
    for b in ref:
        j = next((j for j, a in enumerate(ours) if j not in taken and hit(a, b)), None)
        if j is not None:
            taken.add(j)
            onsets.append(ours[j][0] - b[0])
    prec = len(taken) / len(ours) if ours else None
    rec = len(onsets) / len(ref) if ref else None
    return prec, rec, onsets


def _corr(a: np.ndarray, b: np.ndarray) -> float | None:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None
    return round(float(np.corrcoef(a[ok], b[ok])[0, 1]), 4)


def score_upper(uppers: list[Any], truth: UpperTruth, fps: float) -> dict[str, Any]:
    """The module docstring's figures of tracked upper faces (F UpperFace or None) against
    ``truth`` (F frames at ``fps``)."""
    n = len(uppers)
    cl = np.full((n, 2), np.nan)
    gz = np.full((n, 2), np.nan)
    br = np.full((n, 2), np.nan)
    for i, u in enumerate(uppers):
        if u is not None and u.eyes_ok:
            cl[i] = (u.closure_left, u.closure_right)
            if u.gaze_yaw_deg is not None:
                gz[i] = (u.gaze_yaw_deg, u.gaze_pitch_deg)
        if u is not None and u.brows_ok:
            br[i] = ((u.raise_inner_left_mm + u.raise_outer_left_mm) / 2,
                     (u.raise_inner_right_mm + u.raise_outer_right_mm) / 2)
    true_ev = blink_events(truth.closure.mean(axis=1) > BLINK_CLOSURE, fps)
    ours = blink_events(np.nan_to_num(cl.mean(axis=1)) > BLINK_CLOSURE, fps)

    prec, rec, onsets = match_events(ours, true_ev)
    f1 = 2 * prec * rec / (prec + rec) if prec and rec else 0.0
    open_ = truth.closure.mean(axis=1) < 0.2
    err = np.hypot(*(gz - truth.gaze).T)
    err = err[open_ & np.isfinite(err)]
    return {
        "frames": n, "eyes_ok": round(float(np.isfinite(cl[:, 0]).mean()), 4),
        "true_blinks": len(true_ev), "tracked_blinks": len(ours),
        "blink_precision": None if prec is None else round(prec, 4),
        "blink_recall": None if rec is None else round(rec, 4), "blink_f1": round(f1, 4),
        "onset_frames": [int(o) for o in onsets],
        "onset_within_1": round(float(np.mean(np.abs(onsets) <= 1)), 4) if onsets else None,
        "closure_r": [_corr(cl[:, k], truth.closure[:, k]) for k in range(2)],
        "gaze_median_error_deg": round(float(np.median(err)), 3) if err.size else None,
        "gaze_yaw_r": _corr(gz[:, 0], truth.gaze[:, 0]),
        "gaze_pitch_r": _corr(gz[:, 1], truth.gaze[:, 1]),
        "brow_r": [_corr(br[:, k], truth.brows[:, k]) for k in range(2)],
    }


def evaluate_upper(cfg: UpperEvalConfig = UpperEvalConfig(),
                   clock: Callable[[], float] | None = None,
                   progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Render, enrol, track and score (module docstring)."""
    from articast.core.faces.build import build_speaker
    from articast.core.faces.enrol import EnrolOptions
    from articast.core.faces.finder import FaceFinder, read_every_frame
    from articast.core.faces.live import FusionPolicy, LiveTracker, reader_finder
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.model.build import invert
    from articast.core.outputs.lips import lip_measures
    from articast.core.synthetic import RenderOptions, default_speaker, make_sequence
    from articast.core.synthetic.upper import upper_sequence

    say = progress or (lambda _m: None)
    sp = default_speaker(cfg.seed)
    true_model = sp.model()
    say(f"upper face: rendering the enrolment sentence ({cfg.enrol_frames} frames)")
    enrol = make_sequence(cfg.seed * 100 + 11, cfg.enrol_frames, cfg.enrol_fps, "desk",
                          geometry=sp.geometry)
    enrol_up = upper_sequence(cfg.seed * 100 + 11, cfg.enrol_frames, cfg.enrol_fps)
    imgs = [sp.render(enrol.controls[i], enrol.pose(i), enrol.camera,
                      RenderOptions(seed=10_000 + i), enrol_up.frame(i))
            for i in range(enrol.n_frames)]
    say("upper face: enrolling from the landmarks")
    finder = FaceFinder.load(threads=1)
    faces, prev = [], None
    for im in imgs:
        face = finder.track(im, prev) if prev is not None else None
        prev = face = face or finder.find(im)
        faces.append(face)
    found = np.array([f is not None for f in faces])
    marks = np.array([f.landmarks if f is not None else np.full((478, 3), np.nan)
                      for f in faces])
    fu = FusionPolicy()  # the live tracker's below: its reader reads the enrolment too
    readings = read_every_frame(reader_finder(fu), imgs, faces)
    speaker = build_speaker(imgs, marks, found, mediapipe_scheme("desk"), enrol.camera, "desk",
                            EnrolOptions(), readings=readings,
                            times=np.arange(enrol.n_frames) / cfg.enrol_fps,
                            reader_keep_roi=fu.reader_keep_roi)
    n = int(round(cfg.seconds * cfg.fps))
    say(f"upper face: rendering and tracking the test sentence ({n} frames)")
    test = make_sequence(cfg.seed * 100 + 12, n, cfg.fps, "desk", geometry=sp.geometry)
    up = upper_sequence(cfg.seed * 100 + 12, n, cfg.fps)
    live = LiveTracker(speaker, finder, mediapipe_scheme("desk"), clock=clock)
    results, frame_s = [], 0.0
    for i in range(n):
        im = sp.render(test.controls[i], test.pose(i), test.camera,
                       RenderOptions(seed=20_000 + i), up.frame(i))
        t0 = clock() if clock else 0.0
        results.append(live.track(im, i / cfg.fps))
        frame_s += (clock() - t0) if clock else 0.0
    out = {"config": {"seed": cfg.seed, "seconds": cfg.seconds, "fps": cfg.fps},
           "enrolment": speaker.report.get("upper"),
           **score_upper([r.upper for r in results], up, cfg.fps)}
    ok = np.array([r.ok for r in results])
    ap, _ = lip_measures(speaker.model, np.array([r.alpha for r in results]))
    ap_true, _ = lip_measures(true_model, invert(true_model, test.points))
    out["lips"] = {"ok": round(float(ok.mean()), 4), "aperture_r": _corr(ap[ok], ap_true[ok]),
                   "aperture_mae_mm": round(float(np.abs(ap - ap_true)[ok].mean()), 3)}
    if clock is not None:
        out["frame_ms"] = round(frame_s * 1e3 / max(n, 1), 3)
        out["upper_ms"] = round(live.upper.spent_s * 1e3 / max(n, 1), 3)
    return out

"""articast against the free face trackers, on the same frames, one thread each, in one run.

    python tools/fetch_real_clips.py                      # once: the clips
    python tools/convert_face_models.py --with-v1         # once, in a tools venv: FaceMesh v1
    python benchmarks/setup_peers.py --openseeface-git GIT   # once: the peers' venvs, models
    python benchmarks/peers.py [--json] [--only CLIP ...] [--methods M ...] [--grid DIR]
                               [--variant V] [--offline [--single-reader]]
                               [--set FIELD=VALUE ...] [--enrol-blend W]

Each clip (every clip ``tools/fetch_real_clips.py`` fetched, and ``synthetic``) is read once and
scaled to 640 px wide (aspect kept); every method sees exactly these frames. articast enrols on
the first 60 % (at most 600 frames analysed, as ``articast enroll`` strides) and everything is
scored on the remaining 40 % (held out), where all methods run:

- ``articast``: the live path as a user's loop (``ArticastLoop``: ``FaceFinder.load`` and a
  ``LiveTracker``, then ``track`` per frame: reader, fused fit, motion model, filter, eyes and
  brows); its aperture is ``lips.aperture_mm`` over the fitted outer lip width (8.3-8.4), as in
  ``benchmarks/real_clips.py``. Frames not ok are NaN in its scores, counted in ``ok``.
  ``--offline``: its results smoothed with the frames after, as ``articast track`` writes a
  recorded clip (``core/faces/offline.py``: smoothed, and averaged with the second
  reader's tracker, FaceLandmarker v2 on every frame; ``--single-reader``: FaceMesh v1's
  tracker alone); its CPU figures stay the live loop's, the smoothing's own CPU per frame
  is ``offline_smoothing_cpu_ms`` and the second tracker's ``offline_second_reader_cpu_ms``.
- ``facemesh_v1``: the loop a user would write with MediaPipe FaceMesh v1 on onnxruntime: the
  bundled BlazeFace detector on the first frame and when lost, then the 468-point model (192 px)
  on a crop re-made from the previous frame's landmarks (``FinderPolicy(refine=0,
  keep_roi=0)``). Its mean ms per frame is the **speed baseline** of every ratio.
- ``facelandmarker_v2``: the bundled ``FaceFinder`` (478 points, its default policy) in the
  same loop (``FinderLoop``).
- ``openseeface``, ``mediapipe`` (its own FaceMesh solution), ``dlib`` (68 points): each in its
  own venv (``benchmarks/setup_peers.py``), run as a subprocess (``benchmarks/peer_worker.py``)
  that receives the frames through a pipe and times its own per-frame work *inside* the
  worker: process start-up, model loading and the pipe are not in its time. ``faceapi``
  (face-api.js's 68-point network in its SSD detector's box, WebAssembly, one thread) the
  same way in Node.js (``benchmarks/peer_worker_faceapi.cjs``). A peer that is not set up is
  skipped with its reason.

``--clips DIR`` takes any folder of videos as it is (every video file, named by its stem; a
``clips.json`` where ``tools/fetch_real_clips.py`` wrote one); the default is the team's
``../shared/clips`` beside the repository. ``--speakers DIR`` keeps each clip's enrolment and
reuses it; ``--others DIR`` (a ``--series`` run's folder) reads the methods that ``--methods``
leaves out from it instead of running them: articast's policies scored against the same peers.

Scores per clip and method (held-out frames):

- ``judge_r`` (issue 38): correlation with the **independent judge**, one vote per model
  family outside FaceMesh's (articast reads with that family: FaceMesh v1, mediapipe,
  FaceLandmarker v2) and outside the method's own: for articast and every FaceMesh-family method
  the same series (the median of OpenSeeFace's, dlib's and face-api.js's, each z-scored);
  ``articast_vs_reader``: articast's r gap to its own reader (the FaceMesh v1 loop) and to the
  best FaceMesh-family peer on that judge, with paired block-bootstrap intervals, its jitter gap
  to the reader's, and the lag of its frame-to-frame changes behind the reader's
  (``benchmarks/corpus_summary.py`` tabulates them over the corpus, by half of the people);

- ``consensus_r`` (and ``consensus_n`` frames): correlation of the method's lip aperture (inner
  gap over outer width: MediaPipe 13-14 over 61-291, iBUG 62-66 over 48-54, OpenSeeFace 60-64
  over 58-62; the gap projected on the normal of the corner line) with the per-frame median of
  the *other* methods' (the method left out; frames with fewer than 2 others dropped);
  ``pairwise_r``: every pair's correlation;
- ``jitter``: RMS of the aperture ratio about its linear trend inside still windows, % of the
  outer width; the windows are the 10 % of 0.4 s windows whose mouth image changes least, the
  mouth placed by the per-frame median of the lip boxes of every method but articast
  (``box_motion``, ``window_boxes``: its variants are scored on the same windows);
- ``lag``: the shift (frames, within +-5) of the peak correlation with the leave-one-out
  consensus; positive: the method is late. +-5 means no peak inside the range (a slow drift
  between the two series makes the correlation climb with the shift), hence also
  ``lag_velocity_frames``, the same on the frame-to-frame changes (blind to slow drifts);
- ``ms``: mean wall ms per frame of the method's whole loop (detector, landmarks, fit), one
  thread (onnxruntime sessions with one intra-op thread, ``cv2.setNumThreads(1)`` here and in
  the workers; mediapipe's graph runs its own calculators); ``cpu_ms``: its process CPU time
  per frame (less sensitive to other jobs on the machine); ``x_v1``: ms over the FaceMesh v1
  loop's in the same run. Timings exclude the construction (a user's loop builds its
  sessions once): for articast and the in-process landmark loops it is timed apart,
  ``build_ms`` / ``build_cpu_ms`` (ONNX sessions loaded, articast's ``LiveTracker`` made);
  for the workers, process start-up, model loading and the pipe are not timed (measured
  inside the worker). The first frame (articast's start: detector, finding landmarks, reader;
  the loop's detector) is a frame's work and is timed;
- ``interleaved`` (articast, when the FaceMesh v1 loop runs too; ``--cpu-repeats`` passes,
  default 3, 0 for none): the CPU figure robust to the machine's load drifting. After the
  full run, both loops are built afresh and run again on the same frames, taking turns every
  ``--cpu-chunk`` frames (default 25; who goes first alternates), each keeping its state
  across its turns; per pass, each one's mean CPU (and wall) ms per frame. ``cpu_x_v1`` and
  ``x_v1`` give the pass-by-pass ratios' median, min, max; the per-pass figures and both
  constructions are listed. A load change during a pass then falls on both alike, within
  a turn of ~0.1-0.3 s. Accuracy is scored on the full run alone. ``interleaved_lips``:
  the same for articast's lips alone, a third loop in the same passes (the speaker's upper
  face references left out: no eyes or brows measured, no frame read for the eyes), issue
  18's figure, the upper face having its own budget (issue 19: +1 ms a frame,
  ``benchmarks/blinks.py``);
- ``synthetic`` only: ``truth_r``, the correlation with the true aperture ratio (the truth's
  parameters through the true model: inner midpoints 2.2-2.3 over outer corners 8.3-8.4), and
  for articast the mean absolute error of its aperture and width in mm; ``consensus_vs_truth``:
  whether the consensus ranks the methods as the truth does (Spearman's rank correlation of
  ``consensus_r`` with ``truth_r`` over the methods, and both rankings): the one place where
  the real clips' yardstick can itself be checked.

``--json`` prints one object per clip with the machine's load (``os.getloadavg``) at start and
end; otherwise a markdown table. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import CLIP_CACHE, clip_paths  # noqa: E402
from face_landmarks_clips import box_motion, jitter, still_windows, window_frames  # noqa: E402
from real_clips import enrol_speaker, outer_width_mm  # noqa: E402

from articast.core.faces.build import analysed_frames  # noqa: E402
from articast.core.faces.finder import FaceFinder, FinderPolicy, models_dir  # noqa: E402
from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker  # noqa: E402
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.tracking import kernels  # noqa: E402
from articast.core.tracking.filters import OneEuroPolicy  # noqa: E402
from articast.service.overlay import fit_tile, lip_contours  # noqa: E402

PEER_CACHE = Path.home() / ".cache/articast/peers"
WIDTH = 640
ENROL_FRACTION = 0.6
MAX_ENROL_FRAMES = 600
METHODS = ("articast", "facemesh_v1", "facelandmarker_v2", "openseeface", "mediapipe", "dlib",
           "faceapi")
WORKERS = ("openseeface", "mediapipe", "dlib", "faceapi")
BASELINE = "facemesh_v1"
VARIANTS = {  # --variant: the design's ablation (docs/TRACKING.md, "Fused live tracking")
    "fused": None,  # the default LivePolicy
    # the default before issue 38: the reader every third frame, its cadence cancelled, the
    # filtered fit streamed, the eyes measured on every reading
    "cadence_3": LivePolicy(fusion=FusionPolicy(read_every=3, cadence=0.1, reader_gap=None,
                                                eyes_every=1)),
    "appearance": LivePolicy(fusion=None),  # the appearance fit alone, landmarks to check
    "landmarks": LivePolicy(fusion=FusionPolicy(appearance_weight=0.0)),  # through the model
    "no_kalman": LivePolicy(fusion=FusionPolicy(kalman=False)),
    "no_one_euro": LivePolicy(smoothing=None),
    "read_every_1": LivePolicy(fusion=FusionPolicy(read_every=1)),
    "read_every_2": LivePolicy(fusion=FusionPolicy(read_every=2)),
    "fixed_weights": LivePolicy(fusion=FusionPolicy(adapt=None)),
    "fixed_weights_read_every_2": LivePolicy(fusion=FusionPolicy(adapt=None, read_every=2)),
    "no_reread": LivePolicy(fusion=FusionPolicy(reread=None)),
    "iterations_2": LivePolicy(fusion=FusionPolicy(max_iterations=2)),
    "points_1": LivePolicy(fusion=FusionPolicy(points_weight=1.0)),
    "points_0.1": LivePolicy(fusion=FusionPolicy(points_weight=0.1)),
    "no_speaker_prior": LivePolicy(fusion=FusionPolicy(speaker_prior=None)),
    "no_cadence": LivePolicy(fusion=FusionPolicy(cadence=None)),
    "no_regression": LivePolicy(fusion=FusionPolicy(regression=False)),
    # (re)starts as before issue 18's start change: the finding landmarks, the detector after
    # every diverged fit
    "finder_start": LivePolicy(fusion=FusionPolicy(start="finder", resume=False)),
    "finder_start_resume": LivePolicy(fusion=FusionPolicy(start="finder")),
    "no_resume": LivePolicy(fusion=FusionPolicy(resume=False)),
    "no_recover": LivePolicy(fusion=FusionPolicy(recover=False)),
    # FaceLandmarker v2 as the live reader, its observation model learned at enrolment from
    # the finding landmarks' own readings (~3.4x a v1 call: not within issue 18's budget; a
    # bound on what a better reader is worth through the speaker's model)
    "reader_v2": LivePolicy(fusion=FusionPolicy(reader="v2")),
    "reader_v2_every_frame": LivePolicy(fusion=FusionPolicy(reader="v2", read_every=1,
                                                            cadence=None)),
    # issue 38: the reader read on every frame, its own lip gap in the streamed opening
    "every_frame": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None)),
    "gap": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=1.0)),
    "gap_eyes2": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=1.0,
                                                eyes_every=2)),
    "gap_0.5": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=0.5,
                                              eyes_every=2)),
    "gap_0.65": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=0.65,
                                               eyes_every=2)),
    "gap_0.5_e3": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=0.5,
                                                 eyes_every=3)),
    "gap_0.35": LivePolicy(fusion=FusionPolicy(read_every=1, cadence=None, reader_gap=0.35,
                                               eyes_every=2)),
}
ARTICAST_POLICY: LivePolicy | None = None  # set from --variant (and --set)
SPEAKERS: Path | None = None  # --speakers: the enrolments kept and reused
OTHERS: Path | None = None  # --others: the methods not run, read from a --series run
ENROL_BLEND = 0.0  # --enrol-blend: v1's share of the landmarks the speaker's model is built from
OFFLINE = False  # --offline: articast's results smoothed with the frames after (track's)
SINGLE_READER = False  # --single-reader: offline without the second reader's tracker
READERS = 1  # --readers: live, 2 streams the mean of a v1 and a v2 reader's trackers
SECOND_EVERY = 1  # --second-every: with --readers 2, the second reads every n-th frame
OFFLINE_ONE_EURO = False  # --offline-one-euro: offline with the One Euro filter forward and back
OFFLINE_GAP: float | None = None  # --offline-gap: the readers' share of the offline opening
MAX_LAG = 5
MIN_FRAMES = 10  # fewer frames in common: no correlation reported
#: per scheme: inner upper and lower midpoints, outer corners, outer upper and lower midpoints
SCHEMES = {"mediapipe": (13, 14, 61, 291, 0, 17), "ibug68": (62, 66, 48, 54, 51, 57),
           "openseeface": (60, 64, 58, 62, 50, 55)}


def log(msg: str) -> None:
    print(f"[peers {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- scoring
def aperture_ratio(points: np.ndarray, scheme: str) -> np.ndarray:
    """(F,) inner-lip gap over outer-lip width from (F, K, 2) image points (NaN where none):
    the gap between the inner midpoints projected on the normal of the corner line."""
    up, low, right, left = (points[:, i] for i in SCHEMES[scheme][:4])
    across = left - right
    width = np.linalg.norm(across, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        down = np.stack([-across[:, 1], across[:, 0]], -1) / width[:, None]
        return np.sum((low - up) * down, -1) / width


def lip_box(points: np.ndarray, scheme: str) -> np.ndarray:
    """(F, 4) x0, y0, x1, y1 of the outer lip's corners and midpoints (NaN where none)."""
    pts = points[:, list(SCHEMES[scheme][2:])]
    return np.concatenate([pts.min(1), pts.max(1)], -1)


def pearson(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """Correlation over the frames where both are finite, and their number (NaN if fewer
    than ``MIN_FRAMES``)."""
    both = np.isfinite(a) & np.isfinite(b)
    n = int(both.sum())
    if n < MIN_FRAMES or np.std(a[both]) == 0 or np.std(b[both]) == 0:
        return float("nan"), n
    return float(np.corrcoef(a[both], b[both])[0, 1]), n


def consensus(series: dict[str, np.ndarray], leave_out: str | None = None,
              min_others: int = 2) -> np.ndarray:
    """Per-frame median of the series other than ``leave_out``; NaN where fewer than
    ``min_others`` of them are finite."""
    others = np.array([v for k, v in series.items() if k != leave_out])
    if len(others) == 0:  # the method alone (the others skipped or not asked for)
        return np.full(len(next(iter(series.values()))), np.nan)
    count = np.isfinite(others).sum(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(others, 0)
    return np.where(count >= min_others, med, np.nan)


def lag(x: np.ndarray, ref: np.ndarray, max_lag: int = MAX_LAG) -> int | None:
    """The shift L in [-max_lag, max_lag] maximising corr(x[t], ref[t - L]): positive when
    ``x`` follows ``ref`` late by L frames. None if no shift has a correlation."""
    best, best_r = None, -np.inf
    n = len(x)
    for s in range(-max_lag, max_lag + 1):
        a = x[max(s, 0):n + min(s, 0)]
        b = ref[max(-s, 0):n - max(s, 0)]
        r, _ = pearson(a, b)
        if np.isfinite(r) and r > best_r:
            best, best_r = s, r
    return best


#: the model family of each method: one vote each in the judge. FaceMesh v1, mediapipe's
#: FaceMesh and FaceLandmarker v2 are one family (v1 and mediapipe agree at r ~0.998), and
#: articast reads with it.
FAMILIES = {"articast": "facemesh", "facemesh_v1": "facemesh", "facelandmarker_v2": "facemesh",
            "mediapipe": "facemesh", "openseeface": "openseeface", "dlib": "dlib",
            "faceapi": "faceapi"}
READER_FAMILY = "facemesh"


def judge(aps: dict[str, np.ndarray], method: str) -> np.ndarray:
    """The independent judge of ``method``: per frame, the median of one vote per model family
    outside articast's reader's family (FaceMesh) and outside ``method``'s own, each family's
    vote the median of its members' series, z-scored over the frames it has (the schemes'
    ratios differ in scale and offset: unscaled, the median of three would mostly be the
    family whose ratio sits in the middle, and a mean would weigh each family by its spread);
    NaN where no family has the frame. articast and every FaceMesh-family method are thus
    scored against the same series (OpenSeeFace's, dlib's and face-api.js's)."""
    own = FAMILIES.get(method, method)
    votes = []
    for fam in dict.fromkeys(FAMILIES.get(k, k) for k in aps):
        if fam in (READER_FAMILY, own):
            continue
        members = np.array([v for k, v in aps.items() if FAMILIES.get(k, k) == fam])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            vote = np.nanmedian(members, 0)
        if np.isfinite(vote).sum() > 1:
            vote = (vote - np.nanmean(vote)) / max(float(np.nanstd(vote)), 1e-12)
        votes.append(vote)
    n = len(next(iter(aps.values())))
    if not votes:
        return np.full(n, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.array(votes), 0)


def score(aps: dict[str, np.ndarray], windows: list[slice]) -> dict[str, dict]:
    """Every method's aperture series: r against the leave-one-out consensus and against the
    independent judge (:func:`judge`), jitter, and lag (against the consensus; the
    frame-to-frame changes' lag against the judge too)."""
    out = {}
    for name, ap in aps.items():
        cons = consensus(aps, leave_out=name)
        r, n = pearson(ap, cons)
        ref = judge(aps, name)
        jr, jn = pearson(ap, ref)
        out[name] = {"consensus_r": _round(r, 4), "consensus_n": n,
                     "judge_r": _round(jr, 4), "judge_n": jn,
                     "jitter_pct_width": _round(jitter(ap, windows), 3),
                     "lag_frames": lag(ap, cons),
                     "lag_velocity_frames": lag(np.diff(ap), np.diff(cons)),
                     "judge_lag_velocity_frames": lag(np.diff(ap), np.diff(ref))}
    return out


BOOTSTRAP = 1000  # resamples of the gap to the best peer
BLOCK_S = 1.0  # seconds per bootstrap block (the aperture is correlated over a syllable or two)


def gap_interval(x: np.ndarray, y: np.ndarray, cons_x: np.ndarray, cons_y: np.ndarray,
                 block: int, resamples: int = BOOTSTRAP, seed: int = 0
                 ) -> tuple[float, float, float] | None:
    """r(x, cons_x) - r(y, cons_y) over the clip and its 95 % interval by a paired moving-block
    bootstrap (the same blocks of ``block`` frames drawn for both): whether one method's lead
    over another is more than which frames the clip happened to hold. None when there are
    fewer than two blocks or a correlation is undefined."""
    n = len(x)
    if n < 2 * block:
        return None
    gap = pearson(x, cons_x)[0] - pearson(y, cons_y)[0]
    if not math.isfinite(gap):
        return None
    rng = np.random.default_rng(seed)
    starts = np.arange(n - block + 1)
    k = int(np.ceil(n / block))
    gaps = []
    for _ in range(resamples):
        idx = (rng.choice(starts, k)[:, None] + np.arange(block)[None]).ravel()[:n]
        g = pearson(x[idx], cons_x[idx])[0] - pearson(y[idx], cons_y[idx])[0]
        if math.isfinite(g):
            gaps.append(g)
    if len(gaps) < resamples // 2:
        return None
    lo, hi = np.percentile(gaps, [2.5, 97.5])
    return float(gap), float(lo), float(hi)


def window_gap_interval(x: np.ndarray, y: np.ndarray, windows: list[slice],
                        resamples: int = BOOTSTRAP, seed: int = 0
                        ) -> tuple[float, float, float] | None:
    """jitter(x) - jitter(y) over the still windows and its 95 % interval, the windows
    resampled (paired). None with fewer than two windows."""
    if len(windows) < 2:
        return None
    gap = jitter(x, windows) - jitter(y, windows)
    if not math.isfinite(gap):
        return None
    rng = np.random.default_rng(seed)
    gaps = [jitter(x, sample) - jitter(y, sample)
            for sample in ([windows[i] for i in rng.integers(0, len(windows), len(windows))]
                           for _ in range(resamples))]
    gaps = [g for g in gaps if math.isfinite(g)]
    if not gaps:
        return None
    lo, hi = np.percentile(gaps, [2.5, 97.5])
    return float(gap), float(lo), float(hi)


def against_best(aps: dict[str, np.ndarray], scores: dict[str, dict], windows: list[slice],
                 fps: float, method: str = "articast") -> dict:
    """``method``'s r and jitter gaps to the best other method by each score, each with its
    bootstrap interval (:func:`gap_interval`, :func:`window_gap_interval`)."""
    if method not in aps:
        return {}
    others = {k: v for k, v in scores.items() if k != method}
    out: dict = {}
    with_r = {k: v["consensus_r"] for k, v in others.items() if v["consensus_r"] is not None}
    if with_r and scores[method]["consensus_r"] is not None:
        best = max(with_r, key=lambda k: with_r[k])
        got = gap_interval(aps[method], aps[best], consensus(aps, leave_out=method),
                           consensus(aps, leave_out=best), max(2, int(round(BLOCK_S * fps))))
        if got is not None:
            out["r"] = {"peer": best, "gap": _round(got[0], 4),
                        "ci95": [_round(got[1], 4), _round(got[2], 4)]}
    with_j = {k: v["jitter_pct_width"] for k, v in others.items()
              if v["jitter_pct_width"] is not None}
    if with_j and scores[method]["jitter_pct_width"] is not None:
        best = min(with_j, key=lambda k: with_j[k])
        got = window_gap_interval(aps[method], aps[best], windows)
        if got is not None:
            out["jitter"] = {"peer": best, "gap": _round(got[0], 3),
                             "ci95": [_round(got[1], 3), _round(got[2], 3)]}
    return out


def against_reader(aps: dict[str, np.ndarray], scores: dict[str, dict], windows: list[slice],
                   fps: float, method: str = "articast", truth: np.ndarray | None = None
                   ) -> dict:
    """Issue 38's floor, under the independent judge (:func:`judge`, the same series for both
    sides): ``method``'s r gap to its own reader (the FaceMesh v1 loop) and to the best
    FaceMesh-family peer, each with its paired block-bootstrap interval; its jitter gap to the
    reader; and the lag of its frame-to-frame changes behind the reader's own. Where the
    ``truth`` is known (the rendered speaker) the gaps are taken against it instead (``judge``
    says which): there the judge itself reads the truth at r ~0.85 and its verdict on articast
    against its reader was the reverse of the truth's (docs/TRACKING.md)."""
    if method not in aps:
        return {}
    ref = judge(aps, method) if truth is None else np.asarray(truth, np.float64)
    block = max(2, int(round(BLOCK_S * fps)))
    out: dict = {"judge": "other families" if truth is None else "truth"}
    fam = {k: v["judge_r"] if truth is None else pearson(aps[k], ref)[0]
           for k, v in scores.items()
           if k != method and FAMILIES.get(k) == READER_FAMILY and v["judge_r"] is not None}
    for key, peer in (("reader", BASELINE if BASELINE in fam else None),
                      ("best_facemesh", max(fam, key=lambda k: fam[k]) if fam else None)):
        if peer is None:
            continue
        got = gap_interval(aps[method], aps[peer], ref, ref, block)
        if got is not None:
            out[f"r_vs_{key}"] = {"peer": peer, "gap": _round(got[0], 4),
                                  "ci95": [_round(got[1], 4), _round(got[2], 4)]}
    if BASELINE in aps:
        got = window_gap_interval(aps[method], aps[BASELINE], windows)
        if got is not None:
            out["jitter_vs_reader"] = {"gap": _round(got[0], 3),
                                       "ci95": [_round(got[1], 3), _round(got[2], 3)]}
        out["lag_velocity_vs_reader"] = lag(np.diff(aps[method]), np.diff(aps[BASELINE]))
    return out


def _round(x: float | None, k: int) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), k)


# ---------------------------------------------------------------------------- timing
CPU_REPEATS = 3  # --cpu-repeats: interleaved passes of articast and the v1 loop
CPU_CHUNK = 25  # --cpu-chunk: frames per turn in an interleaved pass

#: a method's loop: ``build()`` makes its sessions and state (a user's set-up, timed apart)
#: and returns ``step(i)``, its whole work on frame i (frames in order, from 0)
Builder = Callable[[], Callable[[int], Any]]
Clock = Callable[[], float]


def timed_pass(build: Builder, n: int, wall: Clock = time.perf_counter,
               cpu: Clock = time.process_time) -> dict:
    """One pass of a method over frames 0..n-1: ``outputs`` (step's per frame), ``step``,
    ``build_ms``
    and ``build_cpu_ms`` (its construction: sessions, tracker), ``ms`` and ``cpu_ms`` (mean
    per frame, construction not included)."""
    w0, c0 = wall(), cpu()
    step = build()
    w1, c1 = wall(), cpu()
    outputs = [step(i) for i in range(n)]
    w2, c2 = wall(), cpu()
    per = 1e3 / max(n, 1)
    return {"outputs": outputs, "step": step, "build_ms": (w1 - w0) * 1e3,
            "build_cpu_ms": (c1 - c0) * 1e3, "ms": (w2 - w1) * per, "cpu_ms": (c2 - c1) * per}


def chunk_schedule(n: int, chunk: int, k: int) -> list[tuple[int, int, tuple[int, ...]]]:
    """The turns of an interleaved pass of ``k`` methods over ``n`` frames: (start, stop,
    order of the methods) per chunk of ``chunk`` frames. Every method sees every frame once,
    in order; the order of the methods is reversed every other chunk, so that none always
    runs first (after another's caches, or first when the load changes)."""
    if n < 0 or chunk < 1 or k < 1:
        raise ValueError(f"need n >= 0, chunk >= 1, k >= 1; got {n}, {chunk}, {k}")
    forward = tuple(range(k))
    return [(a, min(a + chunk, n), forward if (a // chunk) % 2 == 0 else forward[::-1])
            for a in range(0, n, chunk)]


def interleaved_cost(builders: dict[str, Builder], n: int, repeats: int = CPU_REPEATS,
                     chunk: int = CPU_CHUNK, wall: Clock = time.perf_counter,
                     cpu: Clock = time.process_time) -> dict[str, dict[str, list[float]]]:
    """Each method's cost on the same ``n`` frames, in ``repeats`` passes where the methods
    take turns every ``chunk`` frames (:func:`chunk_schedule`), so that a change of the
    machine's load falls on all of them alike. Every pass builds every method afresh (timed
    apart). Per method, one value per pass: ``build_ms``, ``build_cpu_ms`` (construction)
    and ``ms``, ``cpu_ms`` (mean per frame, construction not included)."""
    names = list(builders)
    out: dict[str, dict[str, list[float]]] = {
        m: {"build_ms": [], "build_cpu_ms": [], "ms": [], "cpu_ms": []} for m in names}
    schedule = chunk_schedule(n, chunk, len(names))
    for _ in range(repeats):
        steps, spent = {}, {m: [0.0, 0.0] for m in names}
        for m in names:
            w0, c0 = wall(), cpu()
            steps[m] = builders[m]()
            out[m]["build_ms"].append((wall() - w0) * 1e3)
            out[m]["build_cpu_ms"].append((cpu() - c0) * 1e3)
        for start, stop, order in schedule:
            for j in order:
                m = names[j]
                w0, c0 = wall(), cpu()
                for i in range(start, stop):
                    steps[m](i)
                spent[m][0] += wall() - w0
                spent[m][1] += cpu() - c0
        for m in names:
            out[m]["ms"].append(spent[m][0] * 1e3 / max(n, 1))
            out[m]["cpu_ms"].append(spent[m][1] * 1e3 / max(n, 1))
    return out


def ratio_spread(values: Sequence[float], base: Sequence[float]) -> dict:
    """The ratios values[i] / base[i] of paired passes: their median, min, max and the list
    (rounded to 3 digits; None where a base is not positive)."""
    if len(values) != len(base):
        raise ValueError(f"{len(values)} values for {len(base)} bases")
    r = [v / b for v, b in zip(values, base, strict=True) if b > 0]
    if not r:
        return {"median": None, "min": None, "max": None, "runs": []}
    return {"median": _round(float(np.median(r)), 3), "min": _round(min(r), 3),
            "max": _round(max(r), 3), "runs": [_round(x, 3) for x in r]}


def interleaved_ratios(costs: dict[str, dict[str, list[float]]], method: str,
                       base: str = BASELINE) -> dict:
    """``method``'s per-frame cost over ``base``'s, pass by pass (wall ``x_v1`` and CPU
    ``cpu_x_v1``), with both methods' per-pass figures."""
    a, b = costs[method], costs[base]
    return {"passes": len(a["ms"]), "x_v1": ratio_spread(a["ms"], b["ms"]),
            "cpu_x_v1": ratio_spread(a["cpu_ms"], b["cpu_ms"]),
            "cpu_ms": [_round(x, 2) for x in a["cpu_ms"]],
            "base_cpu_ms": [_round(x, 2) for x in b["cpu_ms"]],
            "build_cpu_ms": [_round(x, 1) for x in a["build_cpu_ms"]],
            "base_build_cpu_ms": [_round(x, 1) for x in b["build_cpu_ms"]]}


# ---------------------------------------------------------------------------- frames
def scaled(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    size = (WIDTH, int(round(h * WIDTH / w / 2)) * 2)
    return cv2.resize(frame, size, interpolation=cv2.INTER_LINEAR if w < WIDTH
                      else cv2.INTER_AREA)


def read_clip(path: Path) -> tuple[list[np.ndarray], list[np.ndarray], float, int, np.ndarray]:
    """Enrolment frames (those of the first 60 % that ``articast enroll`` would analyse:
    strided to at most MAX_ENROL_FRAMES plus a consecutive run), held-out frames (the rest),
    fps, the clip's frame count and the enrolment frames' times (s)."""
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    n = 0
    while cap.grab():
        n += 1
    cap.release()
    n_enrol = int(ENROL_FRACTION * n)
    keep = set(analysed_frames(n_enrol, MAX_ENROL_FRAMES).tolist())
    enrol, held, times = [], [], []
    cap = cv2.VideoCapture(str(path))
    for i in range(n):
        ok, f = cap.read()
        if not ok:
            break
        if i >= n_enrol:
            held.append(scaled(f))
        elif i in keep:
            enrol.append(scaled(f))
            times.append(i / fps)
    cap.release()
    return enrol, held, fps, n, np.array(times)


# ---------------------------------------------------------------------------- methods
class ArticastLoop:
    """articast's live loop as a user writes it: the finding landmarks' sessions and the
    :class:`LiveTracker` (which loads the reader) made once, then one ``track`` per frame."""

    def __init__(self, speaker, frames: list[np.ndarray], fps: float,
                 policy: LivePolicy | None = None, readers: int = 1) -> None:
        """readers : 2, the live stream of two readers (core/faces/two_readers.py; ``live``
        stays the first tracker, whose figures the info reports)."""
        self.frames, self.fps = frames, fps
        self.live = LiveTracker(speaker, FaceFinder.load(threads=1),
                                mediapipe_scheme(speaker.rig), policy, clock=time.perf_counter)
        self.step: Any = self.live
        if readers == 2:
            from articast.core.faces.two_readers import TwoReaderTracker

            pair = TwoReaderTracker.of(self.live)
            if SECOND_EVERY > 1:  # (a point of the cost curve, not the product: the
                # second tracker reads v2 every n-th frame, as the default before issue 38
                # read v1: the cadence cancelled, no reader's gap in its stream)
                s = pair.second
                assert s.fusion is not None
                fu = replace(s.fusion, read_every=SECOND_EVERY, cadence=0.1, reader_gap=None)
                pair = TwoReaderTracker(self.live, LiveTracker(
                    s.speaker, self.live.finder, mediapipe_scheme(s.speaker.rig),
                    replace(s.policy, fusion=fu), clock=time.perf_counter, reader=s.reader))
            self.step = pair

    def __call__(self, i: int) -> Any:
        return self.step.track(self.frames[i], i / self.fps)


class FinderLoop:
    """A landmark model's loop: the detector on the first frame and when lost, else the
    landmarks in a crop grown from the previous frame's (``FaceFinder.track``)."""

    def __init__(self, finder: FaceFinder, frames: list[np.ndarray]) -> None:
        self.finder, self.frames, self.prev = finder, frames, None

    def __call__(self, i: int) -> Any:
        f = self.frames[i]
        face = self.finder.track(f, self.prev) if self.prev is not None else None
        self.prev = face = face or self.finder.find(f)
        return face


def reader_crop() -> float:
    """The live reader's crop under test (``FusionPolicy.reader_keep_roi`` of ``--variant``
    and ``--set``): the enrolment's readings are made with it too."""
    fu = (ARTICAST_POLICY or LivePolicy()).fusion or FusionPolicy()
    return float(fu.reader_keep_roi)


def stored_crop(speaker: Any) -> float:
    """The reader's crop a speaker's readings were made with (``report["reader"]
    ["keep_roi"]``); a speaker enrolled before it was recorded was read with the finder's
    default policy (``FaceFinder.load(landmarks="v1")``): ``FinderPolicy().keep_roi``."""
    got = (speaker.report.get("reader") or {}).get("keep_roi")
    return float(FinderPolicy().keep_roi if got is None else got)


def enrolled(name: str | None, make: Callable[[], Any], reader: str) -> Any:
    """The speaker ``make`` enrols, kept in ``SPEAKERS``/<name> (``--speakers``) and loaded
    from there on the next run: a live-policy experiment need not enrol again (the enrolment
    does not depend on the live policy, but for the reader's crop: a stored speaker whose
    readings were made with another crop than the one under test is refused, SystemExit).
    Only the product's enrolment is kept (the v1 reader, no ``--enrol-blend``); the folder
    is the clip's name. A FaceLandmarker v2 reader (``--variant reader_v2``) tracks a stored
    speaker through the observation model its enrolment learned for v2 (``finder_points``,
    offline track's second reader: :func:`~articast.core.faces.offline.second_reader`), the
    upper face left out (its references are the v1 reader's lids); a folder without it is
    enrolled again with the v2 reader, not kept."""
    folder = SPEAKERS / name if SPEAKERS is not None and name else None
    if folder is not None and reader == "v2" and not ENROL_BLEND \
            and (folder / "points_v2.npz").is_file():
        from articast.core.faces.offline import second_reader
        from articast.core.faces.speaker import Speaker

        got = second_reader(Speaker.load(folder))
        if got is not None:
            return got
    if folder is None or reader != "v1" or ENROL_BLEND:
        return make()
    from articast.core.faces.speaker import Speaker

    if (folder / "speaker.json").is_file():
        try:
            stored = Speaker.load(folder)
        except Exception as e:  # noqa: BLE001 - a stale folder is enrolled again
            log(f"  {name}: stored speaker not loaded ({type(e).__name__}: {e}), enrolling")
        else:
            if stored.points is not None and stored_crop(stored) != reader_crop():
                raise SystemExit(f"{folder}: enrolled with the reader's crop keep_roi "
                                 f"{stored_crop(stored):g}, tracked with {reader_crop():g}: "
                                 "give --speakers a folder of enrolments made with it")
            return stored
    speaker = make()
    folder.mkdir(parents=True, exist_ok=True)
    speaker.save(folder)
    return speaker


def run_articast(enrol, held, fps, camera=None, enrol_fps=None, rig="desk",
                 times=None, build=None, name: str | None = None) -> dict:
    """Enrol on ``enrol`` (already selected, taken at ``times``; ``build``: the enrolment's
    BuildOptions, default its defaults; ``name``: the clip's, for ``--speakers``), track
    ``held`` live."""
    fu = (ARTICAST_POLICY or LivePolicy()).fusion
    reader = fu.reader if fu is not None else "v1"
    try:
        speaker = enrolled(name if build is None else None, lambda: enrol_speaker(
            enrol, enrol_fps or fps, camera=camera, rig=rig, max_frames=None, times=times,
            build=build, reader=reader, blend=ENROL_BLEND, reader_keep_roi=reader_crop()),
            reader)
    except Exception as e:  # noqa: BLE001 - a clip it cannot enrol is a result, not a crash
        return {"error": f"enrolment failed: {type(e).__name__}: {e}"}
    kernels.warm_up()  # numba's compilation: once per process, not a session's

    def build() -> ArticastLoop:
        return ArticastLoop(speaker, held, fps, ARTICAST_POLICY, READERS)

    def build_lips() -> ArticastLoop:  # (the lips alone: the upper face's references left out)
        return ArticastLoop(replace(speaker, upper=None), held, fps, ARTICAST_POLICY, READERS)

    got = timed_pass(build, len(held))
    results, live = got["outputs"], got["step"].live
    m, cam = speaker.model, speaker.camera
    offline_cpu_ms = None
    second_cpu_ms = None
    if OFFLINE and live.fusion is not None:  # as `articast track` writes them (not timed in
        # the loop's figures, which stay the live loop's: the smoothing's own CPU apart, and
        # the second reader's tracker's)
        from articast.core.faces.offline import (
            SECOND_READER,
            OfflineSmoother,
            averaged,
            reader_ratios,
            second_reader,
            smoothed,
            with_reader_gap,
        )

        sp2 = None if SINGLE_READER else second_reader(speaker)
        readers, one_euro = (1 if sp2 is None else 2), (True if OFFLINE_ONE_EURO else None)
        c0 = time.process_time()
        sm = OfflineSmoother.for_live(live, readers, one_euro)
        for r in results:
            sm.add(r)
        frames = sm.finish()
        offline_cpu_ms = (time.process_time() - c0) * 1e3 / max(len(held), 1)
        ratios = [reader_ratios(results)]
        if sp2 is not None:
            c0 = time.process_time()
            # (its reader crops as the first's does: FusionPolicy.reader_keep_roi)
            second = ArticastLoop(sp2, held, fps, replace(SECOND_READER, fusion=replace(
                SECOND_READER.fusion, reader_keep_roi=reader_crop())))
            sm2 = OfflineSmoother.for_live(second.live, readers, one_euro)
            again = [second(i) for i in range(len(held))]
            for r in again:
                sm2.add(r)
            frames = averaged(frames, sm2.finish())
            ratios.append(reader_ratios(again))
            second_cpu_ms = (time.process_time() - c0) * 1e3 / max(len(held), 1)
        if OFFLINE_GAP is not None:
            frames = with_reader_gap(frames, ratios, m, cam, OFFLINE_GAP)
        results = [smoothed(r, f, m) for r, f in zip(results, frames, strict=True)]
    ok = np.array([r.ok for r in results])
    alpha = np.array([r.alpha for r in results])
    from articast.core.outputs.lips import lip_measures

    ap_mm, width_mm = lip_measures(m, alpha)
    ratio = np.where(ok, ap_mm / outer_width_mm(m, alpha), np.nan)
    idx = [m.point(x) for x in ("8.1", "8.2", "8.3", "8.4")]
    boxes = np.full((len(held), 4), np.nan)
    for i, r in enumerate(results):
        if r.ok:
            uv = cam.project_head(m.shape(np.asarray(r.alpha))[idx], r.pose)
            boxes[i] = np.concatenate([uv.min(0), uv.max(0)])
    reasons: dict[str, int] = {}
    for r in results:
        if not r.ok:
            code = r.reason.split(":", 1)[0]
            reasons[code] = reasons.get(code, 0) + 1
    return {"ratio": ratio, "boxes": boxes, **_costs(got), "found": ok, "builder": build,
            "lips_builder": build_lips,
            "speaker": speaker, "results": results, "aperture_mm": ap_mm,
            "width_mm": width_mm, "ok": ok,
            "info": {"ok": _round(ok.mean(), 4), "reasons": reasons,
                     "occluded_frames": [i for i, r in enumerate(results)
                                         if not r.ok and r.reason.startswith("occluded")],
                     "restarts": live.restarts,
                     "gated": getattr(live, "regated", None),
                     "gated_realigned": getattr(live, "realigned", None),
                     "finder_calls_per_frame": _round(live.finder_calls / max(len(held), 1), 3),
                     "offline_smoothing_cpu_ms": _round(offline_cpu_ms, 3),
                     "offline_second_reader_cpu_ms": _round(second_cpu_ms, 2),
                     "enrol_frames": speaker.report["enrol_frames"],
                     "enrol_build_s": _round(speaker.report["build_s"], 1)}}


def _costs(got: dict) -> dict:
    return {k: got[k] for k in ("ms", "cpu_ms", "build_ms", "build_cpu_ms")}


def run_finder(make: Callable[[], FaceFinder], held, scheme="mediapipe") -> dict:
    """A landmark model's loop (:class:`FinderLoop`) on ``held``; ``make`` loads its sessions
    (timed apart)."""
    def build() -> FinderLoop:
        return FinderLoop(make(), held)

    got = timed_pass(build, len(held))
    faces = got["outputs"]
    # NaN where no face, as many points as the model gives (478 for v2, 468 for FaceMesh v1)
    shape = next((f.landmarks.shape for f in faces if f is not None), (478, 3))
    marks = np.array([f.landmarks if f is not None else np.full(shape, np.nan)
                      for f in faces])
    pts = marks[:, :, :2]
    return {"ratio": aperture_ratio(pts, scheme), "boxes": lip_box(pts, scheme),
            **_costs(got), "found": np.array([f is not None for f in faces]),
            "builder": build}


def facemesh_v1_finder(path: Path) -> FaceFinder:
    """The FaceMesh v1 loop's sessions: the bundled detector and the v1 model at ``path``,
    one thread each."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    detector, lm = (ort.InferenceSession(str(f), opts, providers=["CPUExecutionProvider"])
                    for f in (models_dir() / "face_detector.onnx", path))
    return FaceFinder(detector, lm, FinderPolicy(refine=0, keep_roi=0.0))


def run_worker(name: str, peer: dict, held: list[np.ndarray]) -> dict:
    """Run one peer in its venv on ``held`` through a pipe; its own per-frame timing."""
    got = worker_points(name, peer, held)
    if "error" in got:
        return got
    pts, scheme = got["points"], got["scheme"]
    found = np.isfinite(pts).all(axis=(1, 2))
    return {"ratio": aperture_ratio(pts, scheme), "boxes": lip_box(pts, scheme),
            "ms": got["ms"], "cpu_ms": got["cpu_ms"], "found": found}


def worker_points(name: str, peer: dict, held: list[np.ndarray]) -> dict:
    """One peer's points on ``held`` (``points`` (N, K, 2) px, NaN where no face; ``scheme``;
    its mean ``ms`` and ``cpu_ms``), or ``error``."""
    h, w = held[0].shape[:2]
    node = "node" in peer  # a Node.js worker (face-api.js) writes JSON, the Python ones npz
    if node:
        cmd = [peer["node"], str(HERE / f"peer_worker_{name}.cjs"), name, json.dumps(peer)]
    else:
        cmd = [peer["python"], str(HERE / "peer_worker.py"), name, json.dumps(peer)]
    with tempfile.TemporaryDirectory(prefix="articast-peer-") as tmp:
        out = Path(tmp) / ("out.json" if node else "out.npz")
        err = Path(tmp) / "stderr.txt"
        with open(err, "wb") as fh:
            proc = subprocess.Popen(
                [*cmd, str(out)],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=fh,
                env={**os.environ, "OMP_NUM_THREADS": "1", "TF_NUM_INTEROP_THREADS": "1",
                     "TF_NUM_INTRAOP_THREADS": "1", "GLOG_minloglevel": "2"})
            assert proc.stdin is not None
            try:
                proc.stdin.write(json.dumps({"n": len(held), "h": h, "w": w}).encode() + b"\n")
                for f in held:
                    proc.stdin.write(np.ascontiguousarray(f).tobytes())
                proc.stdin.close()
            except BrokenPipeError:
                pass
            code = proc.wait()
        if code != 0 or not out.is_file():
            tail = err.read_text(errors="replace").strip().splitlines()
            return {"error": f"worker exit {code}: {tail[-1] if tail else ''}"}
        if node:
            got = json.loads(out.read_text())
            k = max((len(p) for p in got["points"] if p is not None), default=0)
            pts = np.full((len(got["points"]), k, 2), np.nan)
            for i, p in enumerate(got["points"]):
                if p is not None:
                    pts[i] = p
            data = {"ms": np.asarray(got["ms"], float), "cpu_ms": np.asarray(got["cpu_ms"], float)}
            scheme = str(got["scheme"])
        else:
            data = np.load(out)
            pts, scheme = data["points"], str(data["scheme"])
        if pts.shape[1] == 0:  # no face in any frame: as many NaN points as the scheme needs
            pts = np.full((len(held), max(SCHEMES[scheme]) + 1, 2), np.nan)
        return {"points": pts, "scheme": scheme, "ms": float(data["ms"].mean()),
                "cpu_ms": float(data["cpu_ms"].mean())}


def load_peers(cache: Path) -> dict:
    path = cache / "peers.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def run_methods(methods, held, fps, enrol, facemesh_v1: Path | None, peers: dict,
                articast_kw: dict | None = None) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for name in methods:
        log(f"  {name} on {len(held)} frames")
        t0 = time.perf_counter()
        if name == "articast":
            out[name] = run_articast(enrol, held, fps, **(articast_kw or {}))
        elif name == "facemesh_v1":
            if facemesh_v1 is None or not facemesh_v1.is_file():
                out[name] = {"error": f"no FaceMesh v1 ONNX at {facemesh_v1}: run "
                                      "tools/convert_face_models.py --with-v1"}
            else:
                out[name] = run_finder(lambda: facemesh_v1_finder(facemesh_v1), held)
        elif name == "facelandmarker_v2":
            out[name] = run_finder(lambda: FaceFinder.load(threads=1), held)
        else:
            peer = peers.get(name)
            if not peer or not peer.get("ok"):
                out[name] = {"error": (peer or {}).get("reason") or
                             "not set up: run benchmarks/setup_peers.py"}
            else:
                out[name] = run_worker(name, peer, held)
        if "error" in out[name]:
            log(f"  {name}: skipped: {out[name]['error']}")
        else:
            log(f"  {name}: {out[name]['ms']:.2f} ms/frame "
                f"({time.perf_counter() - t0:.0f} s in all)")
    a, b = out.get("articast", {}), out.get(BASELINE, {})
    if CPU_REPEATS > 0 and "builder" in a and "builder" in b:
        log(f"  articast and {BASELINE} interleaved: {CPU_REPEATS} passes, turns of "
            f"{CPU_CHUNK} frames")
        costs = interleaved_cost({"articast": a["builder"], BASELINE: b["builder"],
                                  "articast_lips": a["lips_builder"]},
                                 len(held), CPU_REPEATS, CPU_CHUNK)
        a["interleaved"] = interleaved_ratios(costs, "articast")
        a["interleaved_lips"] = interleaved_ratios(costs, "articast_lips")
        log(f"  CPU x v1 interleaved: {a['interleaved']['cpu_x_v1']}; the lips alone: "
            f"{a['interleaved_lips']['cpu_x_v1']}")
    return out


# ---------------------------------------------------------------------------- a clip
def read_series(path: Path) -> dict:
    """One clip's ``--series`` file: fps, each method's aperture ratio and lip boxes, and the
    truth (synthetic) or None."""
    d = np.load(path, allow_pickle=False)
    methods = [str(m) for m in d["methods"]]
    return {"fps": float(d["fps"]), "ratio": {m: d[f"ratio_{m}"] for m in methods},
            "boxes": [d[f"box_{m}"] for m in methods],
            "truth": d["truth"] if "truth" in d.files else None}


def series_clips(series: Path, only: Sequence[str] | None,
                 left_out: Sequence[str] = ("articast",), clips: Path = CLIP_CACHE
                 ) -> list[tuple[str, dict]]:
    """The clips of a ``--series`` directory a script can rerun articast on: every clip in it
    (or ``only``) that is fetched (or synthetic), whose series hold articast's and at least
    two methods besides ``left_out``; (name, :func:`read_series` with the clip's ``path``),
    the others logged as skipped. ``clips``: the clips folder (:func:`common.clip_paths`). A
    missing directory is one line (SystemExit)."""
    if not series.is_dir():
        raise SystemExit(f"no series directory {series}: run benchmarks/peers.py --series "
                         f"{series} first")
    fetched = clip_paths(clips)
    out = []
    for name in only or sorted(p.stem for p in series.glob("*.npz")):
        path = series / f"{name}.npz"
        if not path.is_file() or (name != "synthetic" and name not in fetched):
            log(f"{name}: skipped (no series in {series} or clip not fetched)")
            continue
        s = read_series(path)
        s["path"] = fetched.get(name)
        if "articast" not in s["ratio"] or len(set(s["ratio"]) - set(left_out)) < 2:
            log(f"{name}: skipped (fewer than two other methods in its series)")
            continue
        out.append((name, s))
    return out


def add_articast_options(ap: argparse.ArgumentParser) -> None:
    """How articast runs in a benchmark that scores it: ``--variant``, ``--offline``,
    ``--single-reader`` (:func:`use_articast_options` applies them)."""
    ap.add_argument("--variant", choices=list(VARIANTS), default="fused",
                    help="articast's live policy (the ablation of docs/TRACKING.md; default: "
                         "the product's, fused)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    dest="policy_set",
                    help="one field of articast's live policy changed on top of --variant "
                         "(repeatable): a FusionPolicy field (appearance_weight=2, "
                         "read_every=2, cadence=none, regression=false) or one_euro.FIELD "
                         "(min_cutoff, beta, d_cutoff) of the streamed articulation's filter")
    ap.add_argument("--enrol-blend", type=float, default=0.0, metavar="W",
                    help="a diagnosis, not the product: build the speaker's model from "
                         "(1 - W) x the finding landmarks (FaceLandmarker v2) + W x the live "
                         "reader's (FaceMesh v1) on the same enrolment frames (default 0)")
    ap.add_argument("--offline", action="store_true",
                    help="score articast's results as 'articast track' writes a recorded "
                         "clip (core/faces/offline.py); its CPU figures stay the live loop's, "
                         "the smoothing's own cost is offline_smoothing_cpu_ms, the second "
                         "reader's offline_second_reader_cpu_ms")
    ap.add_argument("--readers", type=int, choices=(1, 2), default=1,
                    help="live, 2: the opt-in stream of two readers (core/faces/"
                         "two_readers.py: a second tracker reads FaceLandmarker v2 on every "
                         "frame through the speaker's v2 observation model, each frame the "
                         "mean of the two articulations; timed in the loop); default 1")
    ap.add_argument("--second-every", type=int, default=1, metavar="N",
                    help="with --readers 2, a point of the cost curve (not the product): "
                         "the second tracker reads FaceLandmarker v2 on every N-th frame only "
                         "(its cadence cancelled, no reader's gap in its stream); default 1")
    ap.add_argument("--single-reader", action="store_true",
                    help="with --offline: FaceMesh v1's tracker alone, as 'articast track "
                         "--single-reader' writes it")
    ap.add_argument("--offline-gap", type=float, default=None, metavar="SHARE",
                    help="with --offline: the readers' lip gap's share of the opening "
                         "(core/faces/offline.py READER_GAP; default: track's own; 0: the "
                         "smoothed fit alone, as before issue 38)")
    ap.add_argument("--offline-one-euro", action="store_true",
                    help="with --offline: the One Euro filter forward and back over the "
                         "smoothed fits with two readers too, as sessions 6-8 wrote a track "
                         "(core/faces/offline.py ONE_EURO_READERS)")


def use_articast_options(args: argparse.Namespace) -> None:
    """:func:`add_articast_options`' choices, for :func:`run_articast`."""
    global ARTICAST_POLICY, OFFLINE, SINGLE_READER, ENROL_BLEND, OFFLINE_GAP, OFFLINE_ONE_EURO
    global READERS, SECOND_EVERY
    try:
        ARTICAST_POLICY = policy_with(VARIANTS[args.variant], args.policy_set)
    except ValueError as e:
        raise SystemExit(f"--set: {e}") from None
    if not 0.0 <= args.enrol_blend <= 1.0:
        raise SystemExit(f"--enrol-blend must be within 0..1, got {args.enrol_blend:g}")
    OFFLINE, SINGLE_READER, ENROL_BLEND = args.offline, args.single_reader, args.enrol_blend
    READERS, SECOND_EVERY = args.readers, args.second_every
    if SECOND_EVERY < 1 or (SECOND_EVERY != 1 and READERS != 2):
        raise SystemExit("--second-every N: N >= 1, with --readers 2")
    if READERS != 1 and OFFLINE:
        raise SystemExit("--readers is for the live stream: --offline reads two already "
                         "(--single-reader: one)")
    from articast.core.faces.offline import READER_GAP

    OFFLINE_GAP = READER_GAP if args.offline_gap is None else args.offline_gap
    OFFLINE_ONE_EURO = args.offline_one_euro


def _value(text: str) -> Any:
    low = text.strip().lower()
    if low in ("none", "off"):
        return None
    if low in ("true", "false"):
        return low == "true"
    try:
        return int(low)
    except ValueError:
        pass
    try:
        return float(low)
    except ValueError:
        raise ValueError(f"{text!r} is not a number, true, false or none") from None


def policy_with(policy: LivePolicy | None, changes: Sequence[str]) -> LivePolicy | None:
    """``policy`` (None: the default LivePolicy) with each ``FIELD=VALUE`` of ``changes``
    applied: a :class:`FusionPolicy` field, or ``one_euro.FIELD`` of the streamed filter.
    ValueError (one line) for an unknown field, a malformed change or a policy without
    fusion."""
    if not changes:
        return policy
    live = policy or LivePolicy()
    fusion_fields = set(FusionPolicy.__dataclass_fields__)
    euro_fields = set(OneEuroPolicy.__dataclass_fields__)
    for change in changes:
        name, sep, text = change.partition("=")
        name = name.strip()
        if not sep or not name:
            raise ValueError(f"{change!r} is not FIELD=VALUE")
        value = _value(text)
        if name.startswith("one_euro."):
            field = name.split(".", 1)[1]
            if field not in euro_fields:
                raise ValueError(f"one_euro has no field {field!r} "
                                 f"({', '.join(sorted(euro_fields))})")
            if value is None or isinstance(value, bool):
                raise ValueError(f"{name} takes a number, got {text!r}")
            live = replace(live, smoothing=replace(live.smoothing or OneEuroPolicy(),
                                                   **{field: float(value)}))
        elif name in fusion_fields:
            if live.fusion is None:
                raise ValueError(f"{name}: this variant tracks without fusion")
            live = replace(live, fusion=replace(live.fusion, **{name: value}))
        else:
            raise ValueError(f"no policy field {name!r} (a FusionPolicy field or "
                             f"one_euro.FIELD)")
    return live


def series_parser(doc: str) -> argparse.ArgumentParser:
    """The command line of a script that reruns articast on a ``--series`` directory's clips
    (:func:`series_clips`): its docstring's first paragraph as the description, ``--series``
    and ``--only``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="See the module docstring for what is measured.")
    ap.add_argument("--series", type=Path, required=True,
                    help="a peers.py --series directory (the other methods' series)")
    ap.add_argument("--only", nargs="*", help="these clips (default: every clip in --series "
                                              "that is fetched, and synthetic)")
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE,
                    help=f"the clips folder: a clips.json, or every video in it (default "
                         f"{CLIP_CACHE})")
    return ap


def series_clip(name: str, series: dict, left_out: Sequence[str] = ("articast",)) -> dict:
    """What rerunning articast on one ``--series`` clip needs: its ``enrol`` and ``held``
    frames, ``fps``, :func:`run_articast`'s keywords ``kw``, the ``others``' series (without
    ``left_out``) and the still ``windows``. SystemExit when the series does not match the
    clip's frames (a run of another clip or version)."""
    if name == "synthetic":
        clip = synthetic_clip()
        enrol, held, fps = clip["enrol"], clip["held"], 50.0
        kw: dict = {"camera": clip["camera"], "enrol_fps": 12.0}
    else:
        enrol, held, fps, _, times = read_clip(series["path"])
        kw = {"times": times}
    others = {k: v for k, v in series["ratio"].items() if k not in left_out}
    if len(next(iter(others.values()), [])) != len(held):
        raise SystemExit(f"{name}: the series in --series has another number of frames than "
                         f"the clip ({len(held)}): a run of another clip or version")
    return {"enrol": enrol, "held": held, "fps": fps, "kw": kw, "others": others,
            "windows": clip_windows(held, window_boxes(dict(zip(series["ratio"], series["boxes"],
                                                                strict=True)), left_out), fps)}


def window_boxes(boxes: dict[str, np.ndarray], scored: Sequence[str] = ("articast",)
                 ) -> list[np.ndarray]:
    """The lip boxes that place the mouth for the still windows: every method's but the
    ``scored`` ones' (articast's), so that every variant of articast is scored on the same
    windows as its reader (with its own box in the median, a variant that moved its box by a
    pixel moved the windows and the reader's jitter with them); all of them where no other
    method has one."""
    rest = [b for k, b in boxes.items() if k not in scored]
    return rest or list(boxes.values())


def clip_windows(held, boxes: Sequence[np.ndarray], fps: float) -> list[slice]:
    """The still-mouth windows of ``held``: the mouth placed by the per-frame median of the
    lip ``boxes`` (each (F, 4), NaN where none; :func:`window_boxes`)."""
    stack = np.array(boxes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        box = np.nanmedian(stack, 0) if len(stack) else np.full((len(held), 4), np.nan)
    grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in held]
    length = window_frames(fps)
    motion = box_motion(grey, [b if np.isfinite(b).all() else None for b in box], length)
    return still_windows(motion, length)


def evaluate(name: str, held, fps, runs: dict[str, dict], truth: np.ndarray | None = None
             ) -> dict:
    live = {k: v for k, v in runs.items() if "error" not in v}
    aps = {k: v["ratio"] for k, v in live.items()}
    windows = clip_windows(held, window_boxes({k: v["boxes"] for k, v in live.items()}), fps)
    scores = score(aps, windows)
    base = live.get(BASELINE, {}).get("ms")
    base_cpu = live.get(BASELINE, {}).get("cpu_ms")
    rows = {}
    for k in runs:
        v = runs[k]
        if "error" in v:
            rows[k] = {"skipped": v["error"]}
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            p50 = np.nanmedian(v["ratio"]) if np.isfinite(v["ratio"]).any() else None
        row = {"found": _round(np.mean(v["found"]), 4), **scores[k],
               "aperture_median": _round(p50, 4),
               "ms": _round(v["ms"], 2), "cpu_ms": _round(v["cpu_ms"], 2),
               "x_v1": _round(v["ms"] / base, 3) if base and v["ms"] else None,
               "cpu_x_v1": _round(v["cpu_ms"] / base_cpu, 3)
               if base_cpu and v["cpu_ms"] else None,
               "build_ms": _round(v.get("build_ms"), 1),
               "build_cpu_ms": _round(v.get("build_cpu_ms"), 1)}
        for key in ("interleaved", "interleaved_lips"):
            if key in v:
                row[key] = v[key]
        if truth is not None:
            row["truth_r"] = _round(pearson(v["ratio"], truth)[0], 4)
        if "info" in v:
            row.update(v["info"])
        rows[k] = row
    pair = {a: {b: _round(pearson(aps[a], aps[b])[0], 3) for b in aps if b != a} for a in aps}
    out = {"clip": name, "fps": round(fps, 3), "held_out_frames": len(held),
           "still_windows": len(windows), "methods": rows, "pairwise_r": pair,
           "articast_vs_best": against_best(aps, scores, windows, fps),
           "articast_vs_reader": against_reader(aps, scores, windows, fps, truth=truth)}
    if truth is not None:
        out["consensus_vs_truth"] = consensus_validity(rows)
    return out


def consensus_validity(rows: dict[str, dict]) -> dict | None:
    """Where the truth is known: does the consensus rank the methods as the truth does?
    ``spearman``: rank correlation, over the methods, of ``consensus_r`` with ``truth_r``;
    each ranking best first."""
    pairs = [(k, r["consensus_r"], r["truth_r"]) for k, r in rows.items()
             if r.get("consensus_r") is not None and r.get("truth_r") is not None]
    if len(pairs) < 3:
        return None
    from scipy.stats import spearmanr

    rho = float(spearmanr([p[1] for p in pairs], [p[2] for p in pairs])[0])
    return {"spearman": _round(rho, 3),
            "by_consensus": [p[0] for p in sorted(pairs, key=lambda p: -p[1])],
            "by_truth": [p[0] for p in sorted(pairs, key=lambda p: -p[2])]}


def write_tiles(path: Path, held, run: dict, frames: Sequence[int],
                labels: Sequence[Sequence[str]], tile: int = 160, per_row: int = 10) -> None:
    """A grid of ``held``'s ``frames``, each with articast's fitted mesh (``run``: its run)
    and its lines of ``labels``."""
    if not frames:
        return
    sp = run["speaker"]
    tiles = []
    for i, lines in zip(frames, labels, strict=True):
        t = cv2.resize(fit_tile(held[i], sp.model, sp.camera, run["results"][i],
                                lip_contours(sp)), (tile, tile))
        for row, text in enumerate(lines):
            cv2.putText(t, text, (4, 14 + 14 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                        (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) % per_row:
        tiles.append(np.zeros_like(tiles[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack([np.hstack(tiles[r:r + per_row])
                                      for r in range(0, len(tiles), per_row)]),
                [cv2.IMWRITE_JPEG_QUALITY, 85])


def write_occluded_grid(path: Path, held, run: dict) -> None:
    """Every held-out frame articast marked ``occluded``, with its fitted mesh."""
    frames = run["info"]["occluded_frames"]
    write_tiles(path, held, run, frames, [[f"#{i}"] for i in frames])


def write_worst_grid(path: Path, held, runs: dict[str, dict], count: int = 20) -> None:
    """The ``count`` held-out frames where articast's lip aperture departs most from the
    judge's (each series z-scored over the frames both have: the error Pearson's r counts),
    worst first, with articast's fitted mesh and each frame's z-scores: articast (a), its
    reader (v1) and the judge (j). Where a and v1 agree against j, the judge or the reader's
    family is off; where a alone is off, articast is."""
    a = runs.get("articast", {})
    if "error" in a or "results" not in a:
        return
    aps = {k: v["ratio"] for k, v in runs.items() if "error" not in v and "ratio" in v}
    ref = judge(aps, "articast")
    both = np.isfinite(aps["articast"]) & np.isfinite(ref)
    if both.sum() < 3:
        return

    def z(x: np.ndarray) -> np.ndarray:
        return (x - np.nanmean(x[both])) / max(float(np.nanstd(x[both])), 1e-9)

    za, zj = z(aps["articast"]), z(ref)
    zr = z(aps["facemesh_v1"]) if "facemesh_v1" in aps else np.full(len(za), np.nan)
    err = np.where(both, np.abs(za - zj), -1.0)
    worst = [int(i) for i in np.argsort(-err)[:count] if err[i] >= 0]
    write_tiles(path, held, a, worst, [(f"#{i}", f"a {za[i]:+.1f} v1 {zr[i]:+.1f}",
                                        f"j {zj[i]:+.1f}") for i in worst])


def save_series(series: Path | None, name: str, fps: float, runs: dict[str, dict],
                truth: np.ndarray | None = None) -> None:
    """Each method's per-frame aperture ratio and lip box (NaN where none), to look into."""
    if series is None:
        return
    series.mkdir(parents=True, exist_ok=True)
    live = {k: v for k, v in runs.items() if "error" not in v}
    np.savez_compressed(series / f"{name}.npz", fps=fps, methods=list(live),
                        **{f"ratio_{k}": v["ratio"] for k, v in live.items()},
                        **{f"box_{k}": v["boxes"] for k, v in live.items()},
                        **({"truth": truth} if truth is not None else {}))


def stored_runs(others: Path | None, name: str, n: int, methods: Sequence[str]
                ) -> dict[str, dict]:
    """The methods of ``others``/<name>.npz (a ``--series`` run's) that ``methods`` does not
    run again, as runs with their stored aperture ratio and lip boxes (no timings): articast
    scored against peers run once (``--others``). Empty without ``others``; SystemExit when
    its series does not match the clip's ``n`` held-out frames."""
    if others is None:
        return {}
    path = others / f"{name}.npz"
    if not path.is_file():
        raise SystemExit(f"{name}: no series in {others}: run peers.py --series {others} first")
    s = read_series(path)
    out = {}
    for (k, ratio), box in zip(s["ratio"].items(), s["boxes"], strict=True):
        if k in methods:
            continue
        if len(ratio) != n:
            raise SystemExit(f"{name}: {path} holds {len(ratio)} frames, the clip {n}")
        out[k] = {"ratio": ratio, "boxes": box, "found": np.isfinite(ratio), "ms": None,
                  "cpu_ms": None}
    return out


def run_real(name: str, path: Path, methods, facemesh_v1, peers, grid: Path | None,
             series: Path | None = None) -> dict:
    log(f"{name}: reading {path.name}")
    enrol, held, fps, n, times = read_clip(path)
    runs = run_methods(methods, held, fps, enrol, facemesh_v1, peers,
                       {"times": times, "name": name})
    runs.update(stored_runs(OTHERS, name, len(held), methods))
    save_series(series, name, fps, runs)
    row = evaluate(name, held, fps, runs)
    row.update({"frames": n, "size": list(held[0].shape[1::-1]) if held else None,
                "enrol_fraction": ENROL_FRACTION})
    if grid is not None and "error" not in runs.get("articast", {"error": 1}):
        write_occluded_grid(grid / f"{name}_occluded.jpg", held, runs["articast"])
        write_worst_grid(grid / f"{name}_worst.jpg", held, runs)
    return row


def synthetic_clip(seed: int = 0) -> dict:
    """The built-in speaker on the desk rig: ``enrol`` (300 frames of a sentence read at 12
    fps, as benchmarks/no_truth_path.py), ``held`` (another sentence at 50 fps), the
    ``camera``, and the truth on ``held``: ``truth`` (aperture ratio), ``aperture_mm``,
    ``width_mm``."""
    from articast.core.model.build import invert
    from articast.core.outputs.lips import lip_measures
    from articast.core.synthetic import RenderOptions, default_speaker, make_sequence

    log("synthetic: rendering (desk, speaker 0)")
    sp = default_speaker(seed)
    true_model = sp.model()
    enrol = make_sequence(seed * 100 + 11, 300, 12.0, "desk", geometry=sp.geometry)
    enrol_imgs = [sp.render(enrol.controls[i], enrol.pose(i), enrol.camera,
                            RenderOptions(seed=10_000 + i)) for i in range(enrol.n_frames)]
    test = make_sequence(seed * 100 + 12, 150, 50.0, "desk", geometry=sp.geometry)
    held = [sp.render(test.controls[i], test.pose(i), test.camera,
                      RenderOptions(seed=20_000 + i)) for i in range(test.n_frames)]
    at = invert(true_model, test.points)
    ap_true, width_true = lip_measures(true_model, at)
    return {"enrol": enrol_imgs, "held": held, "camera": enrol.camera,
            "truth": ap_true / outer_width_mm(true_model, at), "aperture_mm": ap_true,
            "width_mm": width_true}


def run_synthetic(methods, facemesh_v1, peers, seed: int = 0, series: Path | None = None
                  ) -> dict:
    """The built-in speaker (:func:`synthetic_clip`), scored against the truth too."""
    clip = synthetic_clip(seed)
    enrol_imgs, held, truth = clip["enrol"], clip["held"], clip["truth"]
    ap_true, width_true = clip["aperture_mm"], clip["width_mm"]
    runs = run_methods(methods, held, 50.0, enrol_imgs, facemesh_v1, peers,
                       {"camera": clip["camera"], "enrol_fps": 12.0, "name": "synthetic"})
    runs.update(stored_runs(OTHERS, "synthetic", len(held), methods))
    save_series(series, "synthetic", 50.0, runs, truth)
    row = evaluate("synthetic", held, 50.0, runs, truth=truth)
    a = runs.get("articast", {})
    if "error" not in a and a:
        ok = a["ok"]
        row["methods"]["articast"]["aperture_mae_mm"] = _round(
            np.abs(a["aperture_mm"] - ap_true)[ok].mean(), 2)
        row["methods"]["articast"]["width_mae_mm"] = _round(
            np.abs(a["width_mm"] - width_true)[ok].mean(), 2)
    row.update({"frames": len(enrol_imgs) + len(held), "size": list(held[0].shape[1::-1]),
                "enrol": "300 frames of another sentence at 12 fps (all analysed)"})
    return row


# ---------------------------------------------------------------------------- output
COLUMNS = (("found / ok", lambda r: r.get("ok", r.get("found"))),
           ("r judge (n)", lambda r: f"{_fmt(r.get('judge_r'))} ({r.get('judge_n')})"),
           ("r consensus (n)", lambda r: f"{_fmt(r['consensus_r'])} ({r['consensus_n']})"),
           ("jitter % width", lambda r: r["jitter_pct_width"]),
           ("lag (velocity)", lambda r: f"{_fmt(r['lag_frames'])} "
                                        f"({_fmt(r['lag_velocity_frames'])})"),
           ("ms/frame", lambda r: r["ms"]),
           ("x v1", lambda r: r["x_v1"]),
           ("CPU ms (x v1)", lambda r: f"{_fmt(r['cpu_ms'])} ({_fmt(r['cpu_x_v1'])})"),
           ("CPU x v1 interleaved", lambda r: _spread(r.get("interleaved"))),
           ("build CPU ms", lambda r: r.get("build_cpu_ms")))


def _spread(inter: dict | None) -> str:
    """The interleaved passes' CPU ratio: median (min-max, passes)."""
    if not inter or inter["cpu_x_v1"]["median"] is None:
        return "–"
    c = inter["cpu_x_v1"]
    return f"{c['median']} ({c['min']}-{c['max']}, {inter['passes']})"


def _fmt(x) -> str:
    return "–" if x is None else str(x)


SUMMARY = (("r against the independent judge (one vote per family outside FaceMesh's and the "
            "method's own)", "judge_r"),
           ("r against the consensus of the others", "consensus_r"),
           ("still-mouth jitter, % of the outer lip width", "jitter_pct_width"),
           ("lag, frames (positive: late; ±5: no peak in the range)", "lag_frames"),
           ("lag of the frame-to-frame changes, frames", "lag_velocity_frames"),
           ("wall ms per frame / FaceMesh v1 loop's", "x_v1"),
           ("CPU ms per frame / FaceMesh v1 loop's", "cpu_x_v1"),
           ("the same, interleaved passes: median (min-max, passes)", "interleaved"),
           ("articast's lips alone (the upper face left out), the same passes",
            "interleaved_lips"),
           ("frames with a face (articast: ok)", None))


def summary(rows: list[dict]) -> list[str]:
    """One table per score: methods down, clips across."""
    clips = [r["clip"] for r in rows]
    methods = list(dict.fromkeys(m for r in rows for m in r["methods"]))
    lines = []
    for title, key in SUMMARY:
        lines += [f"**{title}**", "", "| method | " + " | ".join(clips) + " |",
                  "|---" * (len(clips) + 1) + "|"]
        for m in methods:
            cells = []
            for r in rows:
                v = r["methods"].get(m, {})
                if "skipped" in v or not v:
                    cells.append("–")
                elif key is None:
                    cells.append(_fmt(v.get("ok", v.get("found"))))
                elif key.startswith("interleaved"):
                    cells.append(_spread(v.get(key)))
                else:
                    cells.append(_fmt(v.get(key)))
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def markdown(rows: list[dict], load: dict) -> str:
    lines = [f"load average at start {load['start']}, at end {load['end']}", "",
             *summary(rows)]
    for row in rows:
        truth = row["clip"] == "synthetic"
        lines += [f"### {row['clip']} ({row['held_out_frames']} held-out frames at "
                  f"{row['fps']} fps, {row['still_windows']} still windows)", ""]
        head = [c for c, _ in COLUMNS] + (["r truth"] if truth else [])
        lines += ["| method | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
        for name, r in row["methods"].items():
            if "skipped" in r:
                lines.append(f"| {name} | skipped: {r['skipped']} |" + " |" * (len(head) - 1))
                continue
            cells = [_fmt(f(r)) for _, f in COLUMNS] + ([_fmt(r.get("truth_r"))] if truth
                                                         else [])
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        a = row["methods"].get("articast", {})
        if "ok" in a:
            occ = a["occluded_frames"]
            lines += ["", f"articast: ok {a['ok']}, not ok {a['reasons']}, restarts "
                      f"{a['restarts']}, finder calls/frame {a['finder_calls_per_frame']}, "
                      f"occluded frames {occ[:40]}{' ...' if len(occ) > 40 else ''}"
                      + (f"; aperture MAE {a['aperture_mae_mm']} mm, width MAE "
                         f"{a['width_mae_mm']} mm" if "aperture_mae_mm" in a else "")]
        vs = row.get("articast_vs_best") or {}
        for key, what in (("r", f"r gap (95 % interval, paired {BLOCK_S:g} s block "
                                f"bootstrap)"),
                          ("jitter", "jitter gap, % width (95 % interval, still windows "
                                     "resampled)")):
            if key in vs:
                g = vs[key]
                lines.append(f"articast - best peer ({g['peer']}), {what}: {g['gap']} "
                             f"({g['ci95'][0]} .. {g['ci95'][1]})")
        rd = row.get("articast_vs_reader") or {}
        for key, what in (("r_vs_reader", "its reader"), ("r_vs_best_facemesh",
                                                          "the best FaceMesh-family peer")):
            if key in rd:
                g = rd[key]
                lines.append(f"articast - {what} ({g['peer']}), r against the judge: "
                             f"{g['gap']} ({g['ci95'][0]} .. {g['ci95'][1]})")
        if "jitter_vs_reader" in rd:
            g = rd["jitter_vs_reader"]
            lines.append(f"articast - its reader, jitter: {g['gap']} ({g['ci95'][0]} .. "
                         f"{g['ci95'][1]}); lag of the changes behind the reader: "
                         f"{rd.get('lag_velocity_vs_reader')}")
        names = list(row["pairwise_r"])
        if names:
            lines += ["", "pairwise r: | " + " | ".join(names) + " |",
                      "|---" * (len(names) + 1) + "|"]
            for a_ in names:
                lines.append(f"| {a_} | " + " | ".join(
                    "1" if b == a_ else _fmt(row["pairwise_r"][a_].get(b)) for b in names)
                    + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    global CPU_REPEATS, CPU_CHUNK
    clips = clip_paths(CLIP_CACHE)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE,
                    help="the clips folder: its clips.json (tools/fetch_real_clips.py), or "
                         f"every video file in it, by name (default {CLIP_CACHE})")
    ap.add_argument("--peers", type=Path, default=PEER_CACHE,
                    help="the peers' cache made by benchmarks/setup_peers.py")
    ap.add_argument("--facemesh-v1", type=Path, default=models_dir() / "face_landmarks_v1.onnx",
                    help="FaceMesh v1 ONNX (default: the bundled one, mediapipe 0.10.14's "
                         "weights, which articast reads every frame too)")
    ap.add_argument("--only", nargs="*", help=f"clips (default: all fetched, then synthetic: "
                                              f"{' '.join([*clips, 'synthetic'])})")
    ap.add_argument("--methods", nargs="*", choices=METHODS, default=list(METHODS))
    ap.add_argument("--grid", type=Path,
                    help="write here, per clip, an overlay grid of every frame articast marks "
                         "occluded and one of the 20 frames its lips depart most from the "
                         "judge's (z-scores: articast, its reader, the judge)")
    ap.add_argument("--series", type=Path,
                    help="write each clip's per-method aperture ratio and lip box series here")
    ap.add_argument("--others", type=Path,
                    help="a --series directory of an earlier run: the methods not named by "
                         "--methods are read from it instead of run (articast's variants "
                         "scored against the same peers' series; no timings for those)")
    ap.add_argument("--speakers", type=Path,
                    help="keep each clip's enrolment here (a speaker folder per clip) and "
                         "reuse it on the next run: live-policy experiments without enrolling "
                         "again (only the product's enrolment: not with --enrol-blend or a "
                         "v2-reader variant)")
    add_articast_options(ap)
    ap.add_argument("--cpu-repeats", type=int, default=CPU_REPEATS,
                    help="passes of articast and the FaceMesh v1 loop interleaved on the "
                         "same frames for the CPU ratio's median and spread (0: none; "
                         f"default {CPU_REPEATS})")
    ap.add_argument("--cpu-chunk", type=int, default=CPU_CHUNK,
                    help=f"frames per turn in an interleaved pass (default {CPU_CHUNK})")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.cpu_repeats < 0 or args.cpu_chunk < 1:
        ap.error("--cpu-repeats must be >= 0 and --cpu-chunk >= 1")
    use_articast_options(args)
    CPU_REPEATS, CPU_CHUNK = args.cpu_repeats, args.cpu_chunk
    global SPEAKERS, OTHERS
    SPEAKERS, OTHERS = args.speakers, args.others
    cv2.setNumThreads(1)  # one thread: OpenCV's own pool would otherwise use every core
    clips = clip_paths(args.clips)
    names = args.only or [*clips, "synthetic"]
    peers = load_peers(args.peers)
    load = {"start": [round(x, 2) for x in os.getloadavg()]}
    log(f"load average {load['start']}; methods {' '.join(args.methods)}")
    rows = []
    for name in names:
        at = [round(x, 2) for x in os.getloadavg()]
        if name == "synthetic":
            rows.append(run_synthetic(args.methods, args.facemesh_v1, peers,
                                      series=args.series))
        elif name in clips:
            rows.append(run_real(name, clips[name], args.methods, args.facemesh_v1, peers,
                                 args.grid, args.series))
        else:
            sys.exit(f"{name}: no such clip in {args.clips} (clips there: "
                     f"{' '.join(clips) or 'none'})")
        rows[-1]["load_average_at_start"] = at
    load["end"] = [round(x, 2) for x in os.getloadavg()]
    if args.json:
        print(json.dumps({"load_average": load, "command": " ".join(sys.argv),
                          "variant": args.variant, "offline": args.offline,
                          "clips": rows}, indent=1))
    else:
        print(markdown(rows, load))


if __name__ == "__main__":
    main()

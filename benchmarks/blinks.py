"""articast's blinks on the real clips against an independent method's eye-aspect-ratio minima.

    python tools/fetch_real_clips.py                 # once: the clips
    python benchmarks/setup_peers.py ...              # once: dlib's venv (benchmarks/peers.py)
    python benchmarks/blinks.py [--only CLIP ...] [--grid docs/blinks] [--json]

Each clip is read as ``benchmarks/peers.py`` reads it (640 px wide; articast enrols on the first
60 %, as ``articast enroll`` analyses it, upper-face references included) and everything is
scored on the held-out 40 %:

- **articast**: the live tracker (``LiveTracker``, the product's policy: the FaceMesh v1 reader
  every third frame, and the frames its eyes ask for); a blink frame is one whose mean
  eyelid closure (left, right) is > 0.5;
- **reference**: dlib's 68-point shape predictor (its own HOG detector), in its own venv
  (``benchmarks/peer_worker.py``), a landmark model articast does not use: the eye aspect
  ratio (Soukupova & Cech 2016) of each eye, ``(|p2-p6| + |p3-p5|) / (2 |p1-p4|)``, averaged
  over both eyes; a blink frame is one whose EAR is below ``EAR_FRACTION`` x the clip's
  median EAR (the clip's open eye);
- events are runs of blink frames, runs apart by at most 50 ms merged (one frame at 24-30
  fps; :func:`~articast.core.evaluation.upper.blink_events`, the synthetic scorer's count
  too); an articast event and
  a reference event match when they overlap within ``TOLERANCE`` frames (dlib's own events
  fragment: an event of articast's over three of its pieces is one true event, each piece
  found). precision = matched
  articast events / articast events, recall = matched reference events / reference events;
  ``onset`` = articast's first blink frame minus the reference's, per matched pair;
  ``precision_one_to_one`` / ``recall_one_to_one``: each reference event matched by one of
  articast's at most, the rest false (a blink read as ten flickering events is one true and
  nine false);
- ``brows_vs_dlib_r``: the correlation of articast's brow raise (both sides' mean, mm) with
  dlib's (the brow points' mean height above the eye corners over the inter-ocular
  distance, :func:`brow_raise`) over the held-out frames;
- ``gaze``: ``frames``, the fraction of held-out frames with a gaze (held between readings);
  its median and interquartile range (deg); and against an independent iris,
  ``vs_iris_r`` (yaw, pitch): the correlation of articast's gaze yaw and pitch with
  mediapipe's iris offset over the frames where both have one. The reference is mediapipe's
  legacy FaceMesh with ``refine_landmarks=True`` (its attention model's iris points, in the
  mediapipe venv: ``benchmarks/peer_worker.py`` ``mediapipe_iris``; articast never imports
  it): each eye's iris centre (468, 473) from the middle of its corners (33-133, 362-263),
  along and across the corners' axis over the eye's width (x to the image's right, the
  speaker's left; y up), both eyes averaged (:func:`iris_offsets`). It is in the image, not
  the head's frame: a head turn moves it a little too. ``ref_sd`` is its spread (a clip
  whose speaker hardly moves his eyes has little to correlate);
- ``upper_ms`` / ``upper_cpu_ms``: the time of the upper face's own step per frame
  (``UpperTracker.step``, timed inside the same live run) next to the whole frame's
  (``frame_ms``), one thread; ``over_lips_cpu_ms``: what the upper face costs the frame,
  all of it (its step, and the frames read for the eyes, ``eye_reads``, with their fits):
  the CPU per frame of the live run less that of the same tracker without the upper face
  (the speaker's references left out), the median over 3 interleaved pairs of runs, their
  range ``over_lips_spread_ms``.

- ``precision_confirmed`` / ``recall_confirmed`` (and ``confirmed_events``): the same against
  dlib's events as confirmed by looking at every one in the grids (``blink_review.json``:
  dlib events that are not blinks, e.g. eyes looking down, are dropped; blinks it missed are
  added; frames where nobody can tell are left out for both methods);

``--grid DIR`` writes, per clip, the frames around each event (both methods' events: a tile per
frame from 2 before to 4 after the onset, the upper face, labelled with articast's closure and
the reference's EAR ratio) to DIR/CLIP.jpg.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import peers as peers_mod  # noqa: E402
from blink_review import confirmed  # noqa: E402
from peers import (  # noqa: E402
    CLIP_CACHE,
    PEER_CACHE,
    clip_paths,
    load_peers,
    read_clip,
    worker_points,
)
from real_clips import cost_over_lips, enrol_speaker, upper_again  # noqa: E402

from articast.core.errors import InputError  # noqa: E402
from articast.core.evaluation.upper import (  # noqa: E402
    BLINK_CLOSURE,
    blink_events,
    events,
    match_events,
)
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.live import LivePolicy, LiveTracker  # noqa: E402
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.tracking import kernels  # noqa: E402

EAR_FRACTION = 0.7
UPPER_AGAIN = False  # --upper-again
TOLERANCE = 2
SERIES = ("ours", "ref", "closure", "ear_ratio", "gaze_series", "ours_confirmed",
          "ref_confirmed")  # only in --json
IBUG_EYES = ((36, 37, 38, 39, 40, 41), (42, 43, 44, 45, 46, 47))
IBUG_BROWS = ((17, 18, 19, 20, 21), (22, 23, 24, 25, 26))  # (image left, image right)


def brow_raise(points: np.ndarray) -> np.ndarray:
    """(N,) the brows' mean height above the eyes' corners (iBUG-68 points (N, 68, 2)),
    perpendicular to the line joining the eyes' outer corners, over the inter-ocular distance
    (scale and roll free), both sides averaged."""
    a, b = points[:, 36], points[:, 45]
    axis = b - a
    iod = np.linalg.norm(axis, axis=-1)
    up = np.stack([axis[:, 1], -axis[:, 0]], -1) / iod[:, None]  # up in the image
    out = []
    for brow, eye in zip(IBUG_BROWS, IBUG_EYES, strict=True):
        corners = points[:, [eye[0], eye[3]]].mean(axis=1)
        h = ((points[:, list(brow)].mean(axis=1) - corners) * up).sum(-1)
        out.append(h / iod)
    return np.mean(out, axis=0)


MP_IRIS = ((473, 362, 263), (468, 133, 33))  # (iris centre, corners) per eye, mediapipe 478


def iris_offsets(points: np.ndarray) -> np.ndarray:
    """(N, 2) the iris centre's offset from the middle of its eye's corners, along the
    corners' axis (to the image's right) and across it (up), over the eye's width, both eyes
    averaged, from mediapipe's refined FaceMesh points (N, 478, 2) px; NaN where none."""
    out = []
    for c, a, b in MP_IRIS:
        pa, pb = points[:, a], points[:, b]
        swap = (pa[:, 0] > pb[:, 0])[:, None]
        lo, hi = np.where(swap, pb, pa), np.where(swap, pa, pb)
        axis = hi - lo
        width = np.linalg.norm(axis, axis=-1)
        u = axis / width[:, None]
        v = np.stack([u[:, 1], -u[:, 0]], -1)  # up in the image
        d = points[:, c] - (lo + hi) / 2.0
        out.append(np.stack([(d * u).sum(-1), (d * v).sum(-1)], -1) / width[:, None])
    with warnings.catch_warnings():  # (frames without a face: NaN)
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(out, axis=0)


def gaze_vs_iris(gaze: np.ndarray, ref: np.ndarray) -> dict:
    """The correlation of articast's gaze (N, 2: yaw, pitch deg, NaN where none) with the
    reference's iris offsets (N, 2) over the frames where both are given."""
    both = np.all(np.isfinite(gaze), 1) & np.all(np.isfinite(ref), 1)
    rs = [float(np.corrcoef(gaze[both, k], ref[both, k])[0, 1])
          if both.sum() > 10 and np.std(gaze[both, k]) > 0 and np.std(ref[both, k]) > 0
          else None for k in range(2)]
    return {"vs_iris_r": [None if r is None else round(r, 3) for r in rs],
            "vs_iris_frames": int(both.sum()),
            "ref_sd": np.nanstd(ref, axis=0).round(4).tolist() if np.isfinite(ref).any()
            else None}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def ear(points: np.ndarray) -> np.ndarray:
    """(N,) mean eye aspect ratio of both eyes from iBUG-68 points (N, 68, 2)."""
    out = []
    for e in IBUG_EYES:
        p = points[:, e]
        v = (np.linalg.norm(p[:, 1] - p[:, 5], axis=-1) + np.linalg.norm(p[:, 2] - p[:, 4],
                                                                         axis=-1))
        out.append(v / (2.0 * np.linalg.norm(p[:, 0] - p[:, 3], axis=-1)))
    return np.mean(out, axis=0)


def match(ours: list[tuple[int, int]], ref: list[tuple[int, int]], tol: int = TOLERANCE,
          one_to_one: bool = False) -> tuple[float | None, float | None, list[int]]:
    """precision, recall, onsets (ours - ref) of the matched pairs (by overlap, or one to
    one: :func:`~articast.core.evaluation.upper.match_events`)."""
    return match_events(ours, ref, tol, one_to_one)


def track(speaker, held, fps, cost: bool = True):
    """The tracked frames and their cost: the whole frame's, the upper face's own step
    (timed inside the run) and the upper face's whole cost over the lips alone
    (:func:`~real_clips.cost_over_lips`, the first pair's full run this one)."""
    kernels.warm_up()
    live = LiveTracker(speaker, FaceFinder.load(threads=1), mediapipe_scheme(speaker.rig),
                       peers_mod.ARTICAST_POLICY, clock=time.perf_counter)
    step = live.upper.step
    spent = {"wall": 0.0, "cpu": 0.0}

    def timed(*a, **k):
        w0, c0 = time.perf_counter(), time.process_time()
        out = step(*a, **k)
        spent["wall"] += time.perf_counter() - w0
        spent["cpu"] += time.process_time() - c0
        return out

    live.upper.step = timed  # type: ignore[method-assign]
    w0, c0 = time.perf_counter(), time.process_time()
    res = [live.track(f, i / fps) for i, f in enumerate(held)]
    n = max(len(held), 1)
    cpu = (time.process_time() - c0) * 1e3 / n
    return res, {"frame_ms": (time.perf_counter() - w0) * 1e3 / n, "frame_cpu_ms": cpu,
                 "upper_ms": spent["wall"] * 1e3 / n, "upper_cpu_ms": spent["cpu"] * 1e3 / n,
                 **(cost_over_lips(speaker, held, fps, first=cpu, policy=peers_mod.ARTICAST_POLICY)
                    if cost else {}), "eye_reads": live.eye_reads}


def grid(path: Path, held, closure, ratio, ours, ref, eyes, per_row: int = 7,
         tile: int = 120, most: int = 60) -> None:
    """A row per event (both methods' events, overlapping ones merged): the frames from 2
    before its onset, the upper face (centred on the reference's eye points where it has
    them), labelled with articast's closure (yellow above 0.5) and the EAR ratio (red below
    EAR_FRACTION); the row's first tile says which method saw the event."""
    rows = []
    for s, e in events(np.isin(np.arange(len(held)), [i for a, b in ours + ref
                                                      for i in range(a, b)]), merge=0)[:most]:
        who = ("both" if any(a < e and s < b for a, b in ours) and any(
            a < e and s < b for a, b in ref) else "articast" if any(
            a < e and s < b for a, b in ours) else "reference")
        tiles = []
        for i in range(s - 2, s + per_row - 2):
            if not 0 <= i < len(held):
                tiles.append(np.zeros((tile, tile, 3), np.uint8))
                continue
            img = held[i]
            h, w = img.shape[:2]
            c = eyes[min(max(i, s), e - 1)]
            cx, cy = (int(c[0]), int(c[1])) if np.all(np.isfinite(c)) else (w // 2,
                                                                             int(0.35 * h))
            half = int(0.15 * w)
            pad = cv2.copyMakeBorder(img, half, half, half, half, cv2.BORDER_CONSTANT)
            crop = pad[cy:cy + 2 * half, cx:cx + 2 * half]
            t = cv2.resize(crop, (tile, tile))
            c_i = closure[i]
            cv2.putText(t, f"{i} c{'-' if not np.isfinite(c_i) else f'{c_i:.2f}'}", (3, 14), 0,
                        0.45, (0, 255, 255) if np.isfinite(c_i) and c_i > 0.5 else
                        (255, 255, 255), 1)
            cv2.putText(t, f"ear {ratio[i]:.2f}", (3, tile - 6), 0, 0.45,
                        (0, 0, 255) if ratio[i] < EAR_FRACTION else (255, 255, 255), 1)
            if i == s - 2:
                cv2.putText(t, who, (3, 32), 0, 0.45, (0, 255, 0), 1)
            tiles.append(t)
        rows.append(np.hstack(tiles))
    if rows:
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 75])


def run(name: str, path: Path, peers: dict, grid_dir: Path | None, cost: bool = True) -> dict:
    log(f"{name}: reading")
    enrol, held, fps, n, times = read_clip(path)
    log(f"{name}: enrolling on {len(enrol)} frames (or loading it from --speakers)")
    speaker = peers_mod.enrolled(name, lambda: enrol_speaker(
        enrol, fps, max_frames=None, times=times, reader_keep_roi=peers_mod.reader_crop()),
        "v1")
    if UPPER_AGAIN:  # (read as the live reader reads: its crop)
        log(f"{name}: the upper face's references again, from the enrolment frames")
        fu = (peers_mod.ARTICAST_POLICY or LivePolicy()).fusion
        speaker = upper_again(speaker, enrol, fu)
    log(f"{name}: tracking {len(held)} held-out frames")
    res, cost_ = track(speaker, held, fps, cost)
    cl = np.array([np.nan if r.upper is None or not r.upper.eyes_ok
                   else (r.upper.closure_left + r.upper.closure_right) / 2.0 for r in res])
    src = [None if r.upper is None else r.upper.source for r in res]
    out = {"clip": name, "frames": len(held), "fps": fps,
           "upper": speaker.report.get("upper"),
           **{k: round(v, 3) if isinstance(v, float) else v for k, v in cost_.items()},
           "eyes_ok": round(float(np.isfinite(cl).mean()), 4),
           "photo_frames": int(sum(s == "photo" for s in src))}
    gaze = np.array([(r.upper.gaze_yaw_deg, r.upper.gaze_pitch_deg)
                     if r.upper is not None and r.upper.eyes_ok
                     and r.upper.gaze_yaw_deg is not None else (np.nan, np.nan)
                     for r in res], float).reshape(-1, 2)
    gz = gaze[np.isfinite(gaze[:, 0])]
    # no gaze truth on real clips: how often a gaze is given, and its spread (a sanity check)
    out["gaze"] = {"frames": round(len(gz) / max(len(res), 1), 4),
                   "median_deg": np.median(gz, axis=0).round(2).tolist() if len(gz) else None,
                   "iqr_deg": (np.percentile(gz, 75, axis=0) - np.percentile(gz, 25, axis=0)
                               ).round(2).tolist() if len(gz) else None}
    if "mediapipe" in peers:
        log(f"{name}: mediapipe's iris on the same frames")
        try:
            iris = worker_points("mediapipe_iris", peers["mediapipe"], held)
        except KeyError:  # (no face in any frame: the scheme has no NaN template)
            iris = {"error": "mediapipe found no face"}
        out["gaze"].update(gaze_vs_iris(gaze, iris_offsets(iris["points"])) if "points"
                           in iris else {"vs_iris_r": iris["error"]})
        out["gaze_series"] = [[None if not np.isfinite(v) else round(float(v), 2) for v in g]
                              for g in gaze]
    ours = blink_events(np.nan_to_num(cl) > BLINK_CLOSURE, fps)
    out["articast_events"] = len(ours)
    if "dlib" not in peers:
        out["reference"] = "dlib is not set up (benchmarks/setup_peers.py)"
        return out
    log(f"{name}: dlib on the same frames")
    got = worker_points("dlib", peers["dlib"], held)
    if "error" in got:
        out["reference"] = got["error"]
        return out
    e = ear(got["points"])
    ratio = e / np.nanmedian(e)
    ref = blink_events(np.nan_to_num(ratio, nan=1.0) < EAR_FRACTION, fps)
    prec, rec, onsets = match(ours, ref)
    ours_c, ref_c = confirmed(name, ours, ref)
    prec_c, rec_c, _ = match(ours_c, ref_c)
    prec_1, rec_1, _ = match(ours, ref, one_to_one=True)
    both = np.isfinite(cl) & np.isfinite(e)
    br = np.array([np.nan if r.upper is None or not r.upper.brows_ok else
                   (r.upper.brows_dict()["raise_left_mm"] + r.upper.brows_dict()["raise_right_mm"])
                   / 2.0 for r in res])
    ref_br = brow_raise(got["points"])
    both_b = np.isfinite(br) & np.isfinite(ref_br)
    out["brows_vs_dlib_r"] = (float(np.corrcoef(br[both_b], ref_br[both_b])[0, 1])
                              if both_b.sum() > 10 and np.std(br[both_b]) > 0 else None)
    out.update({"reference_events": len(ref), "precision": prec, "recall": rec,
                "precision_one_to_one": prec_1, "recall_one_to_one": rec_1,
                "onset_median": float(np.median(onsets)) if onsets else None,
                "onset_within_1": (float(np.mean(np.abs(onsets) <= 1)) if onsets else None),
                "closure_vs_ear_r": float(np.corrcoef(cl[both], -e[both])[0, 1])
                if both.sum() > 10 else None,
                "ours": ours, "ref": ref, "confirmed_events": len(ref_c),
                "precision_confirmed": prec_c, "recall_confirmed": rec_c,
                "ours_confirmed": ours_c, "ref_confirmed": ref_c})
    out["closure"] = [None if not np.isfinite(v) else round(float(v), 3) for v in cl]
    out["ear_ratio"] = [None if not np.isfinite(v) else round(float(v), 3) for v in ratio]
    if grid_dir is not None:
        with warnings.catch_warnings():  # frames where dlib found no face: NaN, centred
            warnings.simplefilter("ignore", RuntimeWarning)
            eyes = np.nanmean(got["points"][:, 36:48], axis=1)
        grid(grid_dir / f"{name}.jpg", held, cl, ratio, ours, ref, eyes)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE)
    ap.add_argument("--peers", type=Path, default=PEER_CACHE)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--grid", type=Path)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--speakers", type=Path, help="keep and reuse the enrolments here (as "
                                                  "benchmarks/peers.py --speakers: the same)")
    ap.add_argument("--no-cost", action="store_true",
                    help="skip the upper face's cost over the lips alone (3 interleaved "
                         "pairs of runs): the accuracy alone, ~4x faster")
    ap.add_argument("--upper-again", action="store_true",
                    help="with --speakers: compute each stored enrolment's upper-face "
                         "references again with this code, from its enrolment frames (the "
                         "eyes' calibration changed; the rest of the enrolment did not)")
    peers_mod.add_articast_options(ap)
    args = ap.parse_args(argv)
    global UPPER_AGAIN
    UPPER_AGAIN = args.upper_again
    peers_mod.use_articast_options(args)
    if peers_mod.READERS != 1:  # (core/faces/two_readers.py: the eyes are the first's)
        ap.error("--readers: the eyes of two readers' stream are the first tracker's, "
                 "which this script measures already")
    peers_mod.SPEAKERS = args.speakers
    cv2.setNumThreads(1)
    clips = clip_paths(args.clips)
    peers = load_peers(args.peers)
    rows = []
    for name in args.only or list(clips):
        if name not in clips:
            log(f"{name}: no such clip in {args.clips}")
            continue
        try:
            row = run(name, clips[name], peers, args.grid, cost=not args.no_cost)
        except InputError as e:  # (a clip the enrolment refuses: no face in enough frames)
            row = {"clip": name, "error": str(e)}
        rows.append(row)
        short = {k: v for k, v in row.items() if k not in SERIES}
        log(json.dumps(short))
    print(json.dumps(rows, indent=1) if args.json else "\n".join(
        json.dumps({k: v for k, v in r.items() if k not in SERIES}) for r in rows))


if __name__ == "__main__":
    main()

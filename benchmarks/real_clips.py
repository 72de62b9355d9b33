"""Real faces: enrol on the first part of each clip, track the held-out rest, and compare with
the landmark model run on every frame (an independent method), in the same run.

    python tools/fetch_real_clips.py            # once: the clips into ~/.cache/articast/clips
    python benchmarks/real_clips.py --json [--grid docs/real_clips]

Per clip (held-out frames only):
- ``ok``: fraction of frames the tracker marks ok;
- ``aperture_r``: correlation of the tracker's lip aperture with the landmarks', both as a
  fraction of the same method's outer lip width (the landmarks: inner-lip midpoints 13-14
  over corners 61-291, image px; the tracker: ``lips.aperture_mm`` over the fitted model's
  outer corners 8.3-8.4). The ratio is what the image shows without a scale; comparing the
  tracker's mm with the landmarks' ratio (``aperture_mm_r``, the figure before) mixed in the
  lips' width changes (spread and rounded lips, a laugh);
- ``jitter_pct_width``: RMS of the aperture about its linear trend inside the still windows,
  in % of the outer lip width, for the tracker and for the landmark model; the windows are the
  10 % of 0.4 s windows where the mouth's image changes least (chosen from pixels, not from
  either method's output);
- speed: ms per frame of the whole live path (tracker + its landmark calls) against the
  landmark model alone on every frame, one thread each, frames upscaled to 640x480 (the clips
  are 360x288 and 400x300; a webcam gives 640x480), and their ratio (target <= 0.7).

A grid of held-out frames with the fitted mesh drawn on them is written with ``--grid DIR``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from face_landmarks_clips import (  # noqa: E402
    aperture,
    jitter,
    mouth_motion,
    still_windows,
    window_frames,
)

from articast.core.faces.build import BuildOptions, build_speaker  # noqa: E402
from articast.core.faces.enrol import DEPTHS, EnrolOptions  # noqa: E402
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.live import LivePolicy, LiveTracker  # noqa: E402
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.model.camera import Camera  # noqa: E402
from articast.core.outputs.lips import lip_measures  # noqa: E402
from articast.core.tracking import kernels  # noqa: E402

CLIPS = {  # name: (enrolment seconds, at most this many held-out seconds)
    "franck": (40.0, 60.0),
    "cap12": (25.0, 28.0),
    "cap13": (18.0, 13.0),
}
SIZE = (640, 480)


def read_frames(path: Path) -> tuple[list[np.ndarray], float]:
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(cv2.resize(f, SIZE, interpolation=cv2.INTER_LINEAR))
    cap.release()
    return frames, fps


def landmarks_every_frame(finder: FaceFinder, frames: list[np.ndarray]
                          ) -> tuple[np.ndarray, np.ndarray, float]:
    """Landmarks per frame (NaN where none), found, ms per frame (the landmark model alone,
    with its own tracking policy: detector only when lost)."""
    marks, found, prev = [], [], None
    t0 = time.perf_counter()
    for f in frames:
        face = finder.track(f, prev) if prev is not None else None
        face = face or finder.find(f)
        prev = face
        marks.append(face.landmarks if face is not None else np.full((478, 3), np.nan))
        found.append(face is not None)
    ms = (time.perf_counter() - t0) * 1000 / max(len(frames), 1)
    return np.array(marks), np.array(found), ms


def run_clip(name: str, path: Path, grid: Path | None, live_policy: LivePolicy | None = None,
             series: Path | None = None, depth: str | None = None,
             flow: bool | None = None, upper_lip_off_jaw: bool = False,
             enrol_with_held: int | None = None) -> dict:
    frames, fps = read_frames(path)
    enrol_s, test_s = CLIPS[name]
    n_enrol = int(enrol_s * fps)
    held = frames[n_enrol:n_enrol + int(test_s * fps)]
    finder = FaceFinder.load(threads=1)
    camera = Camera.default(*SIZE, 60.0)
    # enrolment: the first part, every other frame (as `articast enroll` strides long clips)
    enrol = frames[:n_enrol:2]
    marks, found, _ = landmarks_every_frame(finder, enrol)
    if enrol_with_held:  # a diagnosis, not a held-out measure: see --enrol-with-held
        extra = held[::enrol_with_held]
        more, more_found, _ = landmarks_every_frame(finder, extra)
        enrol, marks = enrol + extra, np.concatenate([marks, np.nan_to_num(more)])
        found = np.concatenate([found, more_found])
    opts = EnrolOptions(jaw_moves_upper_lip=not upper_lip_off_jaw,
                        **({"depth": depth} if depth is not None else {}))
    t0 = time.perf_counter()
    speaker = build_speaker(enrol, marks, found, mediapipe_scheme("desk"), camera, "desk", opts,
                            BuildOptions(flow=flow))
    build_s = time.perf_counter() - t0
    kernels.warm_up()
    # the landmark model alone on every held-out frame (the independent reference and the
    # speed baseline), then the live path on the same frames, in the same process
    lm, lm_found, lm_ms = landmarks_every_frame(FaceFinder.load(threads=1), held)
    live = LiveTracker(speaker, FaceFinder.load(threads=1), mediapipe_scheme("desk"),
                       live_policy, clock=time.perf_counter)
    results = []
    t0 = time.perf_counter()
    for i, f in enumerate(held):
        results.append(live.track(f, i / fps))
    live_ms = (time.perf_counter() - t0) * 1000 / max(len(held), 1)
    ok = np.array([r.ok for r in results])
    alpha = np.array([r.alpha for r in results])
    ap_mm, _ = lip_measures(speaker.model, alpha)
    m = speaker.model
    outer = np.linalg.norm(m.shape(alpha)[:, m.point("8.3")] - m.shape(alpha)[:, m.point("8.4")],
                           axis=-1)
    ap_lm = np.array([aperture(x)[0] if np.isfinite(x).all() else np.nan for x in lm])
    grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in held]
    length = window_frames(fps)
    motion = mouth_motion(grey, [x if np.isfinite(x).all() else None for x in lm], length)
    windows = still_windows(motion, length)
    both = ok & np.isfinite(ap_lm)
    out = {
        "clip": name, "fps": round(fps, 3), "enrol_frames": len(enrol),
        "held_out_frames": len(held), "ok": round(float(ok.mean()), 4),
        "reasons": _reasons(results),
        "aperture_r": round(float(np.corrcoef((ap_mm / outer)[both], ap_lm[both])[0, 1]), 4),
        "aperture_mm_r": round(float(np.corrcoef(ap_mm[both], ap_lm[both])[0, 1]), 4),
        "jitter_pct_width": {"tracker": round(jitter(np.where(ok, ap_mm / outer, np.nan),
                                                     windows), 3),
                             "landmarks": round(jitter(ap_lm, windows), 3)},
        "still_windows": len(windows),
        "ms_per_frame": {"live": round(live_ms, 2), "landmarks_every_frame": round(lm_ms, 2)},
        "speed_ratio": round(live_ms / lm_ms, 3),
        "finder_calls_per_frame": round(live.finder_calls / max(len(held), 1), 3),
        "restarts": live.restarts,
        "variance_pct": {k: round(v, 1) for k, v in speaker.report["variance_pct"].items()},
        "residual_p99": round(speaker.residual.p99, 4),
        "enrol_build_s": round(build_s, 1), "depth": opts.depth,
        "flow": speaker.report["pixels"] != "landmarks",
        "enrol_with_held": enrol_with_held,
    }
    if grid is not None:
        _write_grid(grid / f"{name}.png", held, results, speaker)
    if series is not None:  # per-frame series, to see where the two methods part
        series.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(series / f"{name}.npz", ok=ok, alpha=alpha,
                            aperture_mm=ap_mm, outer_width_mm=outer, landmarks_ratio=ap_lm,
                            inner_midpoints_mm=m.shape(alpha)[:, [m.point("2.2"),
                                                                  m.point("2.3")]],
                            fps=fps)
    return out


def _reasons(results) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in results:
        if not r.ok:
            code = r.reason.split(":", 1)[0]
            out[code] = out.get(code, 0) + 1
    return out


def _write_grid(path: Path, frames, results, speaker, n: int = 9) -> None:
    """``n`` held-out frames spread over the clip, each with the fit drawn on it as the
    product draws it (articast.service.overlay: ``track --overlay``, enroll's contact
    sheet)."""
    from articast.service.overlay import fit_tile, grid, label, lip_contours

    contours = lip_contours(speaker)
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    tiles = []
    for i in idx:
        tile = fit_tile(frames[i], speaker.model, speaker.camera, results[i], contours)
        lips = results[i].lips or {}
        tiles.append(label(tile, f"#{i} aperture {lips.get('aperture_mm', float('nan')):.1f} mm"))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), grid(tiles))


def add_enrol_options(ap: argparse.ArgumentParser) -> None:
    """The enrolment variants the real-clip and no-truth benchmarks compare."""
    ap.add_argument("--depth", choices=list(DEPTHS), default=None,
                    help="enrolment depth option (default: the enrolment's default)")
    ap.add_argument("--flow", action=argparse.BooleanOptionalAction, default=None,
                    help="enrol with (--flow) or without (--no-flow) the landmarks' pixels "
                         "refined by optical flow (default: the rig's, core/faces/flow.py "
                         "BY_RIG: on for head, off for desk; see docs/REAL_SPEAKERS.md)")
    ap.add_argument("--upper-lip-off-jaw", action="store_true",
                    help="enrol with the upper lip kept off jaw1's basis (EnrolOptions "
                         "jaw_moves_upper_lip=False; off by default: see docs/REAL_SPEAKERS.md)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache/articast/clips")
    ap.add_argument("--only", nargs="*", default=list(CLIPS))
    ap.add_argument("--grid", type=Path, help="write an overlay grid per clip here")
    ap.add_argument("--series", type=Path,
                    help="write each clip's per-frame series (tracker and landmarks) here")
    add_enrol_options(ap)
    ap.add_argument("--no-motion", action="store_true",
                    help="live tracking without the upper face's optical flow (LivePolicy.motion "
                         "None: the tracker predicts the head's translation by itself)")
    ap.add_argument("--enrol-with-held", type=int, metavar="N",
                    help="diagnosis: also enrol on every Nth held-out frame (so the figures "
                         "are no longer held out): how far an appearance that had seen the "
                         "test part's conditions would agree (docs/REAL_SPEAKERS.md, franck)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    live = LivePolicy(motion=None) if args.no_motion else None
    rows = []
    for name in args.only:
        path = next(iter(args.cache.glob(f"{name}.*")), None)
        if path is None:
            sys.exit(f"{name}: not in {args.cache}: run python tools/fetch_real_clips.py")
        row = run_clip(name, path, args.grid, live, series=args.series, depth=args.depth,
                       flow=args.flow, upper_lip_off_jaw=args.upper_lip_off_jaw,
                       enrol_with_held=args.enrol_with_held)
        rows.append(row)
        if not args.json:
            print(row, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

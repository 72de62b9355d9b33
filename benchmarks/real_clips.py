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
from dataclasses import replace
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

from articast.core.faces.build import (  # noqa: E402
    BuildOptions,
    analysed_frames,
    build_speaker,
    upper_reference,
    upper_report,
)
from articast.core.faces.enrol import DEPTHS, EnrolOptions  # noqa: E402
from articast.core.faces.finder import FaceFinder, read_every_frame  # noqa: E402
from articast.core.faces.live import (  # noqa: E402
    FusionPolicy,
    LivePolicy,
    LiveTracker,
    reader_finder,
)
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.faces.speaker import Speaker  # noqa: E402
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
        marks.append(face.landmarks if face is not None else None)
        found.append(face is not None)
    ms = (time.perf_counter() - t0) * 1000 / max(len(frames), 1)
    # NaN where no face, as many points as the model gives (478 for v2, 468 for FaceMesh v1)
    shape = next((m.shape for m in marks if m is not None), (478, 3))
    return (np.array([m if m is not None else np.full(shape, np.nan) for m in marks]),
            np.array(found), ms)


def found_faces(finder: FaceFinder, frames: list[np.ndarray]) -> list:
    """The finding landmarks on each frame as an enrolment reads them (tracked from the
    previous frame's face, searched for where that fails); None where no face is found."""
    faces, prev = [], None
    for f in frames:
        face = finder.track(f, prev) if prev is not None else None
        prev = face = face or finder.find(f)
        faces.append(face)
    return faces


def upper_again(speaker: Speaker, frames: list[np.ndarray],
                fusion: FusionPolicy | None = None) -> Speaker:
    """A stored enrolment (``--speakers``) with its upper-face references computed again by
    the current code from its enrolment ``frames`` (as ``enrol_speaker`` gave them: the
    reader's readings of the same frames, cropped as ``fusion``'s reader crops, default
    :class:`FusionPolicy`'s; ``build.upper_reference``): an experiment on the eyes'
    calibration need not build the whole speaker again. Desk speakers only."""
    if speaker.rig != "desk":
        return speaker
    faces = found_faces(FaceFinder.load(threads=1), frames)
    readings = read_every_frame(reader_finder(fusion), frames, faces)
    upper = upper_reference(frames, readings)
    return replace(speaker, upper=upper,
                   report={**speaker.report, "upper": upper_report(upper)})


def enrol_speaker(frames: list[np.ndarray], fps: float, *, camera: Camera | None = None,
                  rig: str = "desk", max_frames: int | None = 600,
                  finder: FaceFinder | None = None,
                  options: EnrolOptions | None = None, build: BuildOptions | None = None,
                  extra: list[np.ndarray] | None = None,
                  times: np.ndarray | None = None, reader: str = "v1",
                  blend: float = 0.0, reader_keep_roi: float | None = None) -> Speaker:
    """Enrol a speaker on ``frames`` (BGR, all the same size) as ``articast enroll`` does: the
    frames it analyses (:func:`~articast.core.faces.build.analysed_frames`: strided to
    ``max_frames`` plus a consecutive run; None: the frames as given, taken at ``times`` s,
    default i / fps), the bundled landmark model on each and, on a desk camera, the live
    reader (FaceMesh v1), then ``build_speaker``. ``camera``: default a 60-degree webcam at
    the frames' size. ``extra``: more frames appended to the enrolment (a diagnosis:
    --enrol-with-held). ``reader``: the live reader whose observation model is learned
    ("v1", the product's; "v2": the finding landmarks' own readings, for the benchmark's
    ``reader_v2`` ablation). ``blend`` (a diagnosis, not the product; desk only): the model is
    built from (1 - blend) x the finding landmarks + blend x the reader's on the frames both
    read (their x, y; the finding network's iris points and depth kept), the observation
    model still learned from the reader's own readings. ``speaker.report["build_s"]`` is the
    time of ``build_speaker``. ``reader_keep_roi``: the reader's crop
    (``FusionPolicy.reader_keep_roi``; None: the default policy's), recorded in the speaker."""
    finder = finder or FaceFinder.load(threads=1)
    crop = (FusionPolicy(reader=reader) if reader_keep_roi is None
            else FusionPolicy(reader=reader, reader_keep_roi=reader_keep_roi))
    h, w = frames[0].shape[:2]
    camera = camera or Camera.default(w, h, 60.0)
    if max_frames is not None:
        idx = analysed_frames(len(frames), max_frames)
        enrol, at = [frames[i] for i in idx], idx / fps
    else:
        enrol = list(frames)
        at = np.arange(len(enrol)) / fps if times is None else np.asarray(times, float)
    if extra:
        enrol = enrol + list(extra)
        at = np.concatenate([at, at[-1] + (1 + np.arange(len(extra))) * 1000.0])
    faces = found_faces(finder, enrol)
    found = np.array([f is not None for f in faces])
    marks = np.array([f.landmarks if f is not None else np.full((478, 3), np.nan)
                      for f in faces])
    readings = None
    if rig == "desk":
        readings = (marks if reader == "v2" else
                    read_every_frame(reader_finder(crop), enrol, faces))
    if blend and readings is not None:
        both = found & np.isfinite(readings[:, :, :2]).all(axis=(1, 2))
        n = readings.shape[1]  # (marks is this function's own array: mixed in place)
        marks[both, :n, :2] = ((1.0 - blend) * marks[both, :n, :2]
                               + blend * readings[both, :, :2])
    t0 = time.perf_counter()
    speaker = build_speaker(enrol, marks, found, mediapipe_scheme(rig), camera, rig,
                            options or EnrolOptions(), build or BuildOptions(),
                            readings=readings, reader=reader, times=at,
                            reader_keep_roi=(crop.reader_keep_roi if readings is not None
                                             and reader != "v2" else None))
    speaker.report["build_s"] = time.perf_counter() - t0
    speaker.report["enrol_frames"] = len(enrol)
    return speaker


def track_live(speaker: Speaker, frames: list[np.ndarray], fps: float, *,
               live_policy: LivePolicy | None = None, finder: FaceFinder | None = None,
               t0: float = 0.0) -> tuple[list, float, LiveTracker]:
    """Track ``frames`` live (one thread, the speaker's rig): the per-frame results, the mean
    ms per frame of the whole live path (its landmark calls and optical flow included; the
    numba kernels are warmed up first, outside the timing) and the tracker (for its
    ``finder_calls``, ``restarts``)."""
    kernels.warm_up()
    live = LiveTracker(speaker, finder or FaceFinder.load(threads=1),
                       mediapipe_scheme(speaker.rig), live_policy, clock=time.perf_counter)
    results = []
    start = time.perf_counter()
    for i, f in enumerate(frames):
        results.append(live.track(f, t0 + i / fps))
    ms = (time.perf_counter() - start) * 1000 / max(len(frames), 1)
    return results, ms, live


def cost_over_lips(speaker: Speaker, frames: list[np.ndarray], fps: float,
                   repeats: int = 3, first: float | None = None, policy=None) -> dict:
    """What the upper face costs a frame, all of it (its step, the frames read for the eyes,
    their fits), in the same run: the CPU ms per frame of the live tracker less that of the
    same tracker without the speaker's upper-face references (no eyes measured, none read
    for), the median over ``repeats`` interleaved pairs of runs, and their range. ``first``:
    a run with the upper face already made (its CPU ms per frame), used as the first pair's.
    ``policy``: the live policy (default the product's)."""
    kernels.warm_up()
    lips_only = replace(speaker, upper=None)

    def cpu_ms(sp: Speaker) -> float:
        live = LiveTracker(sp, FaceFinder.load(threads=1), mediapipe_scheme(sp.rig), policy)
        c0 = time.process_time()
        for i, f in enumerate(frames):
            live.track(f, i / fps)
        return (time.process_time() - c0) * 1e3 / max(len(frames), 1)

    over = []
    for k in range(repeats):
        full = first if k == 0 and first is not None else cpu_ms(speaker)
        over.append(full - cpu_ms(lips_only))
    return {"over_lips_cpu_ms": round(float(np.median(over)), 3),
            "over_lips_spread_ms": [round(min(over), 3), round(max(over), 3)]}


def outer_width_mm(model, alpha: np.ndarray) -> np.ndarray:
    """Outer lip width (mm) of the fitted geometry: the corners 8.3-8.4, per frame."""
    g = model.shape(alpha)
    return np.linalg.norm(g[:, model.point("8.3")] - g[:, model.point("8.4")], axis=-1)


def run_clip(name: str, path: Path, grid: Path | None, live_policy: LivePolicy | None = None,
             series: Path | None = None, depth: str | None = None,
             flow: bool | None = None, upper_lip_off_jaw: bool = False,
             enrol_with_held: int | None = None) -> dict:
    frames, fps = read_frames(path)
    enrol_s, test_s = CLIPS[name]
    n_enrol = int(enrol_s * fps)
    held = frames[n_enrol:n_enrol + int(test_s * fps)]
    camera = Camera.default(*SIZE, 60.0)
    # enrolment: the frames of the first part `articast enroll` would analyse;
    # --enrol-with-held is a diagnosis, not a held-out measure
    opts = EnrolOptions(jaw_moves_upper_lip=not upper_lip_off_jaw,
                        **({"depth": depth} if depth is not None else {}))
    speaker = enrol_speaker(frames[:n_enrol], fps, camera=camera, options=opts,
                            build=BuildOptions(flow=flow),
                            extra=held[::enrol_with_held] if enrol_with_held else None)
    build_s = speaker.report["build_s"]
    # the landmark model alone on every held-out frame (the independent reference and the
    # speed baseline), then the live path on the same frames, in the same process
    kernels.warm_up()
    lm, lm_found, lm_ms = landmarks_every_frame(FaceFinder.load(threads=1), held)
    results, live_ms, live = track_live(speaker, held, fps, live_policy=live_policy)
    ok = np.array([r.ok for r in results])
    alpha = np.array([r.alpha for r in results])
    ap_mm, _ = lip_measures(speaker.model, alpha)
    m = speaker.model
    outer = outer_width_mm(m, alpha)
    ap_lm = np.array([aperture(x)[0] if np.isfinite(x).all() else np.nan for x in lm])
    grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in held]
    length = window_frames(fps)
    motion = mouth_motion(grey, [x if np.isfinite(x).all() else None for x in lm], length)
    windows = still_windows(motion, length)
    both = ok & np.isfinite(ap_lm)
    out = {
        "clip": name, "fps": round(fps, 3), "enrol_frames": speaker.report["enrol_frames"],
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
                         "BY_RIG: on for head, off for desk; see "
                         "docs/history/REAL_SPEAKERS_LOG.md)")
    ap.add_argument("--upper-lip-off-jaw", action="store_true",
                    help="enrol with the upper lip kept off jaw1's basis (EnrolOptions "
                         "jaw_moves_upper_lip=False; off by default: see "
                         "docs/history/REAL_SPEAKERS_LOG.md)")


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
    ap.add_argument("--no-fusion", action="store_true",
                    help="the appearance fit alone, landmarks only to find, check and restart "
                         "(LivePolicy.fusion None: the live path before issue 18)")
    ap.add_argument("--enrol-with-held", type=int, metavar="N",
                    help="diagnosis: also enrol on every Nth held-out frame (so the figures "
                         "are no longer held out): how far an appearance that had seen the "
                         "test part's conditions would agree "
                         "(docs/history/REAL_SPEAKERS_LOG.md, franck)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    live = LivePolicy(**({"motion": None} if args.no_motion else {}),
                      **({"fusion": None} if args.no_fusion else {}))
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

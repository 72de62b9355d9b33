"""The fused tracker's ablation: each part of the per-frame estimate taken out in turn, on every
real clip that can be enrolled, in one process (docs/TRACKING.md, "Fused live tracking").

    python tools/fetch_real_clips.py
    python benchmarks/fusion_ablation.py [--only CLIP ...] [--variants V ...] [--json]

Each clip is read as ``benchmarks/peers.py`` reads it (640 px wide, enrolled on the first 60 %
as ``articast enroll`` would analyse it, scored on the remaining 40 %); articast is enrolled
once per clip, then every variant of ``peers.VARIANTS`` tracks the held-out frames. The
reference is the median of the two bundled landmark networks run on every held-out frame
(FaceLandmarker v2 and FaceMesh v1, each in its own loop): ``r`` is each variant's aperture
ratio against it, ``jitter`` the still-mouth jitter (% of the outer width, windows chosen
from the pixels), ``lag`` the cross-correlation peak (frames, positive late), ``ok`` the
fraction of frames ok with the reasons of the others, ``x_v1`` the variant's wall time over
the FaceMesh v1 loop's on the same frames (noisy on a shared machine: the peer benchmark's
CPU ratio is the reference). Clips too short to enrol from (< 8 s of enrolment) are skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from face_landmarks_clips import aperture, jitter, mouth_motion, still_windows, window_frames  # noqa: E402,I001
from peers import CLIP_CACHE, VARIANTS, clip_paths, read_clip  # noqa: E402
from real_clips import enrol_speaker, landmarks_every_frame, outer_width_mm, track_live  # noqa: E402

from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.outputs.lips import lip_measures  # noqa: E402

MIN_ENROL_S = 8.0


def _r(a: np.ndarray, b: np.ndarray) -> float:
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[both], b[both])[0, 1]) if both.sum() > 10 else float("nan")


def _lag(a: np.ndarray, b: np.ndarray, span: int = 5) -> int:
    both = np.isfinite(a) & np.isfinite(b)
    x = np.where(both, a - np.nanmean(a), 0.0)
    y = np.where(both, b - np.nanmean(b), 0.0)
    cc = [float(np.sum(x[max(0, s):len(x) + min(0, s)] * y[max(0, -s):len(y) + min(0, -s)]))
          for s in range(-span, span + 1)]
    return int(np.argmax(cc)) - span


def run_clip(name: str, path: Path, variants: list[str]) -> dict:
    enrol, held, fps, _, times = read_clip(path)
    if len(times) < 2 or times[-1] - times[0] < MIN_ENROL_S:
        return {"clip": name, "skipped": f"{times[-1] - times[0] if len(times) else 0:.1f} s "
                                         f"to enrol from (< {MIN_ENROL_S:g} s)"}
    speaker = enrol_speaker(enrol, fps, max_frames=None, times=times)
    v2, _, ms_v2 = landmarks_every_frame(FaceFinder.load(threads=1), held)
    v1, _, ms_v1 = landmarks_every_frame(FaceFinder.load(threads=1, landmarks="v1"), held)
    ratio = {k: np.array([aperture(x)[0] if np.isfinite(x).all() else np.nan for x in m])
             for k, m in (("v2", v2), ("v1", v1))}
    reference = np.nanmedian(np.vstack([ratio["v2"], ratio["v1"]]), 0)
    grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in held]
    length = window_frames(fps)
    windows = still_windows(mouth_motion(grey, [x if np.isfinite(x).all() else None
                                                for x in v2], length), length)
    row: dict = {"clip": name, "held_out_frames": len(held), "still_windows": len(windows),
                 "landmarks": {k: {"r_v2_v1": round(_r(ratio["v2"], ratio["v1"]), 3),
                                   "jitter": round(jitter(ratio[k], windows), 3)}
                               for k in ("v2", "v1")},
                 "ms_v1_loop": round(ms_v1, 2), "ms_v2_loop": round(ms_v2, 2), "variants": {}}
    for v in variants:
        results, ms, live = track_live(speaker, held, fps, live_policy=VARIANTS[v])
        ok = np.array([r.ok for r in results])
        alpha = np.array([r.alpha for r in results])
        ap_mm, _ = lip_measures(speaker.model, alpha)
        ours = np.where(ok, ap_mm / outer_width_mm(speaker.model, alpha), np.nan)
        reasons: dict[str, int] = {}
        for r in results:
            if not r.ok:
                code = r.reason.split(":", 1)[0]
                reasons[code] = reasons.get(code, 0) + 1
        row["variants"][v] = {"ok": round(float(ok.mean()), 3), "reasons": reasons,
                              "r": round(_r(ours, reference), 3),
                              "jitter": round(jitter(ours, windows), 3),
                              "lag": _lag(ours, reference),
                              "x_v1": round(ms / ms_v1, 2),
                              "reader_calls_per_frame": round(live.finder_calls / len(held), 2)}
        print(f"[ablation] {name} {v}: {row['variants'][v]}", file=sys.stderr, flush=True)
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    clips = clip_paths(args.clips)
    load = {"start": [round(x, 2) for x in os.getloadavg()]}
    t0 = time.perf_counter()
    rows = [run_clip(n, clips[n], args.variants) for n in (args.only or list(clips))]
    load["end"] = [round(x, 2) for x in os.getloadavg()]
    out = {"load_average": load, "seconds": round(time.perf_counter() - t0),
           "command": " ".join(sys.argv), "clips": rows}
    if args.json:
        print(json.dumps(out, indent=1))
        return
    for row in rows:
        if "skipped" in row:
            print(f"{row['clip']}: skipped, {row['skipped']}")
            continue
        lm = row["landmarks"]
        print(f"{row['clip']}: v2 jitter {lm['v2']['jitter']}, v1 jitter {lm['v1']['jitter']}")
        for v, s in row["variants"].items():
            print(f"  {v:13s} ok {s['ok']:.3f} r {s['r']:.3f} jitter {s['jitter']:.3f} "
                  f"lag {s['lag']} x_v1 {s['x_v1']:.2f} {s['reasons']}")
    print(f"load average {load}")


if __name__ == "__main__":
    main()

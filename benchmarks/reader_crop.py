"""Which crop the live reader (FaceMesh v1) reads the lips best in: its crop's side over the
landmarks' extent, on the held-out frames of every clip, scored as benchmarks/peers.py scores
(lip-aperture r against the consensus of the other trackers; still-mouth jitter, % of the
mouth width, in the same still windows). The consensus leaves out FaceMesh v1 and articast
(which reads through FaceMesh v1): it is FaceLandmarker v2's, OpenSeeFace's, mediapipe's and
dlib's median, from a peers run's saved series.

    python benchmarks/peers.py --json --series /tmp/series       # once: the peers' series
    python benchmarks/reader_crop.py --series /tmp/series [--scales 1.2 1.35 1.5 1.7]

One thread; every frame read in a crop re-grown from its last reading (MediaPipe's loop).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402
from face_landmarks_clips import box_motion, jitter, still_windows, window_frames  # noqa: E402
from real_clips import landmarks_every_frame  # noqa: E402

from articast.core.faces.finder import FaceFinder, FinderPolicy  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--series", type=Path, required=True,
                    help="the folder `peers.py --series` wrote (the other trackers' series)")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.2, 1.35, 1.5, 1.7])
    ap.add_argument("--only", nargs="*", help="clips (default: every clip with a series)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    paths = peers.clip_paths(peers.CLIP_CACHE)
    names = args.only or [p.stem for p in sorted(args.series.glob("*.npz")) if p.stem in paths]
    v1 = peers.facemesh_v1_finder(peers.models_dir() / "face_landmarks_v1.onnx")
    out = {}
    for name in names:
        z = np.load(args.series / f"{name}.npz")
        methods = [str(m) for m in z["methods"]]
        others = {m: z[f"ratio_{m}"] for m in methods if m not in ("articast", "facemesh_v1")}
        if len(others) < 2:
            continue
        _, held, fps, _, _ = peers.read_clip(paths[name])
        cons = peers.consensus(others)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            box = np.nanmedian(np.array([z[f"box_{m}"] for m in others]), 0)
        grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in held]
        length = window_frames(fps)
        windows = still_windows(box_motion(grey, [b if np.isfinite(b).all() else None
                                                  for b in box], length), length)
        row = {}
        for s in args.scales:
            finder = FaceFinder(v1.detector_session, v1.landmarks_session,
                                FinderPolicy(scale=s, refine=0, keep_roi=0.0))
            marks, found, _ = landmarks_every_frame(finder, held)
            ratio = peers.aperture_ratio(marks[:, :, :2], "mediapipe")
            row[str(s)] = {"r": peers._round(peers.pearson(ratio, cons)[0], 4),
                           "jitter_pct_width": peers._round(jitter(ratio, windows), 3),
                           "found": peers._round(float(np.mean(found)), 3)}
        out[name] = row
        print(name, " | ".join(f"{s}: r {v['r']} jitter {v['jitter_pct_width']}"
                               for s, v in row.items()), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

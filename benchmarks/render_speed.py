"""Frames per second of the synthetic speaker's renderer (single thread), printed as JSON.

    python benchmarks/render_speed.py [--frames 100] [--size 640x480] [--rig head|desk|both]

Renders a real talking sequence (articulation + scene + rasterisation + texture + noise) and
reports the mean and median time per frame and frames per second per rig.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from articast.core.synthetic import RenderOptions, default_speaker, make_sequence  # noqa: E402


def bench(rig: str, frames: int, size: tuple[int, int]) -> dict:
    speaker = default_speaker(0)
    seq = make_sequence(0, frames, 50.0, rig, size=size, geometry=speaker.geometry)
    opts = [RenderOptions(noise_sigma=2.0, seed=i) for i in range(frames)]
    speaker.render(seq.controls[0], seq.pose(0), seq.camera, opts[0])  # textures, caches
    times = []
    for i in range(frames):
        t0 = time.perf_counter()
        speaker.render(seq.controls[i], seq.pose(i), seq.camera, opts[i])
        times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    return {"rig": rig, "frames": frames, "size": f"{size[0]}x{size[1]}",
            "ms_mean": round(float(ms.mean()), 2), "ms_median": round(float(np.median(ms)), 2),
            "ms_p95": round(float(np.percentile(ms, 95)), 2),
            "fps_mean": round(float(1e3 / ms.mean()), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--rig", choices=("head", "desk", "both"), default="both")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    size = tuple(int(v) for v in args.size.split("x"))
    rigs = ("head", "desk") if args.rig == "both" else (args.rig,)
    out = {"benchmark": "render_speed", "python": platform.python_version(),
           "numpy": np.__version__, "opencv": cv2.__version__, "threads": 1,
           "results": [bench(r, args.frames, size) for r in rigs]}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()

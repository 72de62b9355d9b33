"""Tracking speed at 640x480 on one core: the default optimiser (Gauss-Newton/LM) and the
paper's Nelder-Mead baseline on the same frames, so their ratio is measured in one run;
memory per tracker. Video decoding and rendering are excluded (frames are pre-rendered), and
so is the one-off compilation of the cost kernel (warmed up first); the numpy reference path
of the cost runs on the same frames too, so the kernel's gain is a ratio from one run; and so
does the compiled kernels' path with each Gauss-Newton evaluation assembled in numpy around
them (``fitting.FIT_TERMS`` off), the gain of ``kernels.fit_terms`` and the compiled LM step.

    python benchmarks/tracking_speed.py [--frames 150] [--nm-frames 40] [--repeats 3]

The timings are repeated ``--repeats`` times on the same frames (Gauss-Newton, Nelder-Mead and
the numpy path interleaved in each repeat), so each ratio comes with its spread over repeats;
the machine's load average before and after is in the output (the figures move with it on a
shared machine). Prints one JSON object.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--nm-frames", type=int, default=40)
    ap.add_argument("--kind", default="la_lin")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3,
                    help="timing repeats on the same frames, for the spread (default 3)")
    args = ap.parse_args()
    from common import load_average

    load_before = load_average()
    cv2.setNumThreads(1)

    from articast.core.appearance.models import TrainingFrame, train_appearance
    from articast.core.evaluation.measures import rms_3d
    from articast.core.model.build import invert
    from articast.core.synthetic import RenderOptions, default_speaker, make_sequence
    from articast.core.tracking.tracker import Tracker, TrackingPolicy

    sp = default_speaker(args.seed)
    model = sp.model()
    tr = make_sequence(args.seed * 100 + 1, 75, 6.0, "head")
    a_tr = invert(model, tr.points)
    app = train_appearance(model, tr.camera, [
        TrainingFrame(sp.render(tr.controls[i], tr.pose(i), tr.camera, RenderOptions(seed=i)),
                      a_tr[i], tr.pose(i)) for i in range(tr.n_frames)], args.kind)
    te = make_sequence(args.seed * 100 + 2, args.frames, 50.0, "head")
    imgs = [sp.render(te.controls[i], te.pose(i), te.camera, RenderOptions(seed=900 + i))
            for i in range(te.n_frames)]
    a_true = invert(model, te.points)

    def memory(policy: TrackingPolicy, n: int = 10) -> float:
        """Peak Python heap (MiB) of a tracker over n frames (traced apart: tracing is slow)."""
        tracemalloc.start()
        tracker = Tracker(model, app, te.camera, policy)
        tracker.reset(te.pose(0), a_true[0])
        for i in range(n):
            tracker.track(imgs[i], float(te.times[i]))
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return peak / 2**20

    def run(policy: TrackingPolicy, n: int, heap: bool = True) -> dict:
        tracker = Tracker(model, app, te.camera, policy, clock=time.perf_counter)
        tracker.reset(te.pose(0), a_true[0])
        res = []
        t0 = time.perf_counter()
        for i in range(n):
            res.append(tracker.track(imgs[i], float(te.times[i])))
        wall = time.perf_counter() - t0
        ms = np.array([r.ms for r in res])
        err = rms_3d(model, np.array([r.alpha for r in res]), a_true[:n])
        return {"frames": n, "fps": n / wall, "ms_per_frame_mean": float(ms.mean()),
                "ms_per_frame_p95": float(np.percentile(ms, 95)),
                "evals_per_frame": float(np.mean([r.evals for r in res])),
                "rms_mm_mean": float(err.mean()),
                "peak_heap_mib": memory(policy) if heap else None}

    from articast.core.tracking import fitting, kernels

    kernels.warm_up()  # compilation (or loading the on-disk cache) is not a frame's work
    base = TrackingPolicy.for_rig("head")
    from dataclasses import replace

    nm_policy = replace(base, optimiser="nelder-mead", levels=(0,))
    n_nm = min(args.nm_frames, te.n_frames)
    repeats = []
    for r in range(max(1, args.repeats)):  # interleaved: a burst of load hits all three
        gn = run(base, te.n_frames, heap=r == 0)
        nm = run(nm_policy, n_nm, heap=r == 0)
        gn_same = run(base, n_nm, heap=False)
        numpy_path = assembled = None
        if kernels.AVAILABLE:  # the same tracker on the numpy reference code of the cost
            kernels.AVAILABLE = False
            numpy_path = run(base, n_nm, heap=False)
            kernels.AVAILABLE = True
            # the kernels, but each Gauss-Newton evaluation assembled in numpy around them
            # (fitting.FIT_TERMS off: the reference of kernels.fit_terms)
            fitting.FIT_TERMS = False
            assembled = run(base, n_nm, heap=False)
            fitting.FIT_TERMS = True
        repeats.append({
            "gauss_newton_ms": gn["ms_per_frame_mean"], "gauss_newton_p95_ms":
                gn["ms_per_frame_p95"], "nelder_mead_ms": nm["ms_per_frame_mean"],
            "speedup_vs_nelder_mead_same_frames":
                nm["ms_per_frame_mean"] / gn_same["ms_per_frame_mean"],
            "compiled_kernel_speedup_same_frames": (
                numpy_path["ms_per_frame_mean"] / gn_same["ms_per_frame_mean"]
                if numpy_path else None),
            "compiled_evaluation_speedup_same_frames": (
                assembled["ms_per_frame_mean"] / gn_same["ms_per_frame_mean"]
                if assembled else None),
            "load_1min": load_average()[0]})
        if r == 0:
            first = (gn, nm, gn_same)
    gn, nm, gn_same = first

    def spread(key: str) -> list | None:
        v = [x[key] for x in repeats if x[key] is not None]
        return [round(min(v), 3), round(float(np.median(v)), 3), round(max(v), 3)] if v else None

    out = {
        "image": "640x480", "kind": args.kind, "threads": 1,
        "gauss_newton": gn, "nelder_mead": nm,
        "accuracy_same_frames_mm": {"gauss_newton": gn_same["rms_mm_mean"],
                                    "nelder_mead": nm["rms_mm_mean"]},
        "appearance_model_kb": app.weights.nbytes / 1024,
        "repeats": repeats,
        "min_median_max": {k: spread(k) for k in (
            "gauss_newton_ms", "gauss_newton_p95_ms", "nelder_mead_ms",
            "speedup_vs_nelder_mead_same_frames", "compiled_kernel_speedup_same_frames",
            "compiled_evaluation_speedup_same_frames")},
        "load_average_before": load_before, "load_average_after": load_average(),
        "cpus": os.cpu_count(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()

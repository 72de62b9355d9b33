"""Speed of dense-mesh transfer: bind a ~20,000-point dense mesh to a ~500-point sparse mesh,
then transfer frames. Prints one JSON document (times in ms; ratios are what to compare
across machines).

    python benchmarks/transfer_speed.py [--dense-side 142] [--sparse-side 23] [--frames 200]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from articast.core.dense.transfer import apply, barycentric_apply, bind  # noqa: E402


def surface_grid(side: int, half: float) -> tuple[np.ndarray, np.ndarray]:
    """A curved face-sized patch: (side^2, 3) mm vertices and (2 (side-1)^2, 3) triangles."""
    u = np.linspace(-half, half, side)
    x, y = (g.ravel() for g in np.meshgrid(u, u))
    pts = np.c_[x, y, -(x**2) / 120 - y**2 / 180 + 4e-5 * x**2 * y]
    idx = np.arange(side * side).reshape(side, side)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return pts, np.r_[np.c_[a, b, d], np.c_[a, d, c]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dense-side", type=int, default=142)
    ap.add_argument("--sparse-side", type=int, default=23)
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    sparse, tri = surface_grid(args.sparse_side, 40.0)
    dense, _ = surface_grid(args.dense_side, 39.0)
    t0 = time.perf_counter()
    binding = bind(sparse, tri, dense)
    bind_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    frames = sparse + rng.normal(scale=0.5, size=(args.frames, *sparse.shape))
    apply(binding, frames[0])  # warm-up
    timings = {}
    for name, fn in (("apply", apply), ("barycentric_apply", barycentric_apply)):
        t = []
        for f in frames:
            t0 = time.perf_counter()
            fn(binding, f)
            t.append(time.perf_counter() - t0)
        timings[name] = np.array(t) * 1e3
    doc = {
        "dense_points": len(dense),
        "sparse_points": len(sparse),
        "sparse_triangles": len(tri),
        "bind_s": round(bind_s, 3),
        "apply_ms_median": round(float(np.median(timings["apply"])), 3),
        "apply_ms_p95": round(float(np.percentile(timings["apply"], 95)), 3),
        "barycentric_ms_median": round(float(np.median(timings["barycentric_apply"])), 3),
        "apply_over_barycentric": round(
            float(np.median(timings["apply"]) / np.median(timings["barycentric_apply"])), 2),
        "apply_budget_ms": 2.0,
        "inside_fraction": round(float(binding.inside.mean()), 4),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()

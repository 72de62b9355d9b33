"""A real head scan bound to the synthetic speaker's model by its landmarks: menpo3d's
``james`` (fetch it first: ``python tools/fetch_scan.py``). Prints one JSON document with the
alignment, how the points are bound, and the dense-mode error (linear modes vs per-frame
transfer) over 32 postures of the model's training range, over the articulated points (the
targets of issue 22) and over every point that moves; ``--figure`` draws where the points go.

    python benchmarks/scan_binding.py [--scan DIR] [--seed 0] [--figure docs/scan_binding.png]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from articast.core.dense.landmarks import load_landmarks  # noqa: E402
from articast.core.dense.mesh import load_obj  # noqa: E402
from articast.core.dense.scan import align_scan, bind_scan  # noqa: E402
from articast.core.dense.transfer import apply, dense_modes  # noqa: E402
from articast.core.synthetic import default_speaker  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path, default=Path.home() / ".cache/articast/scans")
    ap.add_argument("--seed", type=int, default=0, help="the speaker")
    ap.add_argument("--figure", type=Path, default=None)
    args = ap.parse_args()
    obj, ljson = args.scan / "james.obj", args.scan / "james.ljson"
    if not obj.is_file():
        raise SystemExit(f"{obj} missing: run python tools/fetch_scan.py")
    model = default_speaker(args.seed).model()
    verts, tris = load_obj(obj)
    t0 = time.perf_counter()
    al = align_scan(model, verts, tris, load_landmarks(ljson))
    head = al.transform.apply(verts)
    binding, rep = bind_scan(model, head, tris)
    elapsed = time.perf_counter() - t0
    s = model.stats
    postures = np.random.default_rng(0).uniform(s.min, s.max, size=(32, model.n_params))
    mean, modes = dense_modes(binding, model)
    linear = mean + np.einsum("fk,kmd->fmd", postures, modes)
    exact = np.stack([apply(binding, x) for x in model.shape(postures)])
    gap = np.linalg.norm(linear - exact, axis=-1)
    art, moving = rep.articulated, binding.follow > 0
    motion = np.linalg.norm(exact - head, axis=-1).max(0)
    out = {
        "scan": str(obj), "dense_points": len(verts), "speaker_seed": args.seed,
        "alignment": {"landmark_pairs": list(al.pairs), "scale": round(al.transform.scale, 5),
                      "landmark_rms_mm": round(al.landmark_rms_mm, 2),
                      "icp_landmark_rms_mm": round(al.icp_landmark_rms_mm, 2),
                      "icp_rms_mm": round(al.icp_rms_mm, 3), "icp_converged": al.icp_converged,
                      "icp_iterations": al.icp_iterations,
                      "overlap_fraction": round(al.overlap_fraction, 3)},
        "points": {"articulated": rep.n_articulated, "border": rep.n_border,
                   "head_only": rep.n_held, "offset_not_fully_turned": rep.n_unturned},
        "inside_fraction_of_articulated": round(rep.inside_support_fraction, 4),
        "dense_modes_error_articulated_mm": _stats(gap[:, art]),
        "dense_modes_error_moving_mm": _stats(gap[:, moving]),
        "motion_over_training_range_mm": {"articulated_max": round(float(motion[art].max()), 2),
                                          "border_max": round(float(motion[moving & ~art].max()),
                                                              2)},
        "align_and_bind_s": round(elapsed, 2),
    }
    print(json.dumps(out, indent=2))
    if args.figure:
        _figure(args.figure, model, head, binding, rep, exact[np.argmax(postures[:, 0])] - head)


def _stats(gap: np.ndarray) -> dict:
    per_frame = gap.max(axis=1)  # the worst point of each posture
    return {"per_posture_max_median": round(float(np.median(per_frame)), 3),
            "per_posture_max_max": round(float(per_frame.max()), 3),
            "per_point_median": round(float(np.median(gap)), 4)}


def _figure(path: Path, model, head, binding, rep, disp) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13.5, 5.2))
    order = np.argsort(head[:, 2])  # far points first
    share = binding.follow
    for ax, (u, v, title) in zip(axes[:2], ((0, 1, "front (x, y)"), (2, 1, "side (z, y)")),
                                 strict=True):
        idx = order if u == 0 else np.argsort(-head[:, 0])
        sc = ax.scatter(head[idx, u], head[idx, v], c=share[idx], s=3, cmap="viridis",
                        vmin=0, vmax=1)
        ax.triplot(model.mean[:, u], model.mean[:, v], model.triangles, lw=0.3, color="0.35",
                   alpha=0.5)
        ax.set_title(f"{title}: share of the motion")
        ax.set_aspect("equal")
        ax.set_xlabel("mm")
    fig.colorbar(sc, ax=axes[:2], shrink=0.7, label="follow (1 articulated, 0 head only)")
    mag = np.linalg.norm(disp, axis=1)
    idx = np.argsort(-head[:, 0])
    sc2 = axes[2].scatter(head[idx, 2], head[idx, 1], c=mag[idx], s=3, cmap="magma")
    axes[2].set_title("side: motion, widest jaw opening (mm)")
    axes[2].set_aspect("equal")
    fig.colorbar(sc2, ax=axes[2], shrink=0.7)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    print(f"figure: {path}", file=sys.stderr)


if __name__ == "__main__":
    main()

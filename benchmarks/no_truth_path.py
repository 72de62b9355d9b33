"""The whole no-truth path on the synthetic speaker: enrol from landmarks on its rendered video
(no ground truth anywhere), track a different sentence, and only then compare with the truth.

    python benchmarks/no_truth_path.py --json [--rigs desk head] [--seeds 0 1 2]

Per rig and speaker:
- ``param_r``: correlation of each enrolled parameter with the true one (direct inversion of
  the true points in the true model) over the test frames marked ok;
- ``lips``: aperture and width (mm) against the true ones: correlation, slope, mean |error|;
- ``rms_mm``: RMS 3D error of the enrolled model's points against the true surface. The
  enrolled points are landmarks, not the true model's points, so each is bound once to the
  true mesh at rest (per-facet affine binding, METHOD.md §5) after a similarity alignment
  (MPEG-4 feature points, then ICP); the true motion of a bound point is the true mesh's
  motion transferred to it. ``rms_mm`` is over the points bound within 4 mm of the surface,
  ``rms_motion_mm`` the same after removing each point's mean offset (what a per-point
  definition difference between the landmarks and the true model contributes), ``scale``
  the similarity's scale (the error of the assumed inter-pupillary distance or mouth width).
  The ICP step slides the enrolled face over the true surface by several mm where the two
  faces' proportions differ, so a landmark can be bound to skin beside the point it follows
  (whose motion differs: a lip corner bound to the cheek); hence also
- ``feature_rms_mm``: RMS 3D error at the MPEG-4 feature points both models label (lips, chin,
  nose: direct correspondences, no binding) after the same similarity, no ICP, and
  ``feature_rms_motion_mm`` after removing each point's mean offset.
- ``--depth``: the enrolment's depth option (core/faces/enrol.py ``EnrolOptions.depth``), to
  compare with the landmarks' own depth.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_clips import add_enrol_options, enrol_speaker  # noqa: E402

from articast.core.dense.mesh import register_icp  # noqa: E402
from articast.core.dense.transfer import apply, bind  # noqa: E402
from articast.core.faces.build import BuildOptions  # noqa: E402
from articast.core.faces.enrol import EnrolOptions, similarity  # noqa: E402
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.live import LivePolicy, LiveTracker  # noqa: E402
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.model.build import invert  # noqa: E402
from articast.core.outputs.lips import lip_measures  # noqa: E402
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence  # noqa: E402

LABELS = ("2.1", "2.2", "2.3", "2.4", "2.5", "8.1", "8.2", "8.3", "8.4", "9.15")


def surface_error(model_e, alpha_e: np.ndarray, ok: np.ndarray, true_model, points: np.ndarray,
                  rest: slice) -> dict:
    """RMS of the enrolled geometry against the true surface (see the module docstring)."""
    ge = model_e.shape(alpha_e)  # (F, N, 3)
    rest_e, rest_t = ge[rest].mean(0), points[rest].mean(0)
    fe = [model_e.point(x) for x in LABELS]
    ft = [true_model.point(x) for x in LABELS]
    s, r, t = similarity(rest_e[fe], rest_t[ft])
    aligned = s * rest_e @ r.T + t
    reg = register_icp(aligned, rest_t, fixed_triangles=true_model.triangles)
    moved = reg.apply(aligned)  # enrolled points in the true head frame
    binding = bind(rest_t, true_model.triangles, moved)
    d = np.linalg.norm(apply(binding, rest_t) - moved, axis=1)
    near = d < 4.0
    # the whole enrolled sequence through the same similarity and ICP correction
    g = s * ge @ r.T + t
    g = reg.apply(g)
    truth = np.stack([apply(binding, p) for p in points])
    diff = (g - truth)[:, near]
    rms = np.sqrt((diff**2).sum(-1).mean(-1))
    bias = diff[ok].mean(0)
    motion = np.sqrt(((diff - bias) ** 2).sum(-1).mean(-1))
    common = [x for x in model_e.feature_points if x in true_model.feature_points]
    fd = (s * ge[:, [model_e.point(x) for x in common]] @ r.T + t
          - points[:, [true_model.point(x) for x in common]])
    f_rms = np.sqrt((fd**2).sum(-1).mean(-1))
    f_motion = np.sqrt(((fd - fd[ok].mean(0)) ** 2).sum(-1).mean(-1))
    return {"rms_mm": float(rms[ok].mean()), "rms_mm_p95": float(np.percentile(rms[ok], 95)),
            "feature_rms_mm": float(f_rms[ok].mean()),
            "feature_rms_motion_mm": float(f_motion[ok].mean()), "feature_points": len(common),
            "rms_motion_mm": float(motion[ok].mean()), "scale": float(s),
            "points_bound": int(near.sum()), "points": int(near.size)}


def run(rig: str, seed: int, enrol_frames: int = 300, test_frames: int = 150,
        depth: str | None = None, flow: bool | None = None,
        upper_lip_off_jaw: bool = False, motion: bool = True, fusion: bool = True) -> dict:
    sp = default_speaker(seed)
    true_model = sp.model()
    finder = FaceFinder.load(threads=1)
    enrol = make_sequence(seed * 100 + 11, enrol_frames, 12.0, rig, geometry=sp.geometry)
    imgs = [sp.render(enrol.controls[i], enrol.pose(i), enrol.camera,
                      RenderOptions(seed=10_000 + i)) for i in range(enrol.n_frames)]
    opts = EnrolOptions(fixed_pose=(rig == "head"), jaw_moves_upper_lip=not upper_lip_off_jaw,
                        **({"depth": depth} if depth is not None else {}))
    speaker = enrol_speaker(imgs, 12.0, camera=enrol.camera, rig=rig, max_frames=None,
                            finder=finder, options=opts, build=BuildOptions(flow=flow))
    build_s = speaker.report["build_s"]
    test = make_sequence(seed * 100 + 12, test_frames, 50.0, rig, geometry=sp.geometry)
    policy = LivePolicy(**({} if motion else {"motion": None}),
                        **({} if fusion else {"fusion": None}))
    live = LiveTracker(speaker, finder, mediapipe_scheme(rig), policy, clock=time.perf_counter)
    res = [live.track(sp.render(test.controls[i], test.pose(i), test.camera,
                                RenderOptions(seed=20_000 + i)), float(test.times[i]))
           for i in range(test.n_frames)]
    ok = np.array([r.ok for r in res])
    alpha = np.array([r.alpha for r in res])
    at = invert(true_model, test.points)
    names = speaker.model.param_names[:6]
    param_r = {n: round(float(np.corrcoef(alpha[ok, k], at[ok, k])[0, 1]), 3)
               for k, n in enumerate(names)}
    ap, wd = lip_measures(speaker.model, alpha)
    apt, wdt = lip_measures(true_model, at)
    lips = {}
    for key, e, tr in (("aperture", ap, apt), ("width", wd, wdt)):
        lips[key] = {"r": round(float(np.corrcoef(e[ok], tr[ok])[0, 1]), 3),
                     "slope": round(float(np.polyfit(tr[ok], e[ok], 1)[0]), 3),
                     "mean_abs_mm": round(float(np.abs(e - tr)[ok].mean()), 2)}
    # lag: the shift (frames) that best aligns the tracked aperture with the true one
    a0, b0 = ap - ap.mean(), apt - apt.mean()
    shifts = range(-5, 6)
    score = [float(np.dot(a0[max(s, 0):len(a0) + min(s, 0)], b0[max(-s, 0):len(b0) - max(s, 0)]))
             for s in shifts]
    lips["lag_frames"] = int(list(shifts)[int(np.argmax(score))])
    still = test.still_segments()
    rest = slice(*still[0]) if still else slice(0, 1)
    surf = surface_error(speaker.model, alpha, ok, true_model, test.points, rest)
    return {"rig": rig, "seed": seed, "ok": round(float(ok.mean()), 3), "param_r": param_r,
            "lips": lips, **{k: round(v, 3) if isinstance(v, float) else v
                             for k, v in surf.items()},
            "depth": opts.depth, "flow": speaker.report["pixels"] != "landmarks",
            "upper_lip_off_jaw": not opts.jaw_moves_upper_lip, "motion": motion,
            "fused": live.fusion is not None,
            "enrol_build_s": round(build_s, 1),
            "ms_per_frame_median": round(float(np.median([r.ms for r in res])), 2)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", nargs="*", default=["desk", "head"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    add_enrol_options(ap)
    ap.add_argument("--no-motion", action="store_true",
                    help="live tracking without the upper face's optical flow")
    ap.add_argument("--no-fusion", action="store_true",
                    help="live tracking without the reader's landmarks every frame (the "
                         "appearance fit alone; LivePolicy.fusion None)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    for rig in args.rigs:
        for seed in args.seeds:
            row = run(rig, seed, depth=args.depth, flow=args.flow,
                      upper_lip_off_jaw=args.upper_lip_off_jaw, motion=not args.no_motion,
                      fusion=not args.no_fusion)
            rows.append(row)
            if not args.json:
                print(row, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

"""What each of the tracker's departures from the paper buys, per camera rig.

    python benchmarks/tracking_ablation.py [--rig head|desk] [--seeds 0 1 2] [--kind la_lin]
        [--json]

Same protocol as ``articast evaluate``'s teleconference (``--rig head``, default) or desk
condition (appearance trained on the 75 enrolment frames of the speaker on that rig, two
150-frame test sequences at 50 fps, started at the true first state; RMS 3D error of the model
geometry at the tracked vs the true articulation, frames marked ok), for each speaker seed
given. Variants, each adding to the one before:

head rig
- ``paper``: least squares, pose prior on the previous frame, the paper's largest-displacement
  point selection (5 points per parameter), ridge 0.01 — the tracker before these changes;
- ``+robust``: the per-point Cauchy loss;
- ``+anchor``: the pose prior centred on the running average pose (head rig);
- ``+ridge``: ridge 0.1 (la);
- ``+information``: information-based selection of 56 points, the head pose taken as known,
  filters 2.5 px (the default until the desk work);
- ``default``: what ``articast evaluate`` trains: the selection plans for the estimated pose,
  84 points, filters 0.7 mm on the face.

desk rig (free head motion; all with the robust loss, ridge 0.1, previous-frame pose prior)
- ``+information``: as above (56 points, pose known, 2.5 px);
- ``+pose-aware``: the selection marginalises the head pose (the desk's per-frame s.d.);
- ``+84 points``;
- ``+rotation``: la rotation terms (shading as the head turns);
- ``default``: and filters 0.7 mm on the face (1.25 px at 56 cm).

Accuracy only (the speed is benchmarks/tracking_speed.py's). Prints a table, or JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from articast.core.appearance.models import train_appearance  # noqa: E402
from articast.core.evaluation.measures import rms_3d  # noqa: E402
from articast.core.model.build import invert  # noqa: E402
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence  # noqa: E402
from articast.core.synthetic.enrol import enrolment_appearance, enrolment_frames  # noqa: E402
from articast.core.synthetic.sequence import default_camera  # noqa: E402
from articast.core.tracking.tracker import POSE_SIGMA, Tracker, TrackingPolicy  # noqa: E402

PAPER_TRAIN = {"selection": "displacement", "per_param": 5, "ridge": 0.01}
INFO_TRAIN = {"per_param": 8, "sigma": 2.5}
VARIANTS = {
    # name: (training options, robust scale, pose anchor rate)
    "head": {
        "paper": (PAPER_TRAIN, None, None),
        "+robust": (PAPER_TRAIN, 2.0, None),
        "+anchor": (PAPER_TRAIN, 2.0, 0.02),
        "+ridge": ({**PAPER_TRAIN, "ridge": 0.1}, 2.0, 0.02),
        "+information": (INFO_TRAIN, 2.0, 0.02),
        "default": (None, 2.0, 0.02),
    },
    "desk": {
        "+information": (INFO_TRAIN, 2.0, None),
        "+pose-aware": ({**INFO_TRAIN, "pose_sigma": POSE_SIGMA["desk"]}, 2.0, None),
        "+84 points": ({"sigma": 2.5, "pose_sigma": POSE_SIGMA["desk"]}, 2.0, None),
        "+rotation": ({"sigma": 2.5, "pose_sigma": POSE_SIGMA["desk"],
                       "rotation_terms": True}, 2.0, None),
        "default": (None, 2.0, None),
    },
}


def run_seed(seed: int, kind: str, rig: str = "head") -> dict[str, dict[str, float]]:
    speaker = default_speaker(seed)
    model = speaker.model()
    frames = enrolment_frames(speaker, rig, seed * 100 + 1)
    tests = []
    for j in range(2):
        seq = make_sequence(seed * 100 + 2 + j, 150, 50.0, rig)
        imgs = [speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                               RenderOptions(seed=1000 * (j + 1) + i))
                for i in range(seq.n_frames)]
        tests.append((seq, imgs))
    out = {}
    for name, (train, robust, anchor) in VARIANTS[rig].items():
        if train is None:  # the product's options for the rig
            app = enrolment_appearance(speaker, rig, kind, frames)
        else:
            app = train_appearance(model, default_camera(rig), frames, kind, **train)
        pol = TrackingPolicy.for_rig(rig, pose_anchor_rate=anchor)
        pol = replace(pol, fit=replace(pol.fit, robust_scale=robust),
                      reinit_fit=replace(pol.reinit_fit, robust_scale=robust))
        errs, oks = [], []
        for seq, imgs in tests:
            tracker = Tracker(model, app, seq.camera, pol)
            truth = invert(model, seq.points)
            tracker.reset(seq.pose(0), truth[0])
            res = [tracker.track(imgs[i], float(seq.times[i])) for i in range(len(imgs))]
            ok = np.array([r.ok for r in res])
            err = rms_3d(model, np.array([r.alpha for r in res]), truth)
            errs.append(err[ok])
            oks.append(ok)
        e = np.concatenate(errs)
        out[name] = {"points": app.n_samples, "sigma_px": app.sigma,
                     "rms_mm_mean": float(e.mean()),
                     "rms_mm_p95": float(np.percentile(e, 95)),
                     "ok_fraction": float(np.concatenate(oks).mean())}
        print(f"seed {seed} {name:12s} {app.n_samples:3d} points  mean {e.mean():.3f}  "
              f"p95 {np.percentile(e, 95):.3f}", file=sys.stderr)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rig", default="head", choices=["head", "desk"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kind", default="la_lin", choices=["la_lin", "la_quad", "la_cst"])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    results = {str(s): run_seed(s, args.kind, args.rig) for s in args.seeds}
    if args.json:
        print(json.dumps({"kind": args.kind, "rig": args.rig, "seeds": results}, indent=2))
        return
    print(f"{'variant':12s} " + " ".join(f"seed {s}: mean  p95 " for s in args.seeds))
    for name in VARIANTS[args.rig]:
        cells = " ".join(f"      {results[str(s)][name]['rms_mm_mean']:.2f}  "
                         f"{results[str(s)][name]['rms_mm_p95']:.2f}" for s in args.seeds)
        print(f"{name:12s} {cells}")


if __name__ == "__main__":
    main()

"""Where the enrolled geometry's error comes from, on the rendered speaker (diagnosis: the truth
is used to explain, never to enrol).

    python benchmarks/enrol_geometry.py --json [--rig desk] [--seed 0] [--lk]

Renders the no-truth path's enrolment clip (benchmarks/no_truth_path.py: 300 frames at 12 fps),
runs the landmark model on it, and reports, on the enrolment frames themselves:

- ``landmark_depth_r``: per MPEG-4 feature point, the correlation over the frames of its
  landmark's depth relative to the face's mean with the true point's (camera frame);
- per enrolment variant, ``param_r`` (enrolment articulation against the true parameters) and
  the RMS motion error of the enrolled model against the true surface per axis
  (``motion_xyz_mm``, head frame; each point bound to the true mesh as in no_truth_path.py
  and its mean offset removed). Variants: the two ``--depth`` options, and two that replace
  the landmarks by the true surface points they are bound to (``oracle``: true pixels and
  depth, the ceiling of the pipeline; ``oracle_pixels``: true pixels, landmark depth, rigid
  depth option);
- ``feature_offset_mm``: mean distance of the labelled feature points from their true
  counterparts at the mean posture after the binding's similarity, and after its ICP;
- ``--lk``: the landmarks' pixels refined by optical flow as ``articast enroll --flow`` does
  (core/faces/flow.py: pyramidal Lucas-Kanade frame to frame, forward-backward check, pulled
  back to the landmarks by 10 % a frame, restarted from them past 5 % of the face), rigid
  depth, as a variant; and the RMS of each frame-to-frame 2D displacement against the bound
  truth's, for the landmarks and the flow.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from no_truth_path import LABELS  # noqa: E402
from real_clips import landmarks_every_frame  # noqa: E402

from articast.core.dense.mesh import register_icp  # noqa: E402
from articast.core.dense.transfer import apply, bind  # noqa: E402
from articast.core.faces.enrol import EnrolOptions, enrol_geometry, similarity  # noqa: E402
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.flow import refine_pixels  # noqa: E402
from articast.core.faces.scheme import FEATURE_LANDMARKS, mediapipe_scheme  # noqa: E402
from articast.core.model.build import invert  # noqa: E402
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence  # noqa: E402


def _binding(model_e, ge, true_model, points):
    """The enrolled points bound to the true mesh at the clip's mean posture (as no_truth_path)."""
    rest_e, rest_t = ge.mean(0), points.mean(0)
    s, r, t = similarity(rest_e[[model_e.point(x) for x in LABELS]],
                         rest_t[[true_model.point(x) for x in LABELS]])
    reg = register_icp(s * rest_e @ r.T + t, rest_t, fixed_triangles=true_model.triangles)
    return (s, r, t), reg, bind(rest_t, true_model.triangles, reg.apply(s * rest_e @ r.T + t))


def _evaluate(geo, true_model, points) -> dict:
    at = invert(true_model, points[geo.frames])
    ge = geo.model.shape(geo.alpha)
    (s, r, t), reg, binding = _binding(geo.model, ge, true_model, points[geo.frames])
    g = reg.apply(s * ge @ r.T + t)
    truth = np.stack([apply(binding, p) for p in points[geo.frames]])
    diff = g - truth
    diff -= diff.mean(0)
    return {"param_r": {n: round(float(np.corrcoef(geo.alpha[:, k], at[:, k])[0, 1]), 3)
                        for k, n in enumerate(geo.model.param_names[:6])},
            "motion_mm": round(float(np.sqrt((diff**2).sum(-1).mean(-1)).mean()), 3),
            "motion_xyz_mm": [round(float(np.sqrt((diff[..., c] ** 2).mean())), 3)
                              for c in range(3)]}


def run(rig: str, seed: int, lk: bool = False) -> dict:
    sp = default_speaker(seed)
    true_model = sp.model()
    seq = make_sequence(seed * 100 + 11, 300, 12.0, rig, geometry=sp.geometry)
    imgs = [sp.render(seq.controls[i], seq.pose(i), seq.camera, RenderOptions(seed=10_000 + i))
            for i in range(seq.n_frames)]
    marks, found, _ = landmarks_every_frame(FaceFinder.load(threads=1), imgs)
    scheme = mediapipe_scheme(rig)
    cam_true = np.stack([seq.pose(i).transform(seq.points[i]) for i in range(seq.n_frames)])
    depth_r = {}
    for label, lmk in FEATURE_LANDMARKS.items():
        a = marks[:, lmk, 2] - marks[:, :, 2].mean(1)
        b = cam_true[:, true_model.point(label), 2] - cam_true[:, :, 2].mean(1)
        depth_r[label] = round(float(np.corrcoef(a - a.mean(), b - b.mean())[0, 1]), 2)
    out = {"rig": rig, "seed": seed, "landmark_depth_r": depth_r, "variants": {}}

    def enrol(lm, depth):
        return enrol_geometry(lm, found, scheme, seq.camera,
                              EnrolOptions(fixed_pose=(rig == "head"), depth=depth))

    for depth in ("landmarks", "rigid"):
        out["variants"][depth] = _evaluate(enrol(marks, depth), true_model, seq.points)
    # the landmarks replaced by the true surface points they are bound to
    geo = enrol(marks, "landmarks")
    ge = geo.model.shape(geo.alpha)
    (s, r, t), reg, binding = _binding(geo.model, ge, true_model, seq.points[geo.frames])
    rest_t = seq.points[geo.frames].mean(0)
    labels = [x for x in geo.model.feature_points if x in true_model.feature_points]
    sim = s * ge.mean(0)[[geo.model.point(x) for x in labels]] @ r.T + t
    true_pts = rest_t[[true_model.point(x) for x in labels]]
    out["feature_offset_mm"] = {
        "similarity": round(float(np.linalg.norm(sim - true_pts, axis=1).mean()), 2),
        "similarity_icp": round(float(np.linalg.norm(reg.apply(sim) - true_pts, axis=1).mean()),
                                2)}
    oracle = marks.copy()
    for f in range(seq.n_frames):
        pc = seq.pose(f).transform(apply(binding, seq.points[f]))
        k = pc[:, 2].mean() / seq.camera.fx  # mm per px at the face
        oracle[f, scheme.points, :2] = seq.camera.project(pc)
        oracle[f, scheme.points, 2] = (pc[:, 2] - pc[:, 2].mean()) / k
    out["variants"]["oracle"] = _evaluate(enrol(oracle, "landmarks"), true_model, seq.points)
    pix = marks.copy()
    pix[:, scheme.points, :2] = oracle[:, scheme.points, :2]
    out["variants"]["oracle_pixels"] = _evaluate(enrol(pix, "rigid"), true_model, seq.points)
    if lk:
        refined = refine_pixels(imgs, marks, found, scheme.points)
        out["variants"]["lk_rigid"] = _evaluate(enrol(refined, "rigid"), true_model, seq.points)
        ids = scheme.points
        true_d = np.diff(oracle[:, ids, :2], axis=0)
        out["displacement_err_px"] = {
            name: round(float(np.sqrt(((np.diff(p[:, ids, :2], axis=0) - true_d) ** 2)
                                      .sum(-1).mean())), 3)
            for name, p in (("landmarks", marks), ("lk", refined))}
        out["displacement_true_px"] = round(float(np.sqrt((true_d**2).sum(-1).mean())), 3)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rig", default="desk", choices=["desk", "head"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lk", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    row = run(args.rig, args.seed, args.lk)
    print(json.dumps(row, indent=1) if args.json else row)


if __name__ == "__main__":
    main()

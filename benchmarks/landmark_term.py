"""How much of the reader's lip reading survives the speaker's model: the fused fit's landmark
term as an estimator on its own.

    python benchmarks/peers.py --json --series DIR           # once: the peers' series
    python benchmarks/landmark_term.py --series DIR [--only CLIP ...] [--json]

Per clip, articast is enrolled on the first 60 % as ``peers.py`` does, and the FaceMesh v1
loop (``peers.py``'s, the network the live tracker reads) reads every held-out frame. Each
reading is then fitted alone: the speaker's state (7 parameters and the head pose) that best
explains the reader's 300 points through the enrolment's observation model, with the error
modes the points share (:class:`~articast.core.tracking.points.PointTerm`, least squares),
and nothing else: no appearance, no prior, no motion model, no filter. Scored as ``peers.py``
scores articast (r against the consensus of the other methods in DIR, articast's own series
left out; still-mouth jitter on ``peers.py``'s windows, % of the outer lip width):

- ``reader``: the network's own aperture ratio (inner-lip points 13-14 over corners 61-291);
- ``through_model``: the speaker model's aperture over its outer width at the fitted state,
  what articast streams (with the landmarks alone, every frame);
- ``reader_predicted``: the same four reader points as the observation model places them at
  the fitted state: how much of the reader's own opening the fit reproduces;
- ``regression``: the speaker model's aperture at the articulation the enrolment's reading
  regression (:class:`~articast.core.tracking.points.ReadingRegression`) reads off the same
  reading, the head at the fitted pose: the discriminative reading of the same points;
- ``articast``: the fused product's series from DIR, for reference.

``r_through_vs_reader`` and ``r_predicted_vs_reader`` correlate the last two with the reading
itself. A fit that kept the reading's information would score as ``reader`` does.

Accuracy does not depend on the machine's load. ~1-2 min per clip on 2 cores.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import peers  # noqa: E402
from face_landmarks_clips import jitter  # noqa: E402

from articast.core.faces.finder import models_dir  # noqa: E402
from articast.core.faces.fit import fit_pose  # noqa: E402
from articast.core.model.camera import Pose, axis_angle, rotation_matrix  # noqa: E402
from articast.core.outputs.lips import lip_measures  # noqa: E402
from articast.core.tracking.points import PointModel, PointTerm  # noqa: E402

GAP_POINTS = (13, 14, 61, 291)  # peers.SCHEMES["mediapipe"][:4]
LEFT_OUT = ("articast", "facemesh_v1")
RIDGE = 1e-3  # on alpha only: lar1 is not seen by landmarks (its column is ~0)


def fit_reading(pm: PointModel, camera, uv: np.ndarray, alpha: np.ndarray, pose: Pose,
                iterations: int = 8) -> tuple[np.ndarray, Pose]:
    """Gauss-Newton on the landmark term alone (least squares, shared modes), from a start."""
    a, rot, t = alpha.copy(), pose.matrix.copy(), np.array(pose.translation, float)
    term = PointTerm(pm, camera, uv, float(t[2]), scale=None, weight=1.0)
    k = pm.n_params
    for _ in range(iterations):
        r, jac = term.residuals(a, rot, t, True)
        assert jac is not None
        _, g_shared, h_shared = term.shared(r, jac)
        g, h = jac.T @ r - g_shared, jac.T @ jac - h_shared
        h[:k, :k] += RIDGE * np.eye(k)
        g[:k] += RIDGE * a
        step = -np.linalg.solve(h, g)
        a, rot, t = a + step[:k], rotation_matrix(step[k:k + 3]) @ rot, t + step[k + 3:]
        if np.abs(step).max() < 1e-6:
            break
    return a, Pose(axis_angle(rot), t)


def readings_through_model(speaker, held: list[np.ndarray]) -> dict[str, np.ndarray]:
    pm, cam, m = speaker.points, speaker.camera, speaker.model
    loop = peers.FinderLoop(peers.facemesh_v1_finder(models_dir() / "face_landmarks_v1.onnx"),
                            held)
    n = len(held)
    reader, predicted = np.full(n, np.nan), np.full(n, np.nan)
    alphas = np.full((n, m.n_params), np.nan)
    regressed = np.full((n, m.n_params), np.nan)
    a, pose = np.zeros(m.n_params), None
    for i in range(n):
        face = loop(i)
        if face is None:
            continue
        uv = np.asarray(face.landmarks[pm.landmarks, :2], np.float64)
        if pose is None:
            pose = fit_pose(pm.points(a), uv, cam)
            if pose is None:
                continue
        a, pose = fit_reading(pm, cam, uv, a, pose)
        alphas[i] = a
        if pm.regression is not None:
            reg = pm.regression
            regressed[i] = reg.alpha(reg.features(pm.mean, cam, uv, pose.matrix,
                                                  np.asarray(pose.translation, np.float64)))
        full = np.full((468, 2), np.nan)
        full[:] = face.landmarks[:468, :2]
        reader[i] = peers.aperture_ratio(full[None], "mediapipe")[0]
        full[pm.landmarks] = cam.project(pm.points(a) @ pose.matrix.T + pose.translation)
        predicted[i] = peers.aperture_ratio(full[None], "mediapipe")[0]
    return {"reader": reader, "through_model": model_ratio(m, alphas),
            "reader_predicted": predicted, "regression": model_ratio(m, regressed)}


def model_ratio(m, alphas: np.ndarray) -> np.ndarray:
    """The speaker model's aperture over its outer width at each articulation (NaN rows:
    NaN)."""
    ok = np.isfinite(alphas).all(1)
    safe = np.where(ok[:, None], alphas, 0.0)
    ap, _ = lip_measures(m, safe)
    return np.where(ok, ap / peers.outer_width_mm(m, safe), np.nan)


def run_clip(name: str, series: dict) -> dict:
    c = peers.series_clip(name, series, LEFT_OUT)
    held, others, windows = c["held"], c["others"], c["windows"]
    peers.log(f"{name}: enrolling, then fitting each reading alone")
    got = peers.run_articast(c["enrol"], held, c["fps"], **c["kw"])
    if "error" in got:
        return {"clip": name, "error": got["error"]}
    ser = readings_through_model(got["speaker"], held)
    ser["articast"] = series["ratio"]["articast"]
    out: dict = {"clip": name, "frames": len(held), "still_windows": len(windows)}
    cons = peers.consensus(others)
    for key, x in ser.items():
        row = {"r": peers._round(peers.pearson(x, cons)[0], 4),
               "jitter": peers._round(jitter(x, windows), 3)}
        if series["truth"] is not None:
            row["truth_r"] = peers._round(peers.pearson(x, series["truth"])[0], 4)
        out[key] = row
    for key, label in (("through_model", "r_through_vs_reader"),
                       ("reader_predicted", "r_predicted_vs_reader")):
        out[label] = peers._round(peers.pearson(ser[key], ser["reader"])[0], 4)
    peers.log(f"  {out}")
    return out


def main() -> None:
    ap = peers.series_parser(__doc__)
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rows = []
    for name, s in peers.series_clips(args.series, args.only, LEFT_OUT, clips=args.clips):
        rows.append(run_clip(name, s))
    if args.json:
        print(json.dumps({"command": " ".join(sys.argv), "clips": rows}, indent=1))
        return
    print("| clip | reader r / jitter | through the model | the reader's points as fitted "
          "| the regression | articast (fused) | r through vs reader | r fitted vs reader |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        if "error" in row:
            print(f"| {row['clip']} | {row['error']} | | | | | | |")
            continue
        cells = [f"{row[k]['r']} / {row[k]['jitter']}"
                 + (f" (truth {row[k]['truth_r']})" if "truth_r" in row[k] else "")
                 for k in ("reader", "through_model", "reader_predicted", "regression",
                           "articast")]
        print(f"| {row['clip']} | " + " | ".join(cells)
              + f" | {row['r_through_vs_reader']} | {row['r_predicted_vs_reader']} |")


if __name__ == "__main__":
    main()

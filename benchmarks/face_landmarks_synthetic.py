"""Landmark models against the synthetic speaker's truth, desk and head rigs.

Renders the speaker (seed 0) every 6th frame of a 300-frame sequence, runs ``find`` with
each landmark model (v2 bundled; v1 variants from ``tools/convert_face_models.py
--with-v1``'s cache) and compares with the projected true geometry:
- aperture: inner-lip opening over outer lip width (as in face_landmarks_clips.py) against
  the same ratio of the true points 2.2/2.3 and 8.3/8.4: correlation, slope and offset of
  the linear fit (landmarks = slope x truth + offset), RMS difference;
- lips: mean distance (px) of landmarks 13, 14, 0, 17, 291, 61 to the true 2.2, 2.3, 8.1,
  8.2, 8.3, 8.4.

With ``--box`` the head rig runs the landmarks on a fixed 800 px square above the frame
(``find(image, box=...)``, no refinement) instead of the detector.

With ``--still`` it compares crop policies on every frame of 200-frame sequences (seeds 1
and 2) of each rig, v2 only: ``track`` re-cropping every frame (``keep_roi=0``), ``track``
with the default ``keep_roi``, and (head rig) a fixed box; it reports the lip-aperture
jitter on the sequences' still segments (truth constant, sensor noise not) in % of the lip
width, the lip error and the aperture correlation.

    cd benchmarks && python face_landmarks_synthetic.py [--face-models DIR] [--box] [--still]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from face_landmarks_clips import aperture, sessions  # run from benchmarks/ (sys.path)

from articast.core.faces import FaceFinder, FinderPolicy
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence

PAIRS = {"2.2": 13, "2.3": 14, "8.1": 0, "8.2": 17, "8.3": 291, "8.4": 61}
HEAD_BOX = np.array([-80.0, -280.0, 720.0, 520.0])


def true_aperture(t: np.ndarray) -> float:
    """Same ratio as :func:`aperture` on the projected truth (rows in PAIRS order)."""
    width = np.linalg.norm(t[4] - t[5])
    across = (t[4] - t[5]) / width
    return float((t[1] - t[0]) @ np.array([-across[1], across[0]]) / width)


def evaluate(finder: FaceFinder, rig: str, box: np.ndarray | None) -> str:
    speaker = default_speaker(0)
    seq = make_sequence(0, 300, 50.0, rig, size=(640, 480), geometry=speaker.geometry)
    idx = [speaker.geometry.feature_points[k] for k in PAIRS]
    truth, est, err = [], [], []
    for i in range(0, 300, 6):
        image = speaker.render(seq.controls[i], seq.pose(i), seq.camera, RenderOptions(seed=i))
        t = seq.camera.project(seq.pose(i).transform(seq.points[i][idx]))
        face = finder.find(image, box=box)
        truth.append(true_aperture(t))
        est.append(aperture(face.landmarks)[0] if face is not None else np.nan)
        err.append(np.linalg.norm(face.landmarks[list(PAIRS.values()), :2] - t, axis=1).mean()
                   if face is not None else np.nan)
    truth, est = np.array(truth), np.array(est)
    ok = np.isfinite(est)
    slope, offset = np.polyfit(truth[ok], est[ok], 1)
    return (f"found {ok.mean():.2f}  aperture r {np.corrcoef(truth[ok], est[ok])[0, 1]:.3f} "
            f"slope {slope:.2f} offset {offset * 100:.1f} %  rms "
            f"{np.sqrt(np.mean((est[ok] - truth[ok]) ** 2)) * 100:.1f} % of width  "
            f"lips {np.nanmean(err):.1f} px")


def still_jitter(finder: FaceFinder, rig: str, seed: int, policy: str) -> str:
    """One crop policy on every frame of a 200-frame sequence (see the module docstring)."""
    speaker = default_speaker(0)
    seq = make_sequence(seed, 200, 50.0, rig, size=(640, 480), geometry=speaker.geometry)
    idx = [speaker.geometry.feature_points[k] for k in PAIRS]
    previous, est, truth, err = None, [], [], []
    for i in range(seq.n_frames):
        image = speaker.render(seq.controls[i], seq.pose(i), seq.camera, RenderOptions(seed=i))
        t = seq.camera.project(seq.pose(i).transform(seq.points[i][idx]))
        if policy == "fixed box":
            face = finder.find(image, box=HEAD_BOX)
        else:
            face = finder.track(image, previous) if previous is not None else None
            face = previous = face or finder.find(image)
        est.append(aperture(face.landmarks)[0])
        truth.append(true_aperture(t))
        err.append(np.linalg.norm(face.landmarks[list(PAIRS.values()), :2] - t, axis=1).mean())
    est = np.array(est)
    res = np.concatenate([est[a:b] - est[a:b].mean() for a, b in seq.still_segments()])
    return (f"still jitter {np.sqrt(np.mean(res**2)) * 100:.3f} % of width  lips "
            f"{np.mean(err):.2f} px  aperture r {np.corrcoef(est, truth)[0, 1]:.3f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--face-models", type=Path,
                    default=Path.home() / ".cache/articast/face-models")
    ap.add_argument("--box", action="store_true", help="head rig: fixed box, no detector")
    ap.add_argument("--still", action="store_true", help="compare crop policies (v2)")
    args = ap.parse_args(argv)
    if args.still:
        v2 = FaceFinder.load()
        policies = {
            "track, re-crop every frame": FaceFinder(
                v2.detector_session, v2.landmarks_session, FinderPolicy(keep_roi=0.0)),
            "track, keep_roi (default)": v2,
            "fixed box": FaceFinder(v2.detector_session, v2.landmarks_session,
                                    FinderPolicy(refine=0)),
        }
        for rig in ("desk", "head"):
            for seed in (1, 2):
                for name, finder in policies.items():
                    if name != "fixed box" or rig == "head":
                        print(f"{rig:5s} seed {seed}  {name:28s} "
                              f"{still_jitter(finder, rig, seed, name)}")
        return
    for name, finder in sessions(args.face_models, 1).items():
        for rig in ("desk", "head"):
            box = HEAD_BOX if (args.box and rig == "head") else None
            used = finder if box is None else FaceFinder(
                finder.detector_session, finder.landmarks_session, FinderPolicy(refine=0))
            print(f"{rig:5s} {name:34s} {evaluate(used, rig, box)}")


if __name__ == "__main__":
    main()

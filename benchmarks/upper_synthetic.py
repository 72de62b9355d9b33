"""The upper face against ground truth: the synthetic speaker blinks, looks and raises its brows.

    python benchmarks/upper_synthetic.py [--seconds 60] [--fps 30] [--json]

The built-in speaker (seed 0) on the desk rig, its eyes and brows animated by
:func:`articast.core.synthetic.upper.upper_sequence` (blinks 10-20 a minute, some double; gaze
fixations and saccades; brow raises). It is enrolled as ``articast enroll`` would (the finding
landmarks, the live reader, ``build_speaker``, upper-face references included) on another
sentence of 300 frames at 12 fps with its own blinks, then tracked live (``LiveTracker``, the
product's policy: the reader every third frame) on a test sentence of ``--seconds`` at
``--fps``. Scores against the truth:

- ``blink_f1`` (precision, recall): events = runs of frames whose mean closure (left, right) is
  above 0.5 (runs apart by <= 50 ms merged: ``blink_events``, as ``benchmarks/blinks.py``
  counts), in the truth and in the tracked; a tracked and a true event match when they
  overlap, one to one; ``onset``: tracked onset minus true onset (frames) per matched blink,
  ``onset_within_1`` the fraction within one frame;
- ``closure_r``: correlation of the tracked closure (each eye) with the true one;
- ``gaze_median_error_deg``: median over frames with open eyes (true closure < 0.2) of the
  angle between the tracked and the true gaze (yaw, pitch);
- ``brow_r``: correlation of the tracked brow raise (inner and outer mean, each side) with the
  true raise;
- ``lips``: the lip aperture's correlation and mean absolute error against the truth on the
  same frames, with the eyes animated and with the static eyes (the lips must not change);
- ``upper_cpu_ms``: the upper face's own step per frame (``UpperTracker.step``, timed in the
  same run), next to the frame's (``frame_cpu_ms``), one thread; ``over_lips_cpu_ms``: the
  upper face's whole cost over the lips alone, in the same run (the same tracker without the
  upper-face references, 3 interleaved pairs of runs: ``benchmarks/real_clips.py``
  ``cost_over_lips``).

Note: the synthetic eye and the tracker's gaze both take the iris 11.5 mm from the eyeball's
centre (``EYE_RADIUS_MM``): the gaze figure checks the measurement, not that assumption.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from real_clips import cost_over_lips, enrol_speaker  # noqa: E402

from articast.core.evaluation.upper import score_upper  # noqa: E402
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.live import LiveTracker  # noqa: E402
from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.model.build import invert  # noqa: E402
from articast.core.outputs.lips import lip_measures  # noqa: E402
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence  # noqa: E402
from articast.core.synthetic.upper import upper_sequence  # noqa: E402
from articast.core.tracking import kernels  # noqa: E402


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def track(speaker, frames, fps, photometric: bool = False, cost: bool = True):
    kernels.warm_up()
    live = LiveTracker(speaker, FaceFinder.load(threads=1), mediapipe_scheme(speaker.rig),
                       clock=time.perf_counter)
    live.upper.photometric = photometric
    step = live.upper.step
    spent = [0.0]

    def timed(*a, **k):
        c0 = time.process_time()
        out = step(*a, **k)
        spent[0] += time.process_time() - c0
        return out

    live.upper.step = timed  # type: ignore[method-assign]
    c0 = time.process_time()
    res = [live.track(f, i / fps) for i, f in enumerate(frames)]
    n = max(len(frames), 1)
    cpu = (time.process_time() - c0) * 1e3 / n
    over = cost_over_lips(speaker, frames, fps, first=cpu) if cost else {}
    return res, {"frame_cpu_ms": round(cpu, 3), "upper_cpu_ms": round(spent[0] * 1e3 / n, 3),
                 **over}


def corr(a, b) -> float | None:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None
    return round(float(np.corrcoef(a[ok], b[ok])[0, 1]), 4)


def score(res, truth, fps: float) -> dict:
    """The figures of ``articast evaluate --upper`` (core/evaluation/upper.py)."""
    return score_upper([r.upper for r in res], truth, fps)


def lips(res, speaker, true_model, seq) -> dict:
    ok = np.array([r.ok for r in res])
    ap, _ = lip_measures(speaker.model, np.array([r.alpha for r in res]))
    ap_true, _ = lip_measures(true_model, invert(true_model, seq.points))
    return {"ok": round(float(ok.mean()), 4), "aperture_r": corr(ap[ok], ap_true[ok]),
            "aperture_mae_mm": round(float(np.abs(ap - ap_true)[ok].mean()), 3)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-static", action="store_true",
                    help="skip the run with static eyes (the lips' unchanged check)")
    ap.add_argument("--photometric-closure", action="store_true",
                    help="the closure from the photometric measure on every frame, the "
                         "reader's frames too (the ablation of UpperTracker.photometric; the "
                         "default: the reader's lids on its frames, the photometric measure "
                         "between)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    sp = default_speaker(args.seed)
    true_model = sp.model()
    log("rendering the enrolment sentence (300 frames at 12 fps)")
    enrol = make_sequence(args.seed * 100 + 11, 300, 12.0, "desk", geometry=sp.geometry)
    enrol_up = upper_sequence(args.seed * 100 + 11, 300, 12.0)
    enrol_imgs = [sp.render(enrol.controls[i], enrol.pose(i), enrol.camera,
                            RenderOptions(seed=10_000 + i), enrol_up.frame(i))
                  for i in range(enrol.n_frames)]
    n = int(round(args.seconds * args.fps))
    log(f"rendering the test sentence ({n} frames at {args.fps:g} fps)")
    test = make_sequence(args.seed * 100 + 12, n, args.fps, "desk", geometry=sp.geometry)
    up = upper_sequence(args.seed * 100 + 12, n, args.fps)
    frames = [sp.render(test.controls[i], test.pose(i), test.camera,
                        RenderOptions(seed=20_000 + i), up.frame(i)) for i in range(n)]
    log("enrolling")
    speaker = enrol_speaker(enrol_imgs, 12.0, camera=enrol.camera, max_frames=None,
                            times=np.arange(300) / 12.0)
    log("tracking")
    res, cost = track(speaker, frames, args.fps, photometric=args.photometric_closure,
                      cost=not args.photometric_closure)
    out = {"seconds": args.seconds, "fps": args.fps, "enrolment": speaker.report.get("upper"),
           **score(res, up, args.fps), **cost, "lips": lips(res, speaker, true_model, test)}
    if not args.no_static:
        log("tracking the same sentence with static eyes (the lips' check)")
        static = [sp.render(test.controls[i], test.pose(i), test.camera,
                            RenderOptions(seed=20_000 + i)) for i in range(n)]
        res_s, _ = track(speaker, static, args.fps, cost=False)
        out["lips_static_eyes"] = lips(res_s, speaker, true_model, test)
    print(json.dumps(out, indent=1 if args.json else None))


if __name__ == "__main__":
    main()

"""How much articast's figures depend on which enrolment frames trained the speaker.

    python benchmarks/peers.py --json --series DIR           # once: the peers' series
    python benchmarks/enrolment_spread.py --series DIR [--seeds 1 2 3 4] [--only CLIP ...]
                                          [--variant V] [--offline [--single-reader]]

An enrolment trains the appearance on at most 90 frames chosen by farthest-point sampling in
the articulation space (core/faces/build.py, ``coverage_order``), started at the frame nearest
the clip's median posture. Any other start is an equally valid choice. Per clip, articast is
enrolled on the first 60 % as ``peers.py`` does, once with the default start and once per
``--seeds`` value (``BuildOptions.coverage_seed``), tracks the held-out 40 % live, and each
enrolment is scored as ``peers.py`` scores it: r against the consensus of the other methods
(their series read from DIR, the articast of that run left out), still-mouth jitter (% of
the outer lip width) on the windows ``peers.py`` chose (from the lip boxes in DIR), frames
ok, and on the synthetic speaker r against the truth. The spread (min, max, s.d. over the
enrolments) is the part of a single-enrolment figure that is the choice of frames, not the
method: a gap between articast and a peer smaller than it is not measured by one enrolment.
``--variant`` tracks with another live policy of ``peers.py``'s ablation (``peers.VARIANTS``):
two runs, with and without a change, compare it enrolment by enrolment (the same frames
train both). ``--offline`` scores the results smoothed with the frames after, as ``articast
track`` writes a recorded clip (``peers.py --offline``).

Accuracy does not depend on the machine's load. ~1-2 min per clip and enrolment on 2 cores.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import peers  # noqa: E402

from articast.core.faces.build import BuildOptions  # noqa: E402


def spread_of(values: list[float]) -> dict:
    v = np.array([x for x in values if x is not None and math.isfinite(x)], float)
    if len(v) == 0:
        return {}
    return {"min": round(float(v.min()), 4), "max": round(float(v.max()), 4),
            "mean": round(float(v.mean()), 4),
            "sd": round(float(v.std(ddof=1)), 4) if len(v) > 1 else None}


def run_clip(name: str, series: dict, seeds: list[int | None]) -> dict:
    c = peers.series_clip(name, series)
    enrol, held, fps, kw = c["enrol"], c["held"], c["fps"], c["kw"]
    others, windows = c["others"], c["windows"]
    rows = []
    for seed in seeds:
        peers.log(f"{name}: enrolment with coverage seed {seed}")
        got = peers.run_articast(enrol, held, fps, build=replace(BuildOptions(),
                                                                 coverage_seed=seed), **kw)
        if "error" in got:
            rows.append({"seed": seed, "error": got["error"]})
            continue
        scores = peers.score({**others, "articast": got["ratio"]}, windows)["articast"]
        row = {"seed": seed, "r": scores["consensus_r"], "jitter": scores["jitter_pct_width"],
               "lag": scores["lag_frames"], "ok": round(float(np.mean(got["found"])), 4)}
        if series["truth"] is not None:
            row["truth_r"] = peers._round(peers.pearson(got["ratio"], series["truth"])[0], 4)
        rows.append(row)
        peers.log(f"  {row}")
    good = [r for r in rows if "error" not in r]
    out = {"clip": name, "enrolments": rows, "still_windows": len(windows)}
    for key in ("r", "jitter", "ok", "truth_r"):
        if any(key in r for r in good):
            out[key] = spread_of([r.get(key) for r in good])
    return out


def main() -> None:
    ap = peers.series_parser(__doc__)
    ap.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4],
                    help="coverage seeds besides the default start (default 1 2 3 4)")
    peers.add_articast_options(ap)
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = ap.parse_args()
    peers.use_articast_options(args)
    cv2.setNumThreads(1)
    rows = []
    for name, s in peers.series_clips(args.series, args.only, clips=args.clips):
        rows.append(run_clip(name, s, [None, *args.seeds]))
    if args.json:
        print(json.dumps({"command": " ".join(sys.argv), "variant": args.variant,
                          "offline": args.offline, "single_reader": args.single_reader,
                          "seeds": [None, *args.seeds],
                          "clips": rows}, indent=1))
        return
    print("| clip | default start r / jitter | r min-max (s.d.) | jitter min-max (s.d.) "
          "| truth r min-max |")
    print("|---|---|---|---|---|")
    for row in rows:
        first = row["enrolments"][0]
        r, j, t = row.get("r", {}), row.get("jitter", {}), row.get("truth_r", {})
        print(f"| {row['clip']} | {first.get('r')} / {first.get('jitter')} | "
              f"{r.get('min')}-{r.get('max')} ({r.get('sd')}) | "
              f"{j.get('min')}-{j.get('max')} ({j.get('sd')}) | "
              f"{(str(t.get('min')) + '-' + str(t.get('max'))) if t else '-'} |")


if __name__ == "__main__":
    main()

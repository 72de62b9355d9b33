"""Can a session tell that the speaker folder is another person's? (issue 39, row 5)

Tracks the first frames of every clip with every stored speaker folder (``--speakers``: one
folder per clip, named as the clip, as ``peers.py --speakers`` keeps them) through the live
tracker, and prints per pair what an identity warning could read without a face-recognition
model: the appearance fit's robust residual over the folder's own enrolment level (the local
appearance model is the speaker's own), the fraction of frames tracked ``ok``, and the
reader's landmarks' offset from the fitted face over the enrolment's 99th percentile. A
measure that tells people apart must be lower on a clip's own folder (the diagonal; two
clips of one person count as one person) than on every other person's, by a margin one
threshold can take for every folder.

    python benchmarks/identity_check.py --speakers SP [--clips DIR] [--only A B ...] \\
        [--frames 40] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import CLIP_CACHE, clip_paths  # noqa: E402
from people import person  # noqa: E402


def log(msg: str) -> None:
    print(f"[identity {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def first_frames(path: Path, n: int) -> list[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    out: list[np.ndarray] = []
    while len(out) < n:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    cap.release()
    return out


def pair(speaker, finder, frames: list[np.ndarray], fps: float) -> dict:
    """The three measures of one speaker folder on one clip's frames."""
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    live = LiveTracker(speaker, finder, mediapipe_scheme(speaker.rig))
    resid, off, ok = [], [], 0
    for i, f in enumerate(frames):
        r = live.track(f, i / fps)
        ok += bool(r.ok)
        v = r.extra.get("robust_residual")
        if v is not None and np.isfinite(v):
            resid.append(float(v) / speaker.residual.median)
        o = r.extra.get("landmark_offset")
        if o is not None and np.isfinite(o):
            off.append(float(o) / live.point_model.offset_p99)
    return {"residual_x": float(np.median(resid)) if resid else None,
            "ok": ok / max(len(frames), 1),
            "offset_x_p99": float(np.median(off)) if off else None}


def separation(rows: dict[str, dict[str, dict]], key: str) -> dict:
    """Per folder: its own clips' measure, the lowest of other people's clips, and whether
    one threshold over all folders separates own from others (the residual grows with a
    stranger: own must be the lower)."""
    per = {}
    for sp, clips in rows.items():
        own = [v[key] for c, v in clips.items() if person(c) == person(sp) and v[key] is not None]
        other = [v[key] for c, v in clips.items() if person(c) != person(sp)
                 and v[key] is not None]
        if own and other:
            per[sp] = {"own_max": max(own), "other_min": min(other),
                       "margin": min(other) / max(own)}
    owns = [p["own_max"] for p in per.values()]
    others = [p["other_min"] for p in per.values()]
    return {"folders": per, "one_threshold_separates": bool(owns and others
                                                             and max(owns) < min(others)),
            "folders_own_lowest": sum(p["margin"] > 1.0 for p in per.values())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--speakers", type=Path, required=True,
                    help="the speaker folders, one per clip, named as the clip")
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE, help=f"default {CLIP_CACHE}")
    ap.add_argument("--only", nargs="+", help="these clips only (default: every clip with a "
                                              "speaker folder)")
    ap.add_argument("--frames", type=int, default=40, help="first frames tracked (default 40)")
    ap.add_argument("--json", action="store_true", help="print the JSON, not the table")
    args = ap.parse_args(argv)
    import cv2

    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.speaker import Speaker

    cv2.setNumThreads(1)
    paths = clip_paths(args.clips)
    names = [n for n in (args.only or sorted(paths)) if n in paths
             and (args.speakers / n / "speaker.json").is_file()]
    if len(names) < 2:
        raise SystemExit(f"identity_check: fewer than two clips of {args.clips} have a speaker "
                         f"folder in {args.speakers}")
    frames = {n: first_frames(paths[n], args.frames) for n in names}
    finder = FaceFinder.load(threads=1)
    rows: dict[str, dict[str, dict]] = {}
    for sp_name in names:
        speaker = Speaker.load(args.speakers / sp_name)
        rows[sp_name] = {}
        for clip in names:
            rows[sp_name][clip] = pair(speaker, finder, frames[clip], 25.0)
            log(f"{sp_name} on {clip}: {rows[sp_name][clip]}")
    out = {"command": " ".join(sys.argv), "frames": args.frames, "pairs": rows,
           "residual": separation(rows, "residual_x"),
           "offset": separation(rows, "offset_x_p99")}
    if args.json:
        print(json.dumps(out, indent=1))
        return
    print("| folder \\ clip | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for sp_name in names:
        cells = []
        for clip in names:
            v = rows[sp_name][clip]
            r = "–" if v["residual_x"] is None else f"{v['residual_x']:.2f}"
            cells.append(f"**{r}**" if person(clip) == person(sp_name) else r)
        print(f"| {sp_name} | " + " | ".join(cells) + " |")
    for key in ("residual", "offset"):
        s = out[key]
        print(f"{key}: own lowest on {s['folders_own_lowest']} of {len(s['folders'])} folders; "
              f"one threshold separates: {s['one_threshold_separates']}")


if __name__ == "__main__":
    main()

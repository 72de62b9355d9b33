"""Can a session tell that the speaker folder is another person's? (issue 39, row 5)

Every clip with a speaker folder (``--speakers``: one folder per clip, named as the clip, each
enrolled on the first 60 % of its clip, as ``peers.py --speakers`` keeps them) is read from
60 % on, where no enrolment saw it: its first ``--frames`` frames there, as a session's first
frames, by the finding landmarks (FaceLandmarker v2) and the live reader (FaceMesh v1) seeded
from them, as live tracking reads them. Each run of frames is compared with every folder's
face-geometry signature (:mod:`articast.core.faces.identity`): the folder's own, or for a
folder enrolled before the signature was stored, one made by the same function from the
frames of the clip's first 60 % (every k-th, at most ``--enrol-frames``).

A measure that tells people apart reads low on a folder's own person (its own clip, and the
other clip of the same person: ``people.py``) and high on everyone else's. Printed per
network: the two distributions; the warn rate on other people's folders at the threshold
that gives at most one false warning on own folders, and at none; the threshold chosen on
each half of the people (1.2 x the largest own distance there) checked on the other half;
the shipped :data:`~articast.core.faces.identity.WARN_DISTANCE` per folder.

    python benchmarks/identity_check.py --speakers SP [--clips DIR ...] [--only A B ...] \\
        [--frames 40] [--json] [--tracker-measures]

``--tracker-measures``: also the tracker's own measures of the first attempt (the appearance
fit's robust residual over the folder's enrolment level, the fraction of frames ``ok``, the
reader's landmark offset), on the clips' first frames through the live tracker: slow.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import CLIP_CACHE, SHARED_CLIPS, clip_paths, load_average  # noqa: E402
from people import half, person  # noqa: E402

MARGIN = 1.2
"""The threshold chosen on half of the people: this times the largest own distance there."""


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


def read_clip(path: Path, finder: Any, reader: Any, frames: int, enrol_frames: int
              ) -> dict[str, dict[str, np.ndarray]]:
    """The landmarks of one clip, {"enrol"|"held": {"v1"|"v2": (F, L, 3)}}: every k-th frame
    of its first 60 % (found afresh each), and its first ``frames`` frames from 60 % on
    (found, then followed as live tracking does, found again after a loss); the reader
    (v1) reads each frame in a crop grown from the finder's face."""
    import cv2

    from articast.core.faces.finder import reader_seed

    cap = cv2.VideoCapture(str(path))
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cut = int(0.6 * total)
    step = max(1, cut // max(enrol_frames, 1))
    out: dict[str, dict[str, list[np.ndarray]]] = {p: {"v1": [], "v2": []}
                                                   for p in ("enrol", "held")}
    prev = None
    i = 0
    while i < cut + frames:
        ok, img = cap.read()
        if not ok:
            break
        held = i >= cut
        if held or i % step == 0:
            face = finder.track(img, prev) if held and prev is not None else None
            if face is None:
                face = finder.find(img)
            prev = face
            if face is not None:
                part = out["held" if held else "enrol"]
                part["v2"].append(np.asarray(face.landmarks))
                got = reader.track(img, reader_seed(face))
                if got is not None:
                    part["v1"].append(np.asarray(got.landmarks))
        i += 1
    cap.release()
    return {p: {n: np.array(v).reshape(-1, 468 if n == "v1" else 478, 3)
                for n, v in nets.items()} for p, nets in out.items()}


def distances(names: list[str], sigs: dict[str, dict[str, Any]],
              held: dict[str, dict[str, np.ndarray]], net: str) -> dict[str, dict[str, float]]:
    """folder -> clip -> distance of the clip's held-out frames to the folder's signature."""
    from articast.core.faces.identity import distance

    rows: dict[str, dict[str, float]] = {}
    for sp in names:
        sig = sigs[sp].get(net)
        if sig is None:
            continue
        rows[sp] = {}
        for clip in names:
            d = distance(sig, held[clip][net])
            if d is not None:
                rows[sp][clip] = d
    return rows


def _own(sp: str, clip: str) -> bool:
    return person(sp) == person(clip)


def summary(rows: dict[str, dict[str, float]], shipped: float) -> dict[str, Any]:
    """The own and other distributions, the ROC-style figures, the halves and per folder."""
    own = sorted(v for sp, r in rows.items() for c, v in r.items() if _own(sp, c))
    other = sorted(v for sp, r in rows.items() for c, v in r.items() if not _own(sp, c))
    if not own or not other:
        return {}

    def caught(thr: float, sel: Any = None) -> dict[str, Any]:
        o = [v for sp, r in rows.items() for c, v in r.items()
             if _own(sp, c) and (sel is None or sel(sp))]
        t = [v for sp, r in rows.items() for c, v in r.items()
             if not _own(sp, c) and (sel is None or sel(sp))]
        return {"threshold": round(thr, 3), "false_warnings": sum(v > thr for v in o),
                "own_pairs": len(o), "caught": round(float(np.mean([v > thr for v in t])), 4)
                if t else None, "other_pairs": len(t)}

    halves = {}
    for h in "AB":
        train = [v for sp, r in rows.items() for c, v in r.items()
                 if _own(sp, c) and half(sp) == h]
        if train:
            thr = MARGIN * max(train)
            halves[f"chosen_on_{h}"] = {"own_max": round(max(train), 3),
                                        "check_on_other_half": caught(
                                            thr, lambda sp, h=h: half(sp) != h)}
    folders = {}
    for sp, r in rows.items():
        o = [v for c, v in r.items() if _own(sp, c)]
        t = [v for c, v in r.items() if not _own(sp, c)]
        if o and t:
            folders[sp] = {"own": [round(v, 3) for v in o], "other_min": round(min(t), 3),
                           "other_median": round(float(np.median(t)), 3),
                           "caught": round(float(np.mean([v > shipped for v in t])), 3)}
    return {
        "own": {"n": len(own), "min": round(own[0], 3), "median": round(own[len(own) // 2], 3),
                "max": round(own[-1], 3)},
        "other": {"n": len(other), "min": round(other[0], 3),
                  "p10": round(float(np.percentile(other, 10)), 3),
                  "median": round(float(np.median(other)), 3)},
        "at_most_one_false_warning": caught(own[-2] if len(own) > 1 else own[-1]),
        "no_false_warning": caught(own[-1]),
        "shipped": caught(shipped),
        "halves": halves,
        "folders": folders,
    }


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def _at(c: dict) -> str:
    return (f"{c['threshold']:.2f}: {c['false_warnings']} of {c['own_pairs']} own warned, "
            f"{_pct(c['caught'])} of {c['other_pairs']} others")


def markdown(out: dict[str, Any]) -> str:
    """The JSON's tables (docs/RESULTS.md's block; ``benchmarks/results.py`` reads it)."""
    nets = {n: r["summary"] for n, r in out["networks"].items() if r["summary"]}
    made = len(out.get("signatures_made_from_the_clip") or [])
    lines = [f"{len(out['clips'])} clips of {out['people']} people, the first {out['frames']} "
             f"frames from 60 % of each (no enrolment saw them) against every clip's "
             f"folder; {made} folders predate the stored signature: theirs made from their "
             f"clip's first 60 %. Distances in the folder's frame-to-frame spreads; the shipped "
             f"threshold {out['warn_distance']:.1f}.", "",
             "| network | own person (pairs: min / median / max) | other people (pairs: min / "
             "p10 / median) | at most one own warned | no own warned | shipped |",
             "|---|---|---|---|---|---|"]
    for n, s in nets.items():
        o, t = s["own"], s["other"]
        lines.append(f"| {n} | {o['n']}: {o['min']:.2f} / {o['median']:.2f} / {o['max']:.2f} | "
                     f"{t['n']}: {t['min']:.2f} / {t['p10']:.2f} / {t['median']:.2f} | "
                     f"{_at(s['at_most_one_false_warning'])} | {_at(s['no_false_warning'])} | "
                     f"{_at(s['shipped'])} |")
    lines += ["", f"Halves (`people.py`): the threshold chosen on one half ({MARGIN:g} x its "
                  "largest own distance), checked on the other.", "",
              "| network | chosen on | its own max | on the other half |", "|---|---|---|---|"]
    for n, s in nets.items():
        for k, v in s["halves"].items():
            lines.append(f"| {n} | {k.rsplit('_', 1)[1]} | {v['own_max']:.2f} | "
                         f"{_at(v['check_on_other_half'])} |")
    lines += ["", "| folder | " + " | ".join(f"{n} own | {n} others: min / median | {n} warned "
                                             f"at {out['warn_distance']:.1f}" for n in nets)
              + " |", "|---|" + "---|---|---|" * len(nets)]
    folders = sorted({f for s in nets.values() for f in s["folders"]})
    for f in folders:
        cells = []
        for s in nets.values():
            r = s["folders"].get(f)
            cells += (["–"] * 3 if r is None else
                      [", ".join(f"{v:.2f}" for v in r["own"]),
                       f"{r['other_min']:.2f} / {r['other_median']:.2f}", _pct(r["caught"])])
        lines.append(f"| {f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def tracker_measures(speakers: Path, names: list[str], paths: dict[str, Path],
                     frames: int) -> dict[str, dict[str, dict]]:
    """The first attempt's measures (the tracker's own) on the clips' first frames."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.speaker import Speaker

    finder = FaceFinder.load(threads=1)
    imgs = {n: first_frames(paths[n], frames) for n in names}
    rows: dict[str, dict[str, dict]] = {}
    for sp_name in names:
        speaker = Speaker.load(speakers / sp_name)
        rows[sp_name] = {}
        for clip in names:
            live = LiveTracker(speaker, finder, mediapipe_scheme(speaker.rig))
            resid, off, ok = [], [], 0
            for i, f in enumerate(imgs[clip]):
                r = live.track(f, i / 25.0)
                ok += bool(r.ok)
                v = r.extra.get("robust_residual")
                if v is not None and np.isfinite(v):
                    resid.append(float(v) / speaker.residual.median)
                o = r.extra.get("landmark_offset")
                if o is not None and np.isfinite(o):
                    off.append(float(o) / live.point_model.offset_p99)
            rows[sp_name][clip] = {
                "residual_x": float(np.median(resid)) if resid else None,
                "ok": ok / max(len(imgs[clip]), 1),
                "offset_x_p99": float(np.median(off)) if off else None}
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--speakers", type=Path, required=True,
                    help="the speaker folders, one per clip, named as the clip")
    ap.add_argument("--clips", type=Path, nargs="+",
                    default=[SHARED_CLIPS, Path.home() / ".cache/articast/clips"],
                    help=f"folders of clips (default {SHARED_CLIPS} and the fetched clips, "
                         f"{CLIP_CACHE} alone where only it exists)")
    ap.add_argument("--only", nargs="+", help="these clips only (default: every clip with a "
                                              "speaker folder)")
    ap.add_argument("--frames", type=int, default=40,
                    help="held-out frames compared, from 60 %% of the clip (default 40)")
    ap.add_argument("--enrol-frames", type=int, default=150,
                    help="frames of the first 60 %% a signature is made of, for a folder "
                         "without one (default 150)")
    ap.add_argument("--json", action="store_true", help="print the JSON, not the table")
    ap.add_argument("--tracker-measures", action="store_true",
                    help="also the first attempt's tracker measures (slow)")
    args = ap.parse_args(argv)
    import cv2

    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.identity import MIN_FRAMES, WARN_DISTANCE, signature
    from articast.core.faces.speaker import Speaker

    cv2.setNumThreads(1)
    t0 = time.time()
    load0 = load_average()
    paths: dict[str, Path] = {}
    for folder in args.clips:
        paths.update(clip_paths(folder))
    names = [n for n in (args.only or sorted(paths)) if n in paths
             and (args.speakers / n / "speaker.json").is_file()]
    finder = FaceFinder.load(threads=1)
    reader = FaceFinder.load(threads=1, landmarks="v1", detector=finder.detector_session)
    sigs: dict[str, dict[str, Any]] = {}
    held: dict[str, dict[str, np.ndarray]] = {}
    made = []
    for n in names:
        marks = read_clip(paths[n], finder, reader, args.frames, args.enrol_frames)
        if min(len(marks["held"]["v1"]), len(marks["held"]["v2"])) < MIN_FRAMES:
            log(f"{n}: fewer than {MIN_FRAMES} faces read in its held-out frames: left out")
            continue
        stored = Speaker.load(args.speakers / n).identity
        if not stored:
            made.append(n)
        sigs[n] = dict(stored) or {net: s for net in ("v1", "v2")
                                   if (s := signature(marks["enrol"][net], net)) is not None}
        held[n] = marks["held"]
        log(f"{n}: {len(marks['enrol']['v2'])} enrolment frames, "
            f"{len(marks['held']['v2'])} held-out; signature {'stored' if stored else 'made'}")
    names = [n for n in names if n in held]
    if len(names) < 2:
        raise SystemExit(f"identity_check: fewer than two clips of {args.clips} have a speaker "
                         f"folder in {args.speakers} and a face in their held-out frames")
    out: dict[str, Any] = {
        "command": " ".join(["python", "benchmarks/identity_check.py", *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load": [load0,
                                                                            load_average()],
        "seconds": round(time.time() - t0), "frames": args.frames, "clips": names,
        "people": len({person(n) for n in names}), "signatures_made_from_the_clip": made,
        "warn_distance": WARN_DISTANCE, "networks": {}}
    for net in ("v1", "v2"):
        rows = distances(names, sigs, held, net)
        out["networks"][net] = {"pairs": {sp: {c: round(v, 3) for c, v in r.items()}
                                          for sp, r in rows.items()},
                                "summary": summary(rows, WARN_DISTANCE)}
    if args.tracker_measures:
        out["tracker_measures"] = tracker_measures(args.speakers, names, paths, args.frames)
    print(json.dumps(out, indent=1) if args.json else markdown(out))

if __name__ == "__main__":
    main()

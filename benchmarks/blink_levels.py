"""The closure's levels on real blinks and open eyes, from ``blinks.py --json`` output (issue 38).

    python benchmarks/blink_levels.py RUN/blinks.json RUN/blinks_fetched.json [--levels]

Per clip with dlib's series: the confirmed blinks (``blink_review.json``) whose closure peaks
at >= 0.8 (the peak: the highest mean closure within ``TOLERANCE`` frames of the event), the
open eye's closure (its 95th percentile over the frames further than ``MARGIN`` frames from
every event of dlib's, confirmed or not, and from every unsure range), and precision and
recall against the confirmed events (as blinks.py counts them). Pooled over the clips and
over each half of the people (``benchmarks/people.py``).

``--levels``: the series of a run made without the session's levels (before issue 38's
``ClosureLevels``, or ``UpperTracker(levels=False)``) read through them, as a simulation: on
the two eyes' mean closure (the run records no more), where the tracker levels each eye.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from blink_review import REVIEW, confirmed  # noqa: E402
from people import half  # noqa: E402

from articast.core.evaluation.upper import BLINK_CLOSURE, blink_events, match_events  # noqa: E402
from articast.core.faces.upper import ClosureLevels  # noqa: E402

TOLERANCE = 2
MARGIN = 5
SHUT, OPEN = 0.8, 0.15


def levels(row: dict, cl: np.ndarray | None = None, review: dict | None = None) -> dict | None:
    """One clip's figures (``cl``: another closure series for the same frames, else the
    row's own)."""
    if "ear_ratio" not in row or "closure" not in row:
        return None
    if review is None:
        review = json.loads(REVIEW.read_text())
    if cl is None:
        cl = np.array([np.nan if v is None else v for v in row["closure"]], float)
    n, fps = len(cl), row["fps"]
    ours = blink_events(np.nan_to_num(cl) > BLINK_CLOSURE, fps)
    ref = [tuple(e) for e in row["ref"]]
    ours_c, ref_c = confirmed(row["clip"], ours, ref, review)
    prec, rec, _ = match_events(ours_c, ref_c, TOLERANCE, one_to_one=False)
    peaks = []
    for a, b in ref_c:
        w = cl[max(0, a - TOLERANCE):min(n, b + TOLERANCE)]
        peaks.append(float(np.nanmax(w)) if np.isfinite(w).any() else float("nan"))
    away = np.ones(n, bool)
    unsure = review.get("clips", {}).get(row["clip"], {}).get("unsure", [])
    for a, b, *_ in list(ref) + list(ref_c) + [tuple(u[:2]) for u in unsure]:
        away[max(0, a - MARGIN):min(n, b + MARGIN)] = False
    op = cl[away & np.isfinite(cl)]
    matched = sum(any(a < e + TOLERANCE and s < b + TOLERANCE for s, e in ref_c)
                  for a, b in ours_c)
    found = sum(any(a < e + TOLERANCE and s < b + TOLERANCE for a, b in ours_c)
                for s, e in ref_c)
    return {"clip": row["clip"], "half": half(row["clip"]), "events": len(ref_c),
            "ours": len(ours_c), "matched": matched, "found": found,
            "precision": prec, "recall": rec, "peaks": [round(p, 3) for p in peaks],
            "shut": sum(p >= SHUT for p in peaks),
            "open_p95": round(float(np.percentile(op, 95)), 3) if len(op) else None,
            "open_frames": int(len(op))}


def simulated(cl: np.ndarray) -> np.ndarray:
    """A closure series read through :class:`ClosureLevels` (NaN where none)."""
    lv, out = ClosureLevels(), np.full(len(cl), np.nan)
    for t, c in enumerate(cl):
        if np.isfinite(c):
            out[t] = lv.read(float(c))
    return out


def pooled(rows: list[dict]) -> dict:
    ours = sum(r["ours"] for r in rows)
    ev = sum(r["events"] for r in rows)
    return {"precision": round(sum(r["matched"] for r in rows) / ours, 3) if ours else None,
            "recall": round(sum(r["found"] for r in rows) / ev, 3) if ev else None,
            "events": ev, "shut": sum(r["shut"] for r in rows),
            "open_ok": sum(r["open_p95"] is not None and r["open_p95"] <= OPEN for r in rows),
            "open_clips": sum(r["open_p95"] is not None for r in rows),
            "false": ours - sum(r["matched"] for r in rows)}


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def table(rows: list[dict]) -> str:
    out = ["| clip | half | confirmed | peaks >= 0.8 | open p95 | precision | recall |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['clip']} | {r['half']} | {r['events']} | {r['shut']} / {r['events']}"
                   f" | {_f(r['open_p95'])} | {_f(r['precision'])} | {_f(r['recall'])} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--levels", action="store_true",
                    help="simulate the session's levels on a run made without them")
    args = ap.parse_args()

    def series(row: dict) -> np.ndarray | None:
        if not args.levels or "closure" not in row:
            return None
        return simulated(np.array([np.nan if v is None else v for v in row["closure"]], float))

    rows = [r for f in args.runs for row in json.loads(f.read_text())
            if (r := levels(row, series(row))) is not None]
    if args.json:
        print(json.dumps({"clips": rows, "pooled": pooled(rows)}, indent=1))
        return
    print(table(rows))
    for h in "AB":
        print(h, pooled([r for r in rows if r["half"] == h]))
    print("all", pooled(rows))


if __name__ == "__main__":
    main()

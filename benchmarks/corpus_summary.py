"""Issue 38's figures from ``benchmarks/peers.py --json`` runs: every clip, by half of the people.

    python benchmarks/peers.py --json --series DIR > run.json     # a run (any variant)
    python benchmarks/corpus_summary.py run.json [other.json ...] [--half A|B] [--json]

Per clip (the held-out 40 %): articast's live lip aperture r against the independent judge
(``peers.judge``: one vote per family outside FaceMesh's — OpenSeeFace, dlib, face-api.js), its
reader's (the FaceMesh v1 loop) and the best FaceMesh-family peer's against the same judge, the
gaps with their paired 95 % block-bootstrap intervals (``peers.against_reader``): *not worse*
when the interval reaches zero, *better* when its lower bound is above zero; still-mouth jitter
against the reader's, with its interval; the lag of articast's frame-to-frame changes behind the
reader's own and behind the judge's; the best single peer of any family (by its own judge r,
which for a FaceMesh-family peer is the same judge as articast's). ``synthetic`` (the rendered
speaker) keeps its truth r.

Pooled, per half of the people (``benchmarks/people.py``) and over all: the mean gap to the
reader over clips, and its 95 % interval by a bootstrap over *people* (a person's clips drawn
together), the count of clips worse / not worse / better. Several runs: one block each, in
the order given (e.g. the current design, then a variant).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from blink_review import confirmed  # noqa: E402
from people import half, person  # noqa: E402


def verdict(g: dict | None) -> str:
    if not g:
        return "–"
    lo, hi = g["ci95"]
    if lo is None or hi is None:
        return "?"
    return "better" if lo > 0 else ("worse" if hi < 0 else "not worse")


def _by(rd: dict, key: str) -> dict | None:
    """A gap of ``articast_vs_reader``, marked ``truth`` where the truth judged it (the
    rendered speaker, peers.py ``against_reader``)."""
    g = rd.get(key)
    return None if not g else {**g, "truth": rd.get("judge") == "truth"}


def clip_row(c: dict) -> dict:
    m = c["methods"]
    a = m.get("articast", {})
    rd = c.get("articast_vs_reader") or {}
    peers = {k: v for k, v in m.items() if k != "articast" and v.get("judge_r") is not None}
    best = max(peers, key=lambda k: peers[k]["judge_r"]) if peers else None
    return {"clip": c["clip"], "half": half(c["clip"]) if c["clip"] != "synthetic" else "-",
            "person": person(c["clip"]), "frames": c["held_out_frames"],
            "ok": a.get("ok"), "occluded": len(a.get("occluded_frames") or []),
            "articast": a.get("judge_r"), "reader": m.get("facemesh_v1", {}).get("judge_r"),
            "gap_reader": _by(rd, "r_vs_reader"), "gap_family": _by(rd, "r_vs_best_facemesh"),
            "jitter": a.get("jitter_pct_width"),
            "reader_jitter": m.get("facemesh_v1", {}).get("jitter_pct_width"),
            "jitter_gap": rd.get("jitter_vs_reader"),
            "lag_vs_reader": rd.get("lag_velocity_vs_reader"),
            "lag_vs_judge": a.get("judge_lag_velocity_frames"),
            "best_peer": best, "best_peer_r": peers[best]["judge_r"] if best else None,
            "consensus_r": a.get("consensus_r"), "truth_r": a.get("truth_r"),
            "reader_truth_r": m.get("facemesh_v1", {}).get("truth_r")}


def pooled(rows: list[dict], key: str = "gap_reader", resamples: int = 2000,
           seed: int = 0) -> dict:
    """Mean gap over the clips and its 95 % interval, people resampled."""
    got = [(r["person"], r[key]["gap"]) for r in rows if r.get(key)]
    if not got:
        return {}
    by: dict[str, list[float]] = {}
    for p, g in got:
        by.setdefault(p, []).append(g)
    people = list(by)
    rng = np.random.default_rng(seed)
    means = []
    for _ in range(resamples):
        pick = rng.integers(0, len(people), len(people))
        vals = [g for i in pick for g in by[people[i]]]
        means.append(float(np.mean(vals)))
    lo, hi = np.percentile(means, [2.5, 97.5])
    verdicts = [verdict(r[key]) for r in rows if r.get(key)]
    return {"mean": round(float(np.mean([g for _, g in got])), 4),
            "ci95": [round(float(lo), 4), round(float(hi), 4)], "clips": len(got),
            "people": len(people), **{v: verdicts.count(v)
                                      for v in ("worse", "not worse", "better")}}


FACEMESH_FAMILY = ("facemesh_v1", "facelandmarker_v2", "mediapipe")


def single_peer(rows: list[dict], clips: list[dict], resamples: int = 2000,
                seed: int = 0) -> dict:
    """Issue 38's goal, as it is worded: articast's pooled r against **the best single
    peer**, the one FaceMesh-family method (scored by the same judge) with the best mean r
    over the clips every one of them read; the mean of the per-clip r differences over the
    clips articast and that peer both read, its 95 % interval with people resampled (no
    per-clip verdicts: a per-clip interval is only computed against the reader and the
    per-clip best)."""
    by_clip = {c["clip"]: c["methods"] for c in clips}
    names = sorted({r["clip"] for r in rows})  # (sorted: a set's order changes with the
    # process's string hashing, and the people's order decides what the seeded resampling picks)
    both = [c for c in names
            if by_clip[c].get("articast", {}).get("judge_r") is not None
            and all(by_clip[c].get(p, {}).get("judge_r") is not None for p in FACEMESH_FAMILY)]
    if not both:
        return {}
    best = max(FACEMESH_FAMILY,
               key=lambda p: float(np.mean([by_clip[c][p]["judge_r"] for c in both])))
    person_of = {r["clip"]: r["person"] for r in rows}
    got = {c: by_clip[c]["articast"]["judge_r"] - by_clip[c][best]["judge_r"] for c in names
           if by_clip[c].get("articast", {}).get("judge_r") is not None
           and by_clip[c].get(best, {}).get("judge_r") is not None}
    by: dict[str, list[float]] = {}
    for c, g in got.items():
        by.setdefault(person_of[c], []).append(g)
    people = list(by)
    rng = np.random.default_rng(seed)
    means = [float(np.mean([g for i in rng.integers(0, len(people), len(people))
                            for g in by[people[i]]])) for _ in range(resamples)]
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"peer": best, "peer_r": round(float(np.mean([by_clip[c][best]["judge_r"]
                                                          for c in got])), 4),
            "articast_r": round(float(np.mean([by_clip[c]["articast"]["judge_r"]
                                               for c in got])), 4),
            "mean": round(float(np.mean(list(got.values()))), 4),
            "ci95": [round(float(lo), 4), round(float(hi), 4)], "clips": len(got),
            "people": len(people)}


def pools_of(rows: list[dict], clips: list[dict]) -> dict:
    """The pooled lines under a peers table: each half and all against the reader, all
    against the per-clip best FaceMesh-family peer, and all against the best single one."""
    real = [r for r in rows if r["clip"] != "synthetic"]
    pools = {h: pooled([r for r in real if r["half"] == h]) for h in ("A", "B")}
    pools["all"] = pooled(real)
    pools["all, to the best FaceMesh-family peer"] = pooled(real, "gap_family")
    pools["all, to the best single peer"] = single_peer(real, clips)
    return pools


def _f(x, nd=3) -> str:
    return "–" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def _g(g: dict | None) -> str:
    if not g:
        return "–"
    by = " by the truth" if g.get("truth") else ""
    return f"{g['gap']:+.3f} ({g['ci95'][0]:+.3f}..{g['ci95'][1]:+.3f}) {verdict(g)}{by}"


def _jv(g: dict | None) -> str:
    """The jitter gap's verdict (lower is better: *worse* when its interval is above 0)."""
    if not g:
        return ""
    lo, hi = g["ci95"]
    return "worse" if lo > 0 else ("better" if hi < 0 else "not worse")


def markdown(run: dict, rows: list[dict], pools: dict) -> str:
    head = ("| clip | half | ok | articast r | reader r | gap to reader (95 %) | gap to best "
            "FaceMesh (95 %) | best peer (r) | jitter (reader) | lag vs reader / judge | "
            "occluded | truth r (reader) |")
    out = [f"command: `{run.get('command')}`, variant {run.get('variant')}, offline "
           f"{run.get('offline')}, load {run.get('load_average')}", "", head,
           "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        out.append(f"| {r['clip']} | {r['half']} | {_f(r['ok'])} | {_f(r['articast'])} | "
                   f"{_f(r['reader'])} | {_g(r['gap_reader'])} | {_g(r['gap_family'])} | "
                   f"{r['best_peer']} ({_f(r['best_peer_r'])}) | {_f(r['jitter'])} "
                   f"({_f(r['reader_jitter'])}) {_jv(r['jitter_gap'])} | "
                   f"{_f(r['lag_vs_reader'])} / "
                   f"{_f(r['lag_vs_judge'])} | {r['occluded']} | {_f(r['truth_r'])} "
                   f"({_f(r['reader_truth_r'])}) |")
    out.append("")
    jv = [_jv(r["jitter_gap"]) for r in rows if r["clip"] != "synthetic" and r["jitter_gap"]]
    out.append(f"still-mouth jitter against the reader's: worse {jv.count('worse')}, not worse "
               f"{jv.count('not worse')}, better {jv.count('better')}")
    for name, p in pools.items():
        if p and "peer" in p:
            out.append(f"pooled {name} ({p['peer']}, mean r {p['peer_r']:.3f}; articast "
                       f"{p['articast_r']:.3f}): mean gap {p['mean']:+.4f} "
                       f"({p['ci95'][0]:+.4f}..{p['ci95'][1]:+.4f}, people resampled), "
                       f"{p['clips']} clips of {p['people']} people: "
                       f"{verdict(p)}")
        elif p:
            what = "" if "best" in name else " to the reader"
            out.append(f"pooled {name}: mean gap{what} {p['mean']:+.4f} "
                       f"({p['ci95'][0]:+.4f}..{p['ci95'][1]:+.4f}, people resampled), "
                       f"{p['clips']} clips of {p['people']} people: worse {p['worse']}, "
                       f"not worse {p['not worse']}, better {p['better']}")
    return "\n".join(out)


def _matched(a: list, b: list, tol: int = 2) -> int:
    """How many events of ``a`` overlap one of ``b`` within ``tol`` frames (blinks.py's
    ``match``: an event over several of the other's pieces is one)."""
    return sum(any(s < e2 + tol and s2 < e + tol for s2, e2 in b) for s, e in a)


def blink_rows(path: Path) -> tuple[list[str], dict]:
    """A ``benchmarks/blinks.py --json`` run: a markdown row per clip (articast's events,
    dlib's, precision and recall against dlib's events as they are and as confirmed by
    looking, ``blink_review.json``; each confirmed event's closure peak) and the pooled
    precision and recall (events summed over the clips with a reference); the open eyes'
    closure (frames where dlib's eye-aspect ratio is over 0.9 of its open eye's: median and
    95th percentile; the issue's bound for an open eye is 0.15) and how many confirmed blinks
    peak at 0.8 or more (a shut eye's bound)."""
    rows = json.loads(path.read_text())
    out = ["| clip | half | articast events | dlib events | precision | recall | confirmed "
           "blinks | precision (confirmed) | recall (confirmed) | closure peak at the "
           "confirmed blinks | open eyes' closure: median / p95 |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    tot = dict.fromkeys(("ours", "hit_ours", "ref", "hit_ref", "ours_c", "hit_ours_c",
                         "ref_c", "hit_ref_c", "peaks", "peaks_shut", "open_clips",
                         "open_p95_over"), 0)
    for r in rows:
        if "ref" not in r:
            out.append(f"| {r['clip']} | {half(r['clip'])} | {r.get('articast_events')} | "
                       f"– | – | – | – | – | – | {r.get('reference') or r.get('error', '')} "
                       f"| – |")
            continue
        ours, ref = [tuple(e) for e in r["ours"]], [tuple(e) for e in r["ref"]]
        ours_c, ref_c = confirmed(r["clip"], ours, ref)
        cl = np.array([np.nan if v is None else v for v in r.get("closure") or []])
        peaks = [float(np.nanmax(cl[max(a - 2, 0):b + 2])) if len(cl) and
                 np.isfinite(cl[max(a - 2, 0):b + 2]).any() else float("nan")
                 for a, b in ref_c]
        ear = np.array([np.nan if v is None else v for v in r.get("ear_ratio") or []])
        n = min(len(cl), len(ear))
        open_eye = cl[:n][(ear[:n] > 0.9) & np.isfinite(cl[:n])] if n else np.array([])
        if len(open_eye):
            med, p95 = np.median(open_eye), np.percentile(open_eye, 95)
            open_cell = f"{med:.2f} / {p95:.2f}"
            tot["open_clips"] += 1
            tot["open_p95_over"] += int(p95 > 0.15)
        else:
            open_cell = "–"
        tot["peaks"] += sum(np.isfinite(peaks))
        tot["peaks_shut"] += sum(1 for x in peaks if x >= 0.8)
        got = {"ours": len(ours), "hit_ours": _matched(ours, ref), "ref": len(ref),
               "hit_ref": _matched(ref, ours), "ours_c": len(ours_c),
               "hit_ours_c": _matched(ours_c, ref_c), "ref_c": len(ref_c),
               "hit_ref_c": _matched(ref_c, ours_c)}
        for k, v in got.items():
            tot[k] += v

        def ratio(a: str, b: str, g: dict = got) -> str:
            return _f(g[a] / g[b], 2) if g[b] else "–"

        out.append(f"| {r['clip']} | {half(r['clip'])} | {len(ours)} | {len(ref)} | "
                   f"{ratio('hit_ours', 'ours')} | {ratio('hit_ref', 'ref')} | {len(ref_c)} | "
                   f"{ratio('hit_ours_c', 'ours_c')} | {ratio('hit_ref_c', 'ref_c')} | "
                   f"{' '.join(f'{p:.2f}' for p in peaks)} | {open_cell} |")

    def pooled(a: str, b: str) -> float | None:
        return round(tot[a] / tot[b], 3) if tot[b] else None

    return out, {"precision": pooled("hit_ours", "ours"), "recall": pooled("hit_ref", "ref"),
                 "articast_events": tot["ours"], "reference_events": tot["ref"],
                 "precision_confirmed": pooled("hit_ours_c", "ours_c"),
                 "recall_confirmed": pooled("hit_ref_c", "ref_c"),
                 "confirmed_events": tot["ref_c"],
                 "confirmed_peaks_at_least_0.8": f"{tot['peaks_shut']} of {tot['peaks']}",
                 "open_eye_p95_over_0.15": f"{tot['open_p95_over']} of {tot['open_clips']} clips"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--half", choices=["A", "B"], help="only the clips of this half")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--blinks", type=Path, nargs="*", default=[],
                    help="benchmarks/blinks.py --json runs to summarise too")
    args = ap.parse_args()
    out = []
    for path in args.runs:
        run = json.loads(path.read_text())
        rows = [clip_row(c) for c in run["clips"]]
        if args.half:
            rows = [r for r in rows if r["half"] in (args.half, "-")]
        pools = pools_of(rows, run["clips"])
        if args.json:
            out.append({"run": str(path), "rows": rows, "pooled": pools})
        else:
            print(f"## {path}\n\n{markdown(run, rows, pools)}\n")
    for path in args.blinks:
        lines, total = blink_rows(path)
        if args.json:
            out.append({"blinks": str(path), "pooled": total})
        else:
            print(f"## {path}\n\n" + "\n".join(lines) + f"\n\npooled: {total}\n")
    if args.json:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""The corpus/model acceptance criteria over many speaker seeds, printed as JSON.

    python benchmarks/corpus_acceptance.py [--seeds 40]

For each seed: build_model on make_corpus(seed) (0.3 mm noise): cumulative variance (%),
median per-posture direct-inversion RMS (mm), |correlation| of each built parameter's scores
with its generating control; and the median RMS of the noiseless corpus (the speaker's own
non-linearity). Criteria: cumulative >= 95, median <= 0.6, |r| >= 0.9, noiseless median > 0.2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from articast.core.model.build import build_model, invert  # noqa: E402
from articast.core.model.face import PARAM_NAMES  # noqa: E402
from articast.core.synthetic import make_corpus  # noqa: E402


def one(seed: int) -> dict:
    corpus = make_corpus(seed)
    model, table = build_model(corpus)
    scores = invert(model, corpus.postures)
    corr = [abs(float(np.corrcoef(scores[:, k], corpus.controls[:, k])[0, 1]))
            for k in range(len(PARAM_NAMES))]
    _, clean = build_model(make_corpus(seed, noise_mm=0.0))
    return {"seed": seed, "cumulative_pct": float(table.cumulative_pct[-1]),
            "median_rms_mm": float(np.median(list(table.rms_mm_per_posture.values()))),
            "noiseless_median_rms_mm": float(np.median(list(clean.rms_mm_per_posture.values()))),
            "abs_corr": dict(zip(PARAM_NAMES, corr, strict=True))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    rows = [one(s) for s in range(ap.parse_args().seeds)]
    worst_corr = min(min(r["abs_corr"].values()) for r in rows)
    summary = {
        "seeds": len(rows),
        "cumulative_pct_min": round(min(r["cumulative_pct"] for r in rows), 2),
        "median_rms_mm_max": round(max(r["median_rms_mm"] for r in rows), 3),
        "noiseless_median_rms_mm_min": round(min(r["noiseless_median_rms_mm"] for r in rows), 3),
        "abs_corr_min": round(worst_corr, 3),
        "abs_corr_min_per_parameter": {
            n: round(min(r["abs_corr"][n] for r in rows), 3) for n in PARAM_NAMES},
    }
    summary["all_criteria_met"] = bool(
        summary["cumulative_pct_min"] >= 95 and summary["median_rms_mm_max"] <= 0.6
        and worst_corr >= 0.9 and summary["noiseless_median_rms_mm_min"] > 0.2)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()

"""The Markdown report of ``articast evaluate`` and its plots (matplotlib, optional)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

COLUMNS = ("rms_mm_mean", "rms_mm_median", "rms_mm_p95", "rms_points_mm_mean", "ok_fraction",
           "evals_per_frame", "ms_per_frame", "jitter_mm", "lag_frames")


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def write_report(result, cfg, out: Path, seconds: float, command: str) -> None:
    lines = [
        "# articast evaluation on the synthetic speaker", "",
        f"Reproduce: `{command}` ({seconds:.0f} s on this machine). Seed {cfg.seed}; "
        f"appearance trained on {cfg.train_frames} frames; {cfg.test_sequences} test "
        f"sequence(s) of {cfg.test_frames} frames at {cfg.fps:g} fps per condition.", "",
        "RMS 3D error: model geometry at the tracked articulation vs at the true one (direct "
        "inversion of the true 3D points), head frame, all model points, over the frames the "
        "tracker marked ok; `rms_points` compares with the true points themselves (adds the "
        "linear model's own error). Jitter: RMS frame-to-frame motion on still segments. "
        "Lag: cross-correlation peak of the lip-aperture curve (frames).", "",
    ]
    plots = _plots(result, out)
    for cond, per_model in result.figures.items():
        lines += [f"## {cond}", ""]
        extra = sorted({k for f in per_model.values() for k in f} - set(COLUMNS))
        cols = [c for c in COLUMNS if any(c in f for f in per_model.values())] + extra
        lines.append("| model | " + " | ".join(cols) + " |")
        lines.append("|---" * (len(cols) + 1) + "|")
        for model, f in per_model.items():
            lines.append(f"| {model} | " + " | ".join(_fmt(f.get(c)) for c in cols) + " |")
        lines.append("")
        for name in plots.get(cond, []):
            lines += [f"![{cond}]({name})", ""]
    if not plots:
        lines += ["(plots not drawn: install the 'report' extra, `pip install articast[report]`)",
                  ""]
    (out / "report.md").write_text("\n".join(lines))


def _plots(result, out: Path) -> dict[str, list[str]]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return {}
    made: dict[str, list[str]] = {}
    for cond, per_model in result.rms.items():
        names = [m for m in per_model if per_model[m].size]
        if not names:
            continue
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.boxplot([per_model[m] for m in names], showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=20)
        ax.set_ylabel("RMS 3D error (mm)")
        ax.set_title(f"{cond}: RMS 3D error per frame")
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        fname = f"{cond}_rms_boxplot.png"
        fig.savefig(out / fname, dpi=90)
        plt.close(fig)
        made.setdefault(cond, []).append(fname)
    for cond, per_model in result.series.items():
        if not per_model:
            continue
        fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
        first = next(iter(per_model.values()))
        axes[0].plot(first.t, first.width_true, "k-", lw=2, label="truth")
        axes[1].plot(first.t, first.aperture_true, "k-", lw=2, label="truth")
        for m, s in per_model.items():
            axes[0].plot(s.t, s.width, lw=1, label=m)
            axes[1].plot(s.t, s.aperture, lw=1, label=m)
            axes[2].plot(s.t, s.rms_mm, lw=1, label=m)
            axes[3].plot(s.t, s.evals, lw=1, label=m)
        for ax, lab in zip(axes, ("lip width (mm)", "lip aperture (mm)", "RMS 3D error (mm)",
                                  "evaluations / frame"), strict=True):
            ax.set_ylabel(lab)
            ax.grid(alpha=0.3)
        axes[3].set_yscale("log")
        axes[3].set_xlabel("time (s)")
        axes[0].legend(fontsize=7, ncol=3)
        axes[0].set_title(f"{cond}: first test sequence")
        fig.tight_layout()
        fname = f"{cond}_curves.png"
        fig.savefig(out / fname, dpi=80)
        plt.close(fig)
        made.setdefault(cond, []).append(fname)
    return made

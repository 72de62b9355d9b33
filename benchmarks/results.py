"""Every generated figure of docs/RESULTS.md, run and written by one command (issue 39).

    python benchmarks/results.py --run-dir RUN                    # run everything, write the page
    python benchmarks/results.py --run-dir RUN --only live blinks # some sections
    python benchmarks/results.py --run-dir RUN --from-stored      # the tables from RUN's JSON
    python benchmarks/results.py --list                           # the sections and commands

Each section runs one benchmark with the command docs/RESULTS.md states for it (``SECTIONS``),
one after the other (the machine is shared: nothing in parallel), and keeps in RUN what it
printed, ``RUN/NAME.json`` (the benchmark's own JSON, as it printed it: the scripts that
summarise it read it as before), its progress ``RUN/NAME.log`` and ``RUN/NAME.meta.json``: the
command, the date and time at start and end (UTC), the commit (``-dirty`` with uncommitted
changes) and the machine's load average (``uptime``'s three) at start and end. Then it
rewrites the generated parts of docs/RESULTS.md in place: every section's table stands
between ``<!-- results:NAME begin -->`` and ``<!-- results:NAME end -->``, headed by a line
naming the stored file, the command, date, commit and load; the prose around the markers is
left as it is. A page whose markers do not pair up is refused, unchanged.

``--from-stored`` runs nothing: the tables are made again from the JSON already in RUN (a
reviewer checks that the page matches the stored runs: ``git diff`` after it is empty). The
runs of issue 38 were stored before this script under other names (``final5.json`` ...):
``OLD_NAMES`` maps them; their date is the file's time (the run's end), their commit was
not recorded.

A section whose inputs are missing (the peers' environments of
``benchmarks/setup_peers.py``, a clips folder, the peers' series of the ``before`` run) is
skipped with one line on stderr, and its block says why; so is one whose benchmark fails
(its last line of stderr). Plots (the accuracy against the peers per clip, the blinks) are
drawn from the numbers alone into docs/results/ with matplotlib (``pip install
articast[report]``), skipped with one line where it is missing.

Sections, in the order they run (the first writes the peers' series the others score against):
``before`` / ``before_fetched`` (every method, the default before issue 38, ``--variant
cadence_3``, on the shared and on the fetched clips), ``live`` / ``live_fetched`` (articast's
default against the stored peers), ``offline``, ``blinks`` /
``blinks_fetched``, ``cost`` (articast and the FaceMesh v1 loop interleaved), ``identity``
(another person's speaker folder: ``identity_check.py``), then the first run
(``demo_start``, ``fresh_install``), the synthetic speaker (``evaluate``, ``upper_synthetic``,
``no_truth_path``, ``corpus_acceptance``, ``tracking_speed``), the face networks
(``network_speed``), the service (``latency``,
``fanout``, ``soak``, ``abuse_flood``), dense transfer (``transfer_speed``, ``scan_binding``,
``scan_avatar_latency``) and the delegate (``delegate_clips``) (their JSON shown as printed:
a key and value a row).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from common import SHARED_CLIPS  # noqa: E402

RESULTS = ROOT / "docs/RESULTS.md"
PLOTS = ROOT / "docs/results"
FETCHED_CLIPS = Path.home() / ".cache/articast/clips"
PEER_CACHE = Path.home() / ".cache/articast/peers"
MARKER = re.compile(r"^<!-- results:([A-Za-z0-9_.-]+) (begin|end) -->\s*$")
#: the cost run's clips (docs/RESULTS.md, "cost": four clips, three interleaved passes)
COST_CLIPS = ("styletalk_andrew_clip_1", "latentsync_demo3_video", "lia_obama",
              "edtalk_pose_source1")


def log(msg: str) -> None:
    print(f"[results {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Section:
    """One benchmark run and the block of docs/RESULTS.md it fills.

    ``args``: the script's arguments, with ``{run}`` (the run folder), ``{clips}`` (the shared
    clips), ``{fetched}`` (the fetched clips) filled in; ``kind``: how its output is
    tabulated (``peers``: ``corpus_summary.markdown``; ``blinks``:
    ``corpus_summary.blink_rows``; ``cost``: the interleaved passes; ``evaluate``: a row per
    condition and model; ``json``/``text``: as
    printed); ``needs``: what must be there before it runs."""

    name: str
    script: str
    args: tuple[str, ...]
    kind: str
    needs: tuple[str, ...] = ()
    plot: bool = False

    def argv(self, run: Path, clips: Path, fetched: Path) -> list[str]:
        # a script of benchmarks/, or a module of the product (``articast.*``: its CLI)
        head = (["-m", self.script] if self.script.startswith("articast.")
                else [f"benchmarks/{self.script}"])
        return head + [a.format(run=run, clips=clips, fetched=fetched) for a in self.args]


def _peers(clips: str, *extra: str) -> tuple[str, ...]:
    return ("--json", "--clips", clips, *extra)


SECTIONS: tuple[Section, ...] = (
    Section("before", "peers.py", _peers("{clips}", "--variant", "cadence_3", "--series",
                                         "{run}/series", "--speakers", "{run}/speakers",
                                         "--cpu-repeats", "0", "--grid", "{run}/before_grid"),
            "peers", ("clips", "peers")),
    Section("before_fetched", "peers.py",
            _peers("{fetched}", "--variant", "cadence_3", "--series", "{run}/series_fetched",
                   "--speakers", "{run}/speakers", "--cpu-repeats", "0", "--grid",
                   "{run}/before_grid_fetched"), "peers", ("fetched", "peers")),
    Section("live", "peers.py",
            _peers("{clips}", "--methods", "articast", "--others", "{run}/series",
                   "--speakers", "{run}/speakers", "--cpu-repeats", "0", "--grid",
                   "{run}/live_grid"), "peers", ("clips", "series"), plot=True),
    Section("live_fetched", "peers.py",
            _peers("{fetched}", "--methods", "articast", "--others", "{run}/series_fetched",
                   "--speakers", "{run}/speakers", "--cpu-repeats", "0", "--grid",
                   "{run}/live_grid_fetched"), "peers", ("fetched", "series_fetched"),
            plot=True),
    Section("offline", "peers.py",
            _peers("{clips}", "--offline", "--methods", "articast", "--others",
                   "{run}/series", "--speakers", "{run}/speakers", "--cpu-repeats", "0"),
            "peers", ("clips", "series")),
    # the opt-in stream of two readers (core/faces/two_readers.py), same speakers and peers
    Section("live_two_readers", "peers.py",
            _peers("{clips}", "--readers", "2", "--methods", "articast", "--others",
                   "{run}/series", "--speakers", "{run}/speakers", "--cpu-repeats", "0"),
            "peers", ("clips", "series")),
    Section("live_two_readers_fetched", "peers.py",
            _peers("{fetched}", "--readers", "2", "--methods", "articast", "--others",
                   "{run}/series_fetched", "--speakers", "{run}/speakers", "--cpu-repeats",
                   "0"), "peers", ("fetched", "series_fetched")),
    # (--upper-again: the eyes' references by the code that runs, whatever code enrolled
    # RUN/speakers for the lips)
    Section("blinks", "blinks.py", ("--json", "--clips", "{clips}", "--speakers",
                                    "{run}/speakers", "--upper-again", "--no-cost", "--grid",
                                    "{run}/blinks_grid"), "blinks", ("clips", "peers"),
            plot=True),
    Section("blinks_fetched", "blinks.py", ("--json", "--clips", "{fetched}", "--speakers",
                                            "{run}/speakers", "--upper-again", "--no-cost",
                                            "--grid",
                                            "{run}/blinks_grid_fetched"), "blinks",
            ("fetched", "peers"), plot=True),
    Section("cost", "peers.py",
            _peers("{clips}", "--only", *COST_CLIPS, "--methods", "articast", "facemesh_v1",
                   "--others", "{run}/series", "--speakers", "{run}/speakers"), "cost",
            ("clips", "series")),
    Section("cost_two_readers", "peers.py",
            _peers("{clips}", "--readers", "2", "--only", *COST_CLIPS, "--methods", "articast",
                   "facemesh_v1", "--others", "{run}/series", "--speakers", "{run}/speakers"),
            "cost", ("clips", "series")),
    # issue 39, row 5: another person's speaker folder (the folders peers.py enrolled)
    Section("identity", "identity_check.py", ("--json", "--speakers", "{run}/speakers2",
                                              "--clips", "{clips}", "{fetched}"), "identity",
            ("clips", "speakers2")),
    # the older benchmarks ("Figures moved from the README"), with the commands stated there
    Section("demo_start", "demo_start.py", ("--runs", "5", "--json", "--fresh-cache"), "json"),
    # the first-ever demo: an empty HOME and numba cache, this interpreter (issue 39)
    Section("fresh_install", "fresh_install.py", ("--here", "--json"), "json"),
    # the synthetic speaker's tracking accuracy, every condition and appearance model
    Section("evaluate", "articast.service.cli", ("evaluate", "--json", "-o",
                                                 "{run}/evaluation"), "evaluate"),
    # issue 39's subscribe flood: a bystander and /healthz against a no-attack baseline
    Section("abuse_flood", "abuse.py", ("flood", "--connections", "32", "--seconds", "10",
                                        "--json"), "json"),
    Section("upper_synthetic", "upper_synthetic.py", ("--seconds", "60", "--json"), "json"),
    Section("no_truth_path", "no_truth_path.py", ("--json", "--rigs", "desk"), "json"),
    Section("corpus_acceptance", "corpus_acceptance.py", (), "json"),
    Section("tracking_speed", "tracking_speed.py", (), "json"),
    # the bundled face networks' CPU per call (the readers' share of the two loops' cost)
    Section("network_speed", "network_speed.py", ("--json",), "json"),
    Section("latency", "latency.py", ("--json", "--subscribers", "1", "100"), "json"),
    Section("fanout", "fanout.py", ("--json", "--subscribers", "500", "--seconds", "20"),
            "json"),
    Section("soak", "soak.py", ("--json", "--seconds", "60"), "json"),
    Section("transfer_speed", "transfer_speed.py", (), "json"),
    # no --pictures: face images are never written into the repository
    Section("delegate_clips", "delegate_clips.py", ("--json",), "json", ("fetched",)),
    Section("scan_binding", "scan_binding.py", (), "json", ("scan",)),
    Section("scan_avatar_latency", "scan_avatar_latency.py", (), "json", ("scan",)),
)
BY_NAME = {s.name: s for s in SECTIONS}
#: the runs stored before this script (issue 38's RUN folder, /work/bench), by section
OLD_NAMES = {"live": "final5.json", "live_fetched": "final4_f.json",
             "blinks": "final4_blinks.json", "blinks_fetched": "final4_blinks_f.json",
             "offline": "offline4.json",
             "cost": "final5_cpu.json", "before": "base.json", "before_fetched": "base_f.json"}


class PageError(ValueError):
    """docs/RESULTS.md's markers do not pair up."""


# --- the page ------------------------------------------------------------------------------


def blocks(text: str) -> dict[str, tuple[int, int]]:
    """Each block's name -> (the begin marker's line index, the end marker's). Refuses
    (:class:`PageError`, one line) a begin without its end, an end without its begin, a
    block inside another and a name used twice."""
    found: dict[str, tuple[int, int]] = {}
    open_: tuple[str, int] | None = None
    for i, line in enumerate(text.split("\n")):
        m = MARKER.match(line)
        if not m:
            continue
        name, what = m.groups()
        if what == "begin":
            if open_:
                raise PageError(f"line {i + 1}: results:{name} begins inside results:"
                                f"{open_[0]} (begun on line {open_[1] + 1})")
            if name in found:
                raise PageError(f"line {i + 1}: results:{name} a second time")
            open_ = (name, i)
        else:
            if not open_ or open_[0] != name:
                raise PageError(f"line {i + 1}: results:{name} ends but "
                                + (f"results:{open_[0]} is open" if open_ else
                                   "was not begun"))
            found[name] = (open_[1], i)
            open_ = None
    if open_:
        raise PageError(f"line {open_[1] + 1}: results:{open_[0]} begins and never ends")
    return found


def rewrite(text: str, contents: dict[str, str]) -> tuple[str, list[str]]:
    """The page with each named block's lines replaced by ``contents[name]``; the names that
    have no block on the page. Everything outside the blocks is kept byte for byte."""
    where = blocks(text)
    lines = text.split("\n")
    for name in sorted(contents, key=lambda n: -where[n][0] if n in where else 0):
        if name not in where:
            continue
        begin, end = where[name]
        lines[begin + 1:end] = contents[name].split("\n")
    return "\n".join(lines), [n for n in contents if n not in where]


# --- the stored runs ------------------------------------------------------------------------


def stored(run: Path, name: str) -> Path | None:
    """The section's stored output: ``RUN/NAME.json``, or ``RUN/NAME.meta.json`` alone (a
    run that was skipped), else its old name."""
    for candidate in (f"{name}.json", f"{name}.meta.json", OLD_NAMES.get(name)):
        if candidate and (run / candidate).is_file():
            return run / candidate
    return None


def read_output(path: Path, kind: str) -> Any:
    """A benchmark's output: one JSON document, JSON lines (a list), or (``text``) the text."""
    text = path.read_text()
    if kind == "text":
        return text
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return [json.loads(line) for line in text.splitlines() if line.strip()]


def meta_of(path: Path, data: Any) -> dict:
    """What a stored run says of itself: its ``.meta.json`` beside it, else what the JSON
    holds (peers.py: the command and the load) and the file's time."""
    side = path.with_suffix(".meta.json")
    if side.is_file():
        return json.loads(side.read_text())
    meta: dict[str, Any] = {"date_end": dt.datetime.fromtimestamp(
        path.stat().st_mtime, dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "date_note": "the file's time, the run's end"}
    if isinstance(data, dict):
        if "command" in data:
            meta["command"] = data["command"]
        load = data.get("load_average")
        if isinstance(load, dict):
            meta["load_start"], meta["load_end"] = load.get("start"), load.get("end")
    return meta


def _shown(text: str, run: Path) -> str:
    """Paths of the run folder written as ``RUN`` (the page's name for it)."""
    for p in sorted({str(run.resolve()), str(run)}, key=len, reverse=True):
        text = text.replace(p.rstrip("/") + "/", "RUN/").replace(p, "RUN")
    return text


def _load(x: Any) -> str:
    return " ".join(f"{v:g}" for v in x) if isinstance(x, list) else "not recorded"


def provenance(meta: dict, name: str, run: Path) -> str:
    """The line under the block's heading: the command, date, commit and load."""
    cmd = meta.get("command")
    date = (f"{meta['date_start']} to {meta['date_end']}" if meta.get("date_start")
            else f"{meta.get('date_end', 'not recorded')}"
            + (f" ({meta['date_note']})" if meta.get("date_note") else ""))
    verb = "not run" if meta.get("skipped") else "ran"
    return (f"*{verb + ' `' + _shown(cmd, run) + '`' if cmd else 'command not recorded'}"
            f", {date}, commit {meta.get('commit') or 'not recorded'}, load (1, 5, 15 min) "
            f"{_load(meta.get('load_start'))} at start, {_load(meta.get('load_end'))} at end; "
            f"this table: `python benchmarks/results.py --run-dir RUN --from-stored --only "
            f"{name}`*")


# --- tables ---------------------------------------------------------------------------------


def peers_table(data: dict, run: Path) -> str:
    """``corpus_summary.py RUN/X.json``'s block, as it printed it."""
    import corpus_summary as cs

    rows = [cs.clip_row(c) for c in data["clips"]]
    return _shown(cs.markdown(data, rows, cs.pools_of(rows, data["clips"])), run)


def blinks_table(path: Path) -> str:
    """``corpus_summary.py --blinks RUN/X.json``'s block, as it printed it."""
    import corpus_summary as cs

    lines, total = cs.blink_rows(path)
    return "\n".join(lines) + f"\n\npooled: {total}"


def _spread(d: dict | None) -> str:
    if not d or d.get("median") is None:
        return "–"
    return f"{d['median']} ({d['min']}-{d['max']})"


def cost_table(data: dict) -> str:
    """The interleaved passes (``peers.py``'s ``interleaved`` and ``interleaved_lips``): per
    clip, articast's whole live face and its lips alone as CPU per frame over the FaceMesh v1
    loop's, median (min-max) of the passes, and the CPU ms per frame of each pass."""
    out = ["| clip | passes | whole face, CPU x v1 | lips alone, CPU x v1 | "
           "whole face CPU ms (passes) | FaceMesh v1 CPU ms (passes) | load at start |",
           "|---|---|---|---|---|---|---|"]
    for c in data["clips"]:
        a = c["methods"].get("articast", {})
        inter, lips = a.get("interleaved") or {}, a.get("interleaved_lips") or {}

        def ms(v: Any) -> str:
            return " / ".join(f"{x:.2f}" for x in v) if v else "–"

        out.append(f"| {c['clip']} | {inter.get('passes', '–')} | "
                   f"{_spread(inter.get('cpu_x_v1'))} | {_spread(lips.get('cpu_x_v1'))} | "
                   f"{ms(inter.get('cpu_ms'))} | {ms(inter.get('base_cpu_ms'))} | "
                   f"{_load(c.get('load_average_at_start'))} |")
    return "\n".join(out)


def evaluate_table(data: dict) -> str:
    """``articast evaluate --json``: a row per condition and model (RMS 3D error in mm:
    mean, median, p95; frames ok; evaluations and ms a frame; jitter; lag)."""
    cols = ("rms_mm_mean", "rms_mm_median", "rms_mm_p95", "ok_fraction", "evals_per_frame",
            "ms_per_frame", "jitter_mm", "lag_frames")
    out = ["| condition | model | mean mm | median mm | p95 mm | ok | evals/frame | ms/frame "
           "| jitter mm | lag |", "|---|---|---|---|---|---|---|---|---|---|"]
    for cond, models in data["conditions"].items():
        for model, f in models.items():
            out.append(f"| {cond} | {model} | " + " | ".join(
                f"{f[c]:.3g}" if isinstance(f.get(c), float) else _cell(f.get(c))
                for c in cols) + " |")
    return "\n".join(out)


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, list) and all(not isinstance(x, (dict, list)) for x in v):
        return " ".join(_cell(x) for x in v) if len(v) <= 12 else f"({len(v)} values)"
    if isinstance(v, (dict, list)):
        return "…"
    return "–" if v is None else str(v).replace("|", "\\|")


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def json_table(data: Any) -> str:
    """A benchmark's JSON as it printed it: a document as rows of key and value (nested keys
    joined with dots), a list of documents (JSON lines, one per configuration or clip) as one
    column per document."""
    items = data if isinstance(data, list) else [data]
    flats = [_flat(x) if isinstance(x, dict) else {"value": x} for x in items]
    keys = list(dict.fromkeys(k for f in flats for k in f))
    head = ["key", *(["value"] if len(flats) == 1 else
                     [str(f.get("clip") or f.get("subscribers") or i + 1)
                      for i, f in enumerate(flats)])]
    out = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    out += [f"| {k} | " + " | ".join(_cell(f.get(k)) for f in flats) + " |" for k in keys]
    return "\n".join(out)


def text_table(text: str) -> str:
    return f"```text\n{text.rstrip()}\n```"


# --- plots ----------------------------------------------------------------------------------


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_peers(data: dict, path: Path, title: str) -> bool:
    """r against the judge per clip: articast, its reader, the best single peer."""
    import corpus_summary as cs

    plt = _pyplot()
    if plt is None:
        return False
    rows = [r for r in (cs.clip_row(c) for c in data["clips"]) if r["articast"] is not None]
    fig, ax = plt.subplots(figsize=(7, 0.3 * len(rows) + 1.2))
    y = range(len(rows))
    for key, mark, label in (("articast", "o", "articast"), ("reader", "|", "its reader "
                             "(FaceMesh v1 loop)"), ("best_peer_r", "x", "best single peer")):
        ax.scatter([r[key] if r[key] is not None else float("nan") for r in rows], list(y),
                   marker=mark, label=label)
    return _finish(plt, fig, ax, [r["clip"] for r in rows], path, title,
                   "lip aperture r against the judge (held-out frames)", "lower left")


def plot_blinks(rows: list[dict], path: Path, title: str) -> bool:
    """Blink events per clip: articast's and dlib's, and how many of each matched."""
    plt = _pyplot()
    if plt is None:
        return False
    from blink_review import confirmed

    rows = [r for r in rows if "ref" in r]
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.2))
    y = list(range(len(rows)))
    bars = ((lambda r: len(r["ours"]), "articast's events"),
            (lambda r: len(r["ref"]), "dlib's events (eye aspect ratio)"),
            (lambda r: len(confirmed(r["clip"], [tuple(e) for e in r["ours"]],
                                     [tuple(e) for e in r["ref"]])[1]),
             "blinks confirmed by looking (blink_review.json)"))
    for k, (count, label) in enumerate(bars):
        ax.barh([i + (k - 1) * 0.27 for i in y], [count(r) for r in rows], height=0.27,
                label=label)
    return _finish(plt, fig, ax, [r["clip"] for r in rows], path, title,
                   "blink events on the held-out frames", "lower right")


def _finish(plt: Any, fig: Any, ax: Any, clips: list[str], path: Path, title: str,
            xlabel: str, legend: str) -> bool:
    """A per-clip plot's axes, labels and file (the same for every plot here)."""
    ax.set_yticks(list(range(len(clips))), clips, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel(xlabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc=legend)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return True


# --- a section ------------------------------------------------------------------------------


def block(section: Section, run: Path, plots: Path | None, page: Path) -> str:
    """The section's block from its stored run (or why there is none)."""
    path = stored(run, section.name)
    if path is None:
        return (f"### RUN/{section.name}.json\n\n*no stored run yet: `python "
                f"benchmarks/results.py --run-dir RUN --only {section.name}` runs it*")
    if path.name.endswith(".meta.json"):
        meta = json.loads(path.read_text())
        shown = f"RUN/{section.name}.json"
        return (f"### {shown}\n\n{provenance(meta, section.name, run)}\n\n"
                f"**skipped**: {meta.get('skipped', 'no output')}")
    shown = f"RUN/{path.name}"
    data = read_output(path, section.kind)
    meta = meta_of(path, data)
    if section.kind == "peers":
        table = peers_table(data, run)
    elif section.kind == "blinks":
        table = blinks_table(path)
    elif section.kind == "cost":
        table = cost_table(data)
    elif section.kind == "identity":
        import identity_check

        table = identity_check.markdown(data)
    elif section.kind == "evaluate":
        table = evaluate_table(data)
    elif section.kind == "text":
        table = text_table(data)
    else:
        table = json_table(data)
    out = [f"### {shown}", "", provenance(meta, section.name, run), "", table]
    if section.plot and plots is not None:
        png = plots / f"{section.name}.png"
        title = f"{shown}, {meta.get('date_end', '')}"
        made = (plot_peers(data, png, title) if section.kind == "peers"
                else plot_blinks(data, png, title))
        if not made:
            log(f"{section.name}: no plot (matplotlib is not installed: pip install "
                f"'articast[report]')")
        else:
            rel = os.path.relpath(png, page.parent)
            what = ("lip aperture r per clip: articast, its reader, the best peer"
                    if section.kind == "peers" else "blink events per clip")
            out += ["", f"![{what}]({rel})"]
    return "\n".join(out)


def missing(section: Section, run: Path, clips: Path, fetched: Path) -> str | None:
    """Why the section cannot run here, in one line (None: it can)."""
    from common import clip_paths

    for need in section.needs:
        if need == "clips" and not clip_paths(clips):
            return f"no clips in {clips} (--clips DIR: a folder of videos)"
        if need == "fetched" and not clip_paths(fetched):
            return (f"no clips in {fetched} (python tools/fetch_real_clips.py, or "
                    f"--fetched-clips DIR)")
        if need == "peers" and not (PEER_CACHE / "peers.json").is_file():
            return (f"no peer environments in {PEER_CACHE} (python "
                    f"benchmarks/setup_peers.py --openseeface-git GIT)")
        if need.startswith("series") and not (run / need).is_dir():
            src = "before" if need == "series" else "before_fetched"
            return f"no peers' series in RUN/{need} (run --only {src} first)"
        if need.startswith("speakers") and not (run / need).is_dir():
            return (f"no speaker folders in RUN/{need} (one per clip, named as the clip, "
                    f"as peers.py --speakers keeps them)")
        if need == "scan" and not (Path.home() / ".cache/articast/scans").is_dir():
            return "no scan in ~/.cache/articast/scans (python tools/fetch_scan.py)"
    return None


def commit() -> str | None:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "-uno"], cwd=ROOT, text=True,
                               capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("-dirty" if dirty else "")


def _now() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")


def _loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def execute(section: Section, run: Path, clips: Path, fetched: Path,
            spawn: Callable[..., Any] = subprocess.Popen) -> None:
    """Run the section's benchmark; its output, log and meta into RUN."""
    argv = section.argv(run, clips, fetched)
    meta: dict[str, Any] = {"section": section.name, "command": " ".join(
        shlex.quote(a) for a in argv), "commit": commit(), "date_start": _now(),
        "load_start": _loadavg()}
    out, side = run / f"{section.name}.json", run / f"{section.name}.meta.json"
    why = missing(section, run, clips, fetched)
    if why is None:
        log(f"{section.name}: {meta['command']} (load {_loadavg()})")
        last = ""
        with open(out.with_suffix(".tmp"), "w") as sink, \
                open(run / f"{section.name}.log", "w") as logf:
            proc = spawn([sys.executable, *argv], cwd=ROOT, stdout=sink,
                         stderr=subprocess.PIPE, text=True)
            for line in proc.stderr:
                logf.write(line)
                sys.stderr.write(f"  {section.name}| {line}")
                last = line.strip() or last
            code = proc.wait()
        if code == 0:
            out.with_suffix(".tmp").replace(out)
        else:
            why = f"{argv[0]} failed (exit {code}): {last or 'no message'}"
    if why is not None:
        log(f"{section.name}: skipped: {why}")
        meta["skipped"] = why
        out.with_suffix(".tmp").unlink(missing_ok=True)
        for old in (out, side):  # an earlier run of this section is kept, set aside
            if old.exists():
                old.replace(old.with_name(old.name.replace(section.name,
                                                           f"{section.name}.previous", 1)))
    meta.update(date_end=_now(), load_end=_loadavg())
    side.write_text(json.dumps(meta, indent=1) + "\n")
    if why is None:
        log(f"{section.name}: done, RUN/{out.name} (load {_loadavg()})")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run-dir", type=Path, help="the folder of the runs (RUN)")
    ap.add_argument("--only", nargs="+", metavar="SECTION", choices=list(BY_NAME),
                    help="these sections (default: all, in order)")
    ap.add_argument("--from-stored", action="store_true",
                    help="run nothing: the tables from the JSON already in RUN")
    ap.add_argument("--clips", type=Path, default=SHARED_CLIPS,
                    help=f"the corpus's clips (default {SHARED_CLIPS})")
    ap.add_argument("--fetched-clips", type=Path, default=FETCHED_CLIPS,
                    help=f"the clips tools/fetch_real_clips.py fetched (default "
                         f"{FETCHED_CLIPS})")
    ap.add_argument("--results", type=Path, default=RESULTS,
                    help="the page to rewrite (default docs/RESULTS.md)")
    ap.add_argument("--plots", type=Path, default=PLOTS,
                    help="where the plots go (default docs/results)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--list", action="store_true", help="the sections and their commands")
    args = ap.parse_args(argv)
    names = args.only or list(BY_NAME)
    if args.list:
        for s in SECTIONS:
            print(f"{s.name}: python "
                  + " ".join(s.argv(Path("RUN"), Path("CLIPS"), Path("FETCHED"))))
        return 0
    if args.run_dir is None:
        ap.error("--run-dir RUN is needed")
    run: Path = args.run_dir
    try:
        text = args.results.read_text()
        blocks(text)
    except OSError as e:
        print(f"results: cannot read {args.results}: {e.strerror}", file=sys.stderr)
        return 2
    except PageError as e:
        print(f"results: {args.results}: markers do not pair up, nothing written: {e}",
              file=sys.stderr)
        return 2
    if args.from_stored:
        if not run.is_dir() or not any(stored(run, n) for n in names):
            print(f"results: {run} holds none of the stored runs of {' '.join(names)}: "
                  f"nothing written", file=sys.stderr)
            return 2
    else:
        run.mkdir(parents=True, exist_ok=True)
        for name in names:
            execute(BY_NAME[name], run, args.clips, args.fetched_clips)
    plots = None if args.no_plots else args.plots
    contents, unreadable = {}, 0
    for name in names:
        if args.from_stored and stored(run, name) is None:
            # (a RUN folder may hold some sections only, as docs/results/run does: the others'
            # blocks are the tables an earlier RUN wrote, kept, not wiped)
            log(f"{name}: no stored run in {run}: its block is left as it was")
            continue
        try:
            contents[name] = block(BY_NAME[name], run, plots, args.results)
        except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError) as e:
            unreadable += 1  # (json.JSONDecodeError is a ValueError)
            log(f"{name}: {stored(run, name)} cannot be tabulated ({type(e).__name__}: "
                f"{e}): its block is left as it was")
            continue
        if stored(run, name) is None:
            log(f"{name}: no stored run in {run}")
    new, absent = rewrite(text, contents)
    for name in absent:
        log(f"{name}: no block <!-- results:{name} begin --> in {args.results}: not written")
    if new != text:
        args.results.write_text(new)
        log(f"{args.results}: rewrote {len(contents) - len(absent)} block(s)")
    else:
        log(f"{args.results}: unchanged")
    return 1 if unreadable else 0


if __name__ == "__main__":
    sys.exit(main())

"""Capture-to-screen latency of the VRM page against the avatar page, in the same run (issue 40:
"the VRM page's latency no worse than the current page's").

One in-process server replays a talking, blinking, looking-about recording made with an
enrolled speaker's own model (the synthetic speaker 4 by default: enrolled from its rendered
video by ``articast enroll``, no real person), tracked with that speaker's folder, so that the
session has a delegate and a VRM. Headless software-rendered Chromium (SwiftShader, the tests'
``tests/browser.py``) then opens, in turns A, B, A, B, ... (one browser at a time, each turn a
fresh browser):

* A: the avatar page ``/avatar/?session=talk`` (draws the speaker's textured delegate);
* B: the VRM page ``/vrm?session=talk`` (the speaker's own VRM, ``GET /api/sessions/talk/vrm``,
  as ``articast export-vrm`` writes it, driven by perfect sync).

Per turn, after the page shows its face and a settling time: the page's own latency per drawn
frame (``connect.js``'s ``noteLatency``: capture on the server -> drawn, wall clock), the rate
it received and drew frames, and the CPU time of its draw callback (``window.articast.drawMs``,
the page's own ``performance.now()`` around apply + render). Prints one JSON line per turn and
a summary: per page the pooled p50/p95 and the per-turn medians; the ratio VRM / avatar of the
p50 and p95 for each pair of turns (median and range over pairs).

    python benchmarks/page_latency.py SPEAKER_DIR [--turns 4] [--seconds 20] [--fps 30]
    python benchmarks/page_latency.py --make /tmp/spk4     # enrol speaker 4 there first

The machine's load changes what any page achieves (SwiftShader draws on the CPU): print
``uptime`` beside the figures; the ratio within a run is what the interleaving protects.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from articast.core.faces.speaker import Speaker  # noqa: E402
from articast.service.app import ServiceConfig  # noqa: E402
from articast.service.cli import main as cli  # noqa: E402
from articast.service.settings import ServerSettings  # noqa: E402
from articast.service.worker import SessionSpec  # noqa: E402
from tests.browser import Browser  # noqa: E402
from tests.service_helpers import ServerThread  # noqa: E402
from tests.test_vrm import _talking_recording  # noqa: E402

PAGES = {"avatar": ("/avatar/?session=talk", "window.articast.delegate.startsWith('textured')"),
         "vrm": ("/vrm?session=talk", "window.articast.vrm !== '' || window.articast.vrmError")}


def make_speaker(folder: Path) -> Path:
    """Speaker 4 enrolled as tests/conftest.py does (a 20 s desk clip at 6 fps)."""
    if not (folder / "speaker" / "delegate.npz").exists():
        assert cli(["synth", "sequence", "-o", str(folder / "clip"), "--seed", "4",
                    "--sentence", "40", "--rig", "desk", "--frames", "120", "--fps", "6"]) == 0
        assert cli(["enroll", str(folder / "clip" / "video.mp4"), "-o",
                    str(folder / "speaker"), "--quiet", "--json"]) == 0
    return folder / "speaker"


def turn(port: int, page: str, seconds: float, settle: float) -> dict:
    path, ready = PAGES[page]
    with Browser(f"http://127.0.0.1:{port}{path}") as b:
        b.wait_for("window.articast.rendered > 10", 120)
        b.wait_for(ready, 120)
        err = b.evaluate("window.articast.vrmError") if page == "vrm" else ""
        if err:
            raise RuntimeError(err)
        time.sleep(settle)
        skip = b.evaluate("window.articast.latencies.length")
        dskip = b.evaluate("(window.articast.drawMs || []).length")
        f0, d0, t0 = (b.evaluate("window.articast.frames"), b.evaluate("window.articast.rendered"),
                      time.monotonic())
        time.sleep(seconds)
        el = time.monotonic() - t0
        f1, d1 = b.evaluate("window.articast.frames"), b.evaluate("window.articast.rendered")
        lat = np.array(b.evaluate(f"window.articast.latencies.slice({skip})"), float)
        draw = np.array(b.evaluate(f"(window.articast.drawMs || []).slice({dskip})") or [], float)
        shown = b.evaluate("window.articast.drawn || window.articast.mode")
    out = {"page": page, "shows": shown, "received_hz": round((f1 - f0) / el, 1),
           "drawn_hz": round((d1 - d0) / el, 1), "frames": len(lat),
           "p50_ms": round(float(np.median(lat)), 1),
           "p95_ms": round(float(np.percentile(lat, 95)), 1),
           "load1": round(os.getloadavg()[0], 1)}
    if len(draw):
        out["draw_cpu_ms_p50"] = round(float(np.median(draw)), 1)
        out["draw_cpu_ms_p95"] = round(float(np.percentile(draw, 95)), 1)
    out["_lat"] = lat.tolist()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("speaker", type=Path, nargs="?", help="speaker folder with a delegate.npz")
    ap.add_argument("--make", type=Path, help="enrol the synthetic speaker 4 into this folder "
                    "(if not there yet) and use it")
    ap.add_argument("--turns", type=int, default=4, help="turns per page (A, B, A, B, ...)")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per turn")
    ap.add_argument("--settle", type=float, default=3.0)
    ap.add_argument("--fps", type=float, default=30.0, help="the replay's frame rate")
    args = ap.parse_args()
    folder = make_speaker(args.make) if args.make else args.speaker
    if folder is None:
        ap.error("give SPEAKER_DIR or --make DIR")
    speaker = Speaker.load(folder)
    with tempfile.TemporaryDirectory() as tmp:
        rec = _talking_recording(Path(tmp) / "talk.jsonl", speaker, frames=int(8 * args.fps),
                                 fps=args.fps)
        spec = SessionSpec("talk", f"replay-record:{rec}?loop=yes", processor="truth",
                           speaker=str(folder))
        config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,))
        runs: dict[str, list[dict]] = {"avatar": [], "vrm": []}
        with ServerThread(config) as srv:
            for i in range(args.turns):
                for page in ("avatar", "vrm"):
                    r = turn(srv.port, page, args.seconds, args.settle)
                    runs[page].append(r)
                    print(json.dumps({"turn": i, **{k: v for k, v in r.items()
                                                    if not k.startswith("_")}}), flush=True)
    summary: dict = {"fps": args.fps, "turns": args.turns, "seconds": args.seconds}
    for page, rs in runs.items():
        lat = np.concatenate([r["_lat"] for r in rs])
        summary[page] = {"p50_ms": round(float(np.median(lat)), 1),
                         "p95_ms": round(float(np.percentile(lat, 95)), 1),
                         "drawn_hz": [r["drawn_hz"] for r in rs],
                         "turn_p50_ms": [r["p50_ms"] for r in rs]}
    for q in ("p50_ms", "p95_ms"):
        ratio = [v[q] / a[q] for a, v in zip(runs["avatar"], runs["vrm"], strict=True)]
        summary[f"ratio_vrm_avatar_{q[:3]}"] = {"median": round(float(np.median(ratio)), 2),
                                               "min": round(min(ratio), 2),
                                               "max": round(max(ratio), 2)}
    hz = [v["drawn_hz"] / a["drawn_hz"] for a, v in zip(runs["avatar"], runs["vrm"], strict=True)]
    summary["ratio_vrm_avatar_drawn_hz"] = {"median": round(float(np.median(hz)), 2),
                                            "min": round(min(hz), 2), "max": round(max(hz), 2)}
    print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()

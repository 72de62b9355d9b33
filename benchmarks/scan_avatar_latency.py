"""Latency of the browser avatar drawing the textured head scan vs the dense face: real
headless, software-rendered Chromium (SwiftShader) against ``articast replay-record`` streaming
the synthetic speaker (seed 1, the demo's) talking at 60 Hz, once without ``--scan`` (the
dense face, today's page) and once with menpo3d's james bound to that speaker. Latency =
capture on the server -> drawn in the page (the page's own figure, wall clock, one host).

    python tools/fetch_scan.py
    python benchmarks/scan_avatar_latency.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from articast.core.synthetic import default_speaker  # noqa: E402
from articast.service.cli import main as cli  # noqa: E402
from tests.browser import Browser  # noqa: E402
from tests.test_avatar_latency import talking_recording  # noqa: E402


def run(rec: Path, scan: Path | None, seconds: float) -> dict:
    cmd = [sys.executable, "-m", "articast.service.cli", "replay-record", str(rec), "--loop",
           "--port", "0", "--json", "--name", "talk"] + (["--scan", str(scan)] if scan else [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if not line:
            raise SystemExit("the server did not start")
        url = json.loads(line)["avatar"]
        with Browser(url) as b:
            want = "scan" if scan else "dense"
            b.wait_for(f"window.articast.mesh.startsWith('{want}')", 120)
            time.sleep(2.0)
            skip = b.evaluate("window.articast.latencies.length")
            drawn0, t0 = b.evaluate("window.articast.rendered"), time.monotonic()
            time.sleep(seconds)
            drawn = (b.evaluate("window.articast.rendered") - drawn0) / (time.monotonic() - t0)
            lat = np.array(b.evaluate(f"window.articast.latencies.slice({skip})"), float)
            mesh = b.evaluate("window.articast.mesh")
    finally:
        proc.terminate()
        proc.wait(20)
    return {"mesh": mesh, "drawn_per_s": round(drawn, 1),
            "latency_median_ms": round(float(np.median(lat)), 1),
            "latency_p95_ms": round(float(np.percentile(lat, 95)), 1), "samples": len(lat)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path, default=Path.home() / ".cache/articast/scans")
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        default_speaker(1).model().save(d / "speaker.npz")
        with open(os.devnull, "w") as quiet:
            sys.stdout, out = quiet, sys.stdout
            try:
                code = cli(["bind-dense", str(args.scan / "james.obj"), "--landmarks",
                            str(args.scan / "james.ljson"), "--model", str(d / "speaker.npz"),
                            "-o", str(d / "james.npz")])
            finally:
                sys.stdout = out
        if code:
            raise SystemExit("bind-dense failed (run python tools/fetch_scan.py first?)")
        rec = talking_recording(d / "talk.jsonl")
        rows = {"dense face (today)": run(rec, None, args.seconds),
                "textured scan": run(rec, d / "james.npz", args.seconds)}
    print(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()

"""How long ``articast demo`` takes to show a face: start -> URL printed -> first frame.

Each run is a cold start of the command (a new Python process, nothing imported, no server
running); the speaker's cached model and appearance (``~/.cache/articast``, or
``$ARTICAST_CACHE_DIR``) are what the first run of a machine leaves behind. ``--fresh-cache``
adds one run with an empty cache (what a user sees the very first time). The first frame is
the first ``frame`` message a WebSocket subscriber receives; the subscriber connects as soon as
the URL is printed (the URL is printed once the session streams).

    python benchmarks/demo_start.py --runs 5 --json

The same run times a baseline, the cold start of ``articast --help`` (a new Python process
importing the CLI, nothing served), between the demo's starts: ``first_frame_over_baseline``
is the demo's first frame as a multiple of it, a figure that moves less with the machine's
load than seconds do; the load averages before and after are in the output.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


async def _first_frame(url: str, timeout: float) -> None:
    import websockets

    async with websockets.connect(url, open_timeout=timeout) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "demo"}))
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), timeout))
            if msg["type"] == "frame":
                return


def one_start(env: dict[str, str], timeout: float = 120.0) -> dict[str, float]:
    """Seconds from ``Popen`` to the printed URL and to the first frame received."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "demo", "--port", "0",
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env=env)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if not line:
            raise RuntimeError("articast demo printed nothing")
        t_url = time.monotonic() - t0
        asyncio.run(_first_frame(json.loads(line)["url"], timeout))
        return {"url_s": t_url, "first_frame_s": time.monotonic() - t0}
    finally:
        proc.terminate()
        proc.wait(30)


def baseline_start() -> float:
    """Seconds for a cold ``articast --help``: the interpreter and the CLI's imports."""
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "articast.service.cli", "--help"],
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, timeout=120)
    return time.monotonic() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="cold starts to time (default 5)")
    ap.add_argument("--fresh-cache", action="store_true",
                    help="also time one start with an empty cache (trains the appearance)")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args()
    from common import load_average

    env = dict(os.environ)
    out: dict[str, object] = {"load_average_before": load_average()}
    if args.fresh_cache:
        with tempfile.TemporaryDirectory() as d:
            out["fresh_cache"] = one_start({**env, "ARTICAST_CACHE_DIR": d})
    one_start(env)  # fills the cache if empty; not counted
    runs, base = [], []
    for _ in range(args.runs):  # interleaved: load that comes and goes hits both
        base.append(baseline_start())
        runs.append(one_start(env))
    first = [r["first_frame_s"] for r in runs]
    out.update({
        "runs": runs,
        "first_frame_median_s": statistics.median(first),
        "first_frame_max_s": max(first),
        "first_frame_min_s": min(first),
        "url_median_s": statistics.median(r["url_s"] for r in runs),
        "baseline_help_median_s": statistics.median(base),
        "first_frame_over_baseline": statistics.median(first) / statistics.median(base),
        "target_s": 3.0,
        "cpus": os.cpu_count(),
        "load_average_after": load_average(),
    })
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            print(f"{k}: {v}")


if __name__ == "__main__":
    main()

"""Soak: end to end at 60 fps for a bounded time; fps sustained, server memory flat.

    python benchmarks/soak.py --json --seconds 120                      # synthetic speaker
    python benchmarks/soak.py --json --seconds 120 --source recording   # no articast.core.synthetic

The server runs in a subprocess with the given source; a few subscribers read everything.
Reports the tracked fps (from /metrics), capture drops, the server's RSS at the start of the
measured window and at the end, and the RSS slope fitted over the window (MB/min), and the
load averages before and after. With the synthetic source, whose renderer bounds the rate, the
same run times the renderer alone in this process for 5 s before the server starts and 5 s
after it stops (``render_only_fps``, both): the soak's fps is stated as a fraction of their
mean (``fps_over_render_only``), which moves less with the load than fps do.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

import numpy as np
from common import Server, load_average, make_recording


async def readers(url: str, n: int, seconds: float) -> list[int]:
    import websockets

    async def one() -> int:
        got = 0
        async with websockets.connect(url, compression=None, close_timeout=1) as ws:
            await ws.send(json.dumps({"type": "subscribe", "session": "soak",
                                      "streams": ["articulatory", "pose", "mesh"]}))
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                try:
                    m = await asyncio.wait_for(ws.recv(), 1.0)
                except TimeoutError:
                    continue
                got += m.startswith('{"type":"frame"') if isinstance(m, str) else 1
        return got

    return list(await asyncio.gather(*(one() for _ in range(n))))


def render_only_fps(seconds: float) -> float:
    """Frames per second of the synthetic source alone (rendering, no tracking, no server),
    in this process: the bound the synthetic soak runs against."""
    from articast.service.sources import make_source

    src = make_source("synthetic:seed=3&fps=1000&loop=yes")
    src.open()
    try:
        src.read()  # the first frame builds the speaker
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            src.read()
            n += 1
        return n / (time.monotonic() - t0)
    finally:
        src.close()


def metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + "{") or line.startswith(name + " "):
            return float(line.split()[-1])
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--warmup", type=float, default=10.0)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--subscribers", type=int, default=4)
    ap.add_argument("--source", choices=("synthetic", "recording"), default="synthetic")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.source == "synthetic":
        uri = f"synthetic:seed=3&fps={args.fps:g}&loop=yes"
    else:
        uri = f"replay-record:{make_recording(int(args.fps * 30), args.fps)}?loop=yes"
    import httpx

    load_before = load_average()
    render_fps = [render_only_fps(5)] if args.source == "synthetic" else []
    with Server({"soak": uri}) as srv:
        srv.wait_running(60)
        total = args.warmup + args.seconds

        async def run() -> tuple[list[int], list[tuple[float, float]], dict]:
            samples: list[tuple[float, float]] = []
            task = asyncio.create_task(readers(srv.url, args.subscribers, total))
            t0 = time.monotonic()
            m0: dict = {}
            while not task.done():
                await asyncio.sleep(1.0)
                t = time.monotonic() - t0
                if t >= args.warmup:
                    if not m0:
                        text = httpx.get(srv.http + "/metrics", timeout=5).text
                        m0 = {"frames": metric(text, "articast_frames_total"), "t": t}
                    samples.append((t, srv.rss_mb()))
            return await task, samples, m0

        got, samples, m0 = asyncio.run(run())
        text = httpx.get(srv.http + "/metrics", timeout=5).text
        t_end = samples[-1][0]
        frames = metric(text, "articast_frames_total") - m0["frames"]
        ts, rss = np.array(samples).T
        slope = float(np.polyfit(ts / 60.0, rss, 1)[0]) if len(ts) > 2 else float("nan")
        r = {"source": uri.split("?")[0].split(":")[0], "seconds": round(t_end - m0["t"], 1),
             "fps": round(frames / (t_end - m0["t"]), 2), "target_fps": args.fps,
             "source_dropped": metric(text, "articast_source_dropped_total"),
             "subscriber_drops": metric(text, "articast_subscriber_dropped_total"),
             "frames_per_subscriber": got,
             "rss_start_mb": round(float(rss[0]), 1), "rss_end_mb": round(float(rss[-1]), 1),
             "rss_max_mb": round(float(rss.max()), 1), "rss_slope_mb_per_min": round(slope, 3),
             "load_average_before": load_before, "load_average_after": load_average()}
    if render_fps:  # after the server has stopped: the renderer alone again
        render_fps.append(render_only_fps(5))
        r["render_only_fps"] = [round(x, 2) for x in render_fps]
        r["fps_over_render_only"] = round(r["fps"] / float(np.mean(render_fps)), 3)
    print(json.dumps(r) if args.json else r, flush=True)


if __name__ == "__main__":
    main()

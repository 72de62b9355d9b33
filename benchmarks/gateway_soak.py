"""Soak through a gateway: redis-server + 1 track-worker + 1 gateway, bounded time.

    python benchmarks/gateway_soak.py --json --seconds 600

The worker replays a 60 fps recording (loop=yes); ``--subscribers`` clients read everything
through the gateway. Reports the gateway's and the worker's RSS at the start of the measured
window and at the end, the change in percent, the RSS slope fitted over the window
(MB/min), frames delivered, the session's restarts (must stay 0) and the worker process's
restarts as the gateway's API reports them.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

import numpy as np
from common import make_recording
from redis_scaleout import articast, free_port, start_redis


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


async def readers(url: str, n: int, seconds: float) -> list[int]:
    import websockets

    async def one() -> int:
        got = 0
        async with websockets.connect(url, compression=None, close_timeout=1,
                                      max_size=2**24) as ws:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--warmup", type=float, default=15.0)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--subscribers", type=int, default=8)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rec = make_recording(frames=int(args.fps * 60), fps=args.fps, n_points=500)
    port = free_port()
    url = f"redis://127.0.0.1:{port}/0"
    redis = start_redis(port)
    worker = articast("track-worker", "--hub", url, "--json",
                      "--source", f"soak=replay-record:{rec}?loop=yes")
    gateway = None
    try:
        json.loads(worker.stdout.readline())
        gateway = articast("gateway", "--hub", url, "--port", "0", "--json", "--log-level",
                           "error")
        ws_url = json.loads(gateway.stdout.readline())["url"]
        http = ws_url.replace("ws://", "http://").rsplit("/ws", 1)[0]
        time.sleep(2.5)
        samples: list[tuple[float, float, float]] = []

        async def sample() -> None:
            t_end = time.monotonic() + args.warmup + args.seconds
            await asyncio.sleep(args.warmup)
            while time.monotonic() < t_end:
                samples.append((time.monotonic(), rss_mb(gateway.pid), rss_mb(worker.pid)))
                await asyncio.sleep(5.0)

        async def run() -> list[int]:
            got, _ = await asyncio.gather(
                readers(ws_url, args.subscribers, args.warmup + args.seconds), sample())
            return got

        got = asyncio.run(run())
        import httpx

        sessions = httpx.get(http + "/api/sessions", timeout=10).json()
    finally:
        for p in (gateway, worker):
            if p is not None:
                p.terminate()
                p.wait(15)
        redis.kill()
        redis.wait()
    t = np.array([s[0] for s in samples])
    out = {"seconds": args.seconds, "subscribers": args.subscribers, "source_fps": args.fps,
           "frames_per_subscriber": got, "samples": len(samples)}
    for i, role in ((1, "gateway"), (2, "worker")):
        rss = np.array([s[i] for s in samples])
        slope = float(np.polyfit((t - t[0]) / 60.0, rss, 1)[0]) if len(t) > 1 else 0.0
        out[f"{role}_rss_mb_start"] = round(float(rss[0]), 1)
        out[f"{role}_rss_mb_end"] = round(float(rss[-1]), 1)
        out[f"{role}_rss_mb_max"] = round(float(rss.max()), 1)
        out[f"{role}_rss_change_pct"] = round(100 * (rss[-1] - rss[0]) / rss[0], 2)
        out[f"{role}_rss_slope_mb_per_min"] = round(slope, 3)
    s = sessions[0] if sessions else {}
    out["session_state"], out["session_restarts"] = s.get("state"), s.get("restarts")
    print(json.dumps(out) if args.json else json.dumps(out, indent=2), flush=True)


if __name__ == "__main__":
    main()

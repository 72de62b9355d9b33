"""Latency the service adds: frame tracked (worker) -> message received by a subscriber.

A server subprocess replays a ground-truth recording at 60 fps through the truth processor;
N subscribers in this process (one asyncio loop, uvloop if installed) stamp each frame on
arrival. Latency = arrival (time.time) - t_tracked (server clock, same host). Reported per
configuration, one JSON object per line with --json:

    python benchmarks/latency.py --json
    python benchmarks/latency.py --json --subscribers 1 10 100 --seconds 10 --encoding binary
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

from common import Server, make_recording, percentile


async def subscriber(url: str, encoding: str, stop_at: float, warmup_until: float,
                     lat: list[float], drops: list[int]) -> None:
    import websockets

    from service import protocol as P

    async with websockets.connect(url, max_size=2**22, compression=None) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "bench",
                                  "streams": ["articulatory", "pose"], "encoding": encoding}))
        sids: dict[int, str] = {}
        names: dict[int, list[str]] = {}
        dropped = 0
        while True:
            data = await ws.recv()
            now = time.time()
            if isinstance(data, bytes):
                f = P.decode_frame_binary(data, sids, names)
                t_tracked, dropped = f.t_tracked, f.dropped
            else:
                m = json.loads(data)
                if m["type"] == "hello":
                    sids[m["sid"]], names[m["sid"]] = m["session"], m["param_names"]
                    continue
                if m["type"] != "frame":
                    continue
                t_tracked, dropped = m["t_tracked"], m["dropped"]
            if now >= warmup_until:
                lat.append((now - t_tracked) * 1000.0)
            if now >= stop_at:
                break
        drops.append(dropped)


async def measure(url: str, n: int, seconds: float, encoding: str) -> dict:
    lat: list[float] = []
    drops: list[int] = []
    t0 = time.time()
    tasks = [subscriber(url, encoding, t0 + 2.0 + seconds, t0 + 2.0, lat, drops)
             for _ in range(n)]
    await asyncio.gather(*tasks)
    return {"subscribers": n, "rate_hz": round(len(lat) / n / seconds, 1),
            "encoding": encoding, "samples": len(lat),
            "p50_ms": round(percentile(lat, 50), 3), "p90_ms": round(percentile(lat, 90), 3),
            "p99_ms": round(percentile(lat, 99), 3), "max_ms": round(max(lat), 3),
            "drops": sum(drops)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--subscribers", type=int, nargs="+", default=[1, 100])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--encoding", choices=("json", "binary"), default="json")
    ap.add_argument("--worker", choices=("auto", "thread", "process"), default="auto")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass
    rec = make_recording(frames=int(args.fps * 20), fps=args.fps)
    with Server({"bench": f"replay-record:{rec}?loop=0"}, "--worker", args.worker) as srv:
        srv.wait_running()
        for n in args.subscribers:
            r = asyncio.run(measure(srv.url, n, args.seconds, args.encoding))
            r.update(source_fps=args.fps, worker=args.worker)
            print(json.dumps(r) if args.json else
                  f"{n:4d} subscribers: p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms, "
                  f"{r['rate_hz']} Hz each, {r['drops']} drops", flush=True)


if __name__ == "__main__":
    main()

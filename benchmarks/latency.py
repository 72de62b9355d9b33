"""Latency the service adds: frame tracked (worker) -> message received by a subscriber.

A server subprocess replays a ground-truth recording at 60 fps through the truth processor;
N subscribers in a client process stamp each frame on arrival (``time.time()`` when the bytes
reach the client's protocol). Latency = arrival - ``t_tracked`` (the server's clock, same host).
One JSON object per configuration with --json:

    python benchmarks/latency.py --json
    python benchmarks/latency.py --json --subscribers 1 10 100 --encoding binary
    python benchmarks/latency.py --json --client websockets     # the websockets library

``--client lean`` (default) is a minimal client (manual framing, see leanclient.py) so the
figure is the server's, not the client's; with ``--client websockets`` one Python process
decoding 100 subscribers' messages adds its own queueing to the tail.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

from common import ONE_ADDRESS, Server, load_average, make_recording, percentile


async def ws_subscriber(url: str, encoding: str, clock: list[float], lat: list[float],
                        drops: list[int]) -> None:
    import websockets

    from articast.client.protocol import frame_header

    async with websockets.connect(url, max_size=2**22, compression=None,
                                  close_timeout=1) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "bench",
                                  "streams": ["articulatory", "pose"], "encoding": encoding}))
        dropped = 0
        while True:
            data = await ws.recv()
            now = time.time()
            if isinstance(data, bytes):
                h = frame_header(data)
                t_tracked, dropped = h.t_tracked, h.dropped
            else:
                m = json.loads(data)
                if m["type"] != "frame":
                    continue
                t_tracked, dropped = m["t_tracked"], m["dropped"]
            if now >= clock[1]:
                break
            if now >= clock[0]:
                lat.append((now - t_tracked) * 1000.0)
        drops.append(dropped)


async def measure(url: str, n: int, seconds: float, encoding: str, client: str) -> dict:
    lat: list[float] = []
    drops: list[int] = []
    t0 = time.time()
    clock = [t0 + 2.0, t0 + 2.0 + seconds]  # 2 s to connect and warm up
    if client == "websockets":
        await asyncio.gather(*(ws_subscriber(url, encoding, clock, lat, drops)
                               for _ in range(n)))
    else:
        from leanclient import LeanSubscriber

        loop = asyncio.get_running_loop()
        host, port = url.split("//")[1].split("/")[0].split(":")
        sub = {"type": "subscribe", "session": "bench", "streams": ["articulatory", "pose"],
               "encoding": encoding}
        protos = []
        for _ in range(n):
            _, p = await loop.create_connection(
                lambda: LeanSubscriber(sub, clock, {}, sample_every=1), host, int(port))
            protos.append(p)
        await asyncio.gather(*(p.done for p in protos))
        lat = [x for p in protos for x in p.lat]
        drops = [p.dropped for p in protos]
    return {"subscribers": n, "rate_hz": round(len(lat) / n / seconds, 1),
            "encoding": encoding, "client": client, "samples": len(lat),
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
    ap.add_argument("--client", choices=("lean", "websockets"), default="lean")
    ap.add_argument("--worker", choices=("auto", "thread", "process"), default="auto")
    ap.add_argument("--busy-ms", type=float, default=0.0,
                    help="simulate a tracker holding the GIL this long per frame")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass
    rec = make_recording(frames=int(args.fps * 20), fps=args.fps)
    extra = ["--worker", args.worker, *ONE_ADDRESS]
    if args.busy_ms:
        import os

        os.environ["ARTICAST_BUSY_MS"] = str(args.busy_ms)
        extra += ["--processor", "benchmarks.busy:Busy"]
    with Server({"bench": f"replay-record:{rec}?loop=yes"}, *extra) as srv:
        srv.wait_running()
        for n in args.subscribers:
            load_before = load_average()
            r = asyncio.run(measure(srv.url, n, args.seconds, args.encoding, args.client))
            r.update(source_fps=args.fps, worker=args.worker, busy_ms=args.busy_ms,
                     load_average_before=load_before, load_average_after=load_average())
            print(json.dumps(r) if args.json else
                  f"{n:4d} subscribers: p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms, "
                  f"{r['rate_hz']} Hz each, {r['drops']} drops", flush=True)


if __name__ == "__main__":
    main()

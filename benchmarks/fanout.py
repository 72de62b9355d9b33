"""Fan-out: many subscribers at 30 Hz, plus clients that stop reading.

The server (a subprocess) replays a 30 fps ground-truth recording; N subscribers in client
processes read every frame; S "stalled" subscribers ask for the heavy mesh stream and never
read. Reports, as JSON with --json: per-client delivery, drops seen during the measured
window by the clients that keep up (must be 0), drops the server counted in all (the
stalled ones, plus any while clients connected), latency percentiles, the server's CPU use:

    python benchmarks/fanout.py --json --subscribers 500 --seconds 20
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import socket
import time
from typing import Any

from common import ONE_ADDRESS, Server, make_recording, percentile


async def reader(url: str, clock: Any, out: dict, lat: list[float], encoding: str) -> None:
    import websockets

    from articast.client.protocol import frame_header

    async with websockets.connect(url, max_size=2**22, compression=None,
                                  open_timeout=120, close_timeout=1) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "bench",
                                  "streams": ["articulatory", "pose"], "encoding": encoding}))
        got, dropped, first_seq, last_seq, dropped0 = 0, 0, None, None, None
        out["connected"] = out.get("connected", 0) + 1
        while True:
            data = await ws.recv()
            now = time.time()
            t_start, t_stop = clock[0], clock[1]
            if now >= t_stop:
                break
            if isinstance(data, bytes):  # header only: what a lean client reads first
                h = frame_header(data)
                seq, t_tracked, drop = h.seq, h.t_tracked, h.dropped
            else:
                m = json.loads(data)
                if m["type"] != "frame":
                    continue
                seq, t_tracked, drop = m["seq"], m["t_tracked"], m["dropped"]
            if now < t_start:
                continue
            got += 1
            dropped0 = drop if dropped0 is None else dropped0
            dropped = drop - dropped0  # drops during the measured window only
            first_seq = seq if first_seq is None else first_seq
            last_seq = seq
            if got % 10 == 0:
                lat.append((now - t_tracked) * 1000)
        out.setdefault("got", []).append(got)
        out.setdefault("dropped", []).append(dropped)
        out.setdefault("span", []).append((last_seq - first_seq + 1) if got else 0)


def client_process(url: str, n: int, encoding: str, clock: Any, ready: Any, results: Any,
                   lean: bool) -> None:
    """Runs ``n`` readers on one event loop; reports their figures through ``results``."""
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass

    async def run() -> dict:
        out: dict = {}
        lat: list[float] = []
        if lean:
            return await run_lean()
        tasks = [asyncio.create_task(reader(url, clock, out, lat, encoding)) for _ in range(n)]
        while out.get("connected", 0) < n:
            await asyncio.sleep(0.05)
        ready.release()
        await asyncio.gather(*tasks)
        out["lat"] = lat
        return out

    async def run_lean() -> dict:
        from leanclient import LeanSubscriber

        loop = asyncio.get_running_loop()
        host, port = url.split("//")[1].split("/")[0].split(":")
        sub = {"type": "subscribe", "session": "bench", "streams": ["articulatory", "pose"],
               "encoding": "binary"}
        protos = []
        for _ in range(n):
            _, p = await loop.create_connection(lambda: LeanSubscriber(sub, clock, {}),
                                                host, int(port))
            await p.connected
            protos.append(p)
        ready.release()
        await asyncio.gather(*(p.done for p in protos))
        return {"got": [p.got for p in protos], "dropped": [p.dropped for p in protos],
                "span": [(p.last_seq - p.first_seq + 1) if p.got else 0 for p in protos],
                "lat": [x for p in protos for x in p.lat]}

    results.put(asyncio.run(run()))


def stalled_client(url: str) -> socket.socket:
    """A raw WebSocket client with a tiny receive buffer that never reads."""
    import base64
    import os
    import struct

    host, port = url.split("//")[1].split("/")[0].split(":")
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, int(port)))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
               "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    s.recv(1024)
    payload = json.dumps({"type": "subscribe", "session": "bench",
                          "streams": ["articulatory", "pose", "mesh"]}).encode()
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    s.sendall(struct.pack("!BB", 0x81, 0x80 | len(payload)) + mask + masked
              if len(payload) < 126 else
              struct.pack("!BBH", 0x81, 0x80 | 126, len(payload)) + mask + masked)
    return s


def measure(srv: Server, n: int, seconds: float, stalled: int, procs: int,
            encoding: str, lean: bool) -> dict:
    ctx = mp.get_context("spawn")
    clock = ctx.Array("d", [float("inf"), float("inf")])
    ready, results = ctx.Semaphore(0), ctx.Queue()
    sizes = [n // procs + (i < n % procs) for i in range(procs)]
    workers = [ctx.Process(target=client_process, args=(srv.url, k, encoding, clock, ready,
                                                        results, lean), daemon=True) for k in sizes]
    for w in workers:
        w.start()
    for _ in workers:
        if not ready.acquire(timeout=180):
            raise RuntimeError("clients did not connect")
    socks = [stalled_client(srv.url) for _ in range(stalled)]
    time.sleep(3.0)  # warm up; the stalled clients fill their buffers
    t0 = time.time()
    clock[0], clock[1] = t0, t0 + seconds
    cpu0 = srv.cpu_s()
    time.sleep(seconds)
    cpu = (srv.cpu_s() - cpu0) / seconds
    import httpx

    metrics = httpx.get(srv.http + "/metrics", timeout=10).text
    server_drops = sum(int(float(x.split()[-1])) for x in metrics.splitlines()
                       if x.startswith("articast_subscriber_dropped_total{"))
    outs = [results.get(timeout=120) for _ in workers]
    for w in workers:
        w.join(10)
    for s in socks:
        s.close()
    got = [g for o in outs for g in o.get("got", [])]
    span = [g for o in outs for g in o.get("span", [])]
    lat = [x for o in outs for x in o["lat"]]
    return {
        "subscribers": n, "stalled": stalled, "seconds": seconds, "encoding": encoding,
        "client": "lean" if lean else "websockets", "client_processes": procs,
        "rate_hz": round(sum(got) / max(1, len(got)) / seconds, 2),
        "min_rate_hz": round(min(got) / seconds, 2) if got else 0,
        "frames_missed": sum(s - g for s, g in zip(span, got, strict=True)),
        "drops": sum(d for o in outs for d in o.get("dropped", [])),
        "server_drops_total": server_drops,
        "p50_ms": round(percentile(lat, 50), 2), "p99_ms": round(percentile(lat, 99), 2),
        "server_cpu": round(cpu, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--subscribers", type=int, nargs="+", default=[500])
    ap.add_argument("--stalled", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--client-processes", type=int, default=2)
    ap.add_argument("--encoding", choices=("json", "binary"), default="binary")
    ap.add_argument("--client", choices=("lean", "websockets"), default="lean",
                    help="load generator: lean (manual framing, binary) or the websockets "
                    "library (costs the shared CPU more than the server does)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rec = make_recording(frames=int(args.fps * 30), fps=args.fps, n_points=2000)
    with Server({"bench": f"replay-record:{rec}?loop=yes"}, "--max-queue", "8",
                *ONE_ADDRESS) as srv:
        srv.wait_running()
        for n in args.subscribers:
            r = measure(srv, n, args.seconds, args.stalled, args.client_processes,
                        args.encoding, args.client == "lean")
            r["source_fps"] = args.fps
            print(json.dumps(r) if args.json else r, flush=True)


if __name__ == "__main__":
    main()

"""Scale-out on Redis: 1 track-worker, 2 gateways, 1 redis-server, N subscribers at 30 Hz.

    python benchmarks/redis_scaleout.py --json --subscribers 1000 --seconds 20

Everything on loopback, each piece in its own process (redis-server, ``articast
track-worker`` replaying a 30 fps recording, two ``articast gateway``), subscribers split
over the gateways in client processes (lean binary clients). Phases:

1. steady state for ``--seconds``: per-subscriber rate, drops seen by subscribers that keep
   up, added latency (tracked in the worker -> bytes at the subscriber) p50/p99, and the
   gateways' own view (tracked -> written to the subscriber's socket, from their
   ``articast_send_latency_seconds`` histograms: bucket bounds);
2. Redis killed, down for ``--outage`` s, started again (empty): recovery time = from the
   restart until a subscriber receives a frame again (max and p99 over subscribers, and how
   many recovered within 5 s); ``stale_frames`` = frames received after the restart that
   were tracked more than 1 s before it (must be 0: nothing replayed).

JSON on stdout with --json (one object); ``p99_stated`` gives the p99 with the load average
it was measured at (the tail depends on what else the cores run). The lean clients answer
the gateways' keepalive pings (a client that does not is rightly closed after 20 s, which
counted as a lost subscriber in runs before).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import time
from typing import Any

from common import ONE_ADDRESS, ROOT, load_average, make_recording, percentile
from leanclient import answer_pings, client_frame, server_frames, upgrade_request

from articast.client.protocol import frame_header

# shared clock (wall time): [steady start, steady end, redis down, redis up, end]
STEADY0, STEADY1, DOWN, UP, END = range(5)


class Sub(asyncio.Protocol):
    def __init__(self, clock: Any) -> None:
        self.clock = clock
        self.buf = bytearray()
        self.upgraded = False
        loop = asyncio.get_running_loop()
        self.connected, self.done = loop.create_future(), loop.create_future()
        self.got = 0
        self.first_seq: int | None = None
        self.last_seq = 0
        self.dropped0: int | None = None
        self.dropped = 0
        self.lat: list[float] = []
        self.back_at = 0.0  # first frame received after Redis came back
        self.stale = 0

    def connection_made(self, transport: Any) -> None:
        self.transport = transport
        transport.write(upgrade_request())

    def data_received(self, data: bytes) -> None:
        self.buf += data
        if not self.upgraded:
            end = self.buf.find(b"\r\n\r\n")
            if end < 0:
                return
            if not self.buf.startswith(b"HTTP/1.1 101"):
                self.connected.set_exception(ConnectionError(bytes(self.buf[:80]).decode()))
                return
            del self.buf[: end + 4]
            self.upgraded = True
            self.transport.write(client_frame(json.dumps({
                "type": "subscribe", "session": "bench", "streams": ["articulatory", "pose"],
                "encoding": "binary", "geometry": False})))
        frames, used = server_frames(self.buf)
        for opcode, start, end in frames:
            answer_pings(self.transport, self.buf, opcode, start, end)
            if opcode == 2:
                hd = frame_header(self.buf, start)
                self._frame(hd.seq, hd.t_tracked, hd.dropped)
            elif opcode == 1 and not self.connected.done() and b'"hello"' in self.buf[start:end]:
                self.connected.set_result(None)
            elif opcode == 8:
                self._finish()
        del self.buf[:used]

    def _frame(self, seq: int, t_tracked: float, drop: int) -> None:
        now = time.time()
        c = self.clock
        if not self.connected.done():
            self.connected.set_result(None)
        if now >= c[END]:
            self._finish()
            return
        if c[STEADY0] <= now < c[STEADY1]:
            self.got += 1
            if self.first_seq is None:
                self.first_seq, self.dropped0 = seq, drop
            self.last_seq = seq
            self.dropped = drop - (self.dropped0 or 0)
            if self.got % 10 == 0:
                self.lat.append((now - t_tracked) * 1000)
        elif now >= c[UP] and c[UP] > 0:
            if not self.back_at:
                self.back_at = now
            if t_tracked < c[UP] - 1.0:
                self.stale += 1

    def _finish(self) -> None:
        if not self.done.done():
            self.done.set_result(None)
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.connected.done():
            self.connected.set_exception(ConnectionError("lost before hello"))
        self._finish()


def client_process(url: str, n: int, clock: Any, ready: Any, results: Any) -> None:
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass

    async def run() -> dict:
        loop = asyncio.get_running_loop()
        host, port = url.split("//")[1].split("/")[0].split(":")
        subs = []
        for _ in range(n):
            _, p = await loop.create_connection(lambda: Sub(clock), host, int(port))
            subs.append(p)
        await asyncio.wait_for(asyncio.gather(*(p.connected for p in subs)), 120)
        ready.release()
        await asyncio.gather(*(p.done for p in subs))
        return {"got": [p.got for p in subs], "dropped": [p.dropped for p in subs],
                "span": [(p.last_seq - p.first_seq + 1) if p.got else 0 for p in subs],
                "lat": [x for p in subs for x in p.lat],
                "back_at": [p.back_at for p in subs], "stale": sum(p.stale for p in subs)}

    results.put(asyncio.run(run()))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_redis(port: int) -> subprocess.Popen:
    p = subprocess.Popen(["redis-server", "--port", str(port), "--bind", "127.0.0.1",
                          "--save", "", "--appendonly", "no"], stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), 0.2).close()
            return p
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError("redis-server did not start") from None
            time.sleep(0.02)


def articast(*args: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    env["PYTHONPATH"] = str(ROOT)
    return subprocess.Popen([sys.executable, "-m", "articast.service.cli", *args], cwd=ROOT,
                            env=env, stdout=subprocess.PIPE, text=True)


def send_buckets(http: str) -> dict[str, int]:
    """The gateway's cumulative send-latency histogram (tracked -> written to a socket)."""
    import httpx

    out = {}
    for line in httpx.get(http + "/metrics", timeout=10).text.splitlines():
        if line.startswith("articast_send_latency_seconds_bucket{"):
            le = line.split('le="')[1].split('"')[0]
            out[le] = out.get(le, 0) + int(float(line.split()[-1]))
    return out


def bucket_quantile(before: list[dict[str, int]], after: list[dict[str, int]], q: float) -> str:
    """Upper bound (ms) of the histogram bucket holding quantile ``q`` of the window."""
    total: dict[str, int] = {}
    for b, a in zip(before, after, strict=True):
        for le, n in a.items():
            total[le] = total.get(le, 0) + n - b.get(le, 0)
    if not total or not total.get("+Inf"):
        return "n/a"
    need = q * total["+Inf"]
    for le in sorted((k for k in total if k != "+Inf"), key=float):
        if total[le] >= need:
            return f"<= {float(le) * 1000:g}"
    return "> 1000"


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--subscribers", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--outage", type=float, default=2.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--client-processes", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    load_before = load_average()
    rec = make_recording(frames=int(args.fps * 60), fps=args.fps, n_points=200)
    port = free_port()
    url = f"redis://127.0.0.1:{port}/0"
    redis = start_redis(port)
    procs: list[subprocess.Popen] = []
    try:
        worker = articast("track-worker", "--hub", url, "--json",
                          "--source", f"bench=replay-record:{rec}?loop=yes")
        procs.append(worker)
        json.loads(worker.stdout.readline())
        gateways = []
        for _ in range(2):
            g = articast("gateway", "--hub", url, "--port", "0", "--json", "--log-level",
                         "error", "--max-queue", "8", *ONE_ADDRESS)
            procs.append(g)
            gateways.append(g)
        urls = [json.loads(g.stdout.readline())["url"] for g in gateways]
        time.sleep(2.5)  # the gateways learn of the session (1 s poll)
        ctx = mp.get_context("spawn")
        clock = ctx.Array("d", [float("inf")] * 5)
        clock[DOWN] = clock[UP] = 0.0
        ready, results = ctx.Semaphore(0), ctx.Queue()
        per = [args.subscribers // args.client_processes + (i < args.subscribers
                                                              % args.client_processes)
               for i in range(args.client_processes)]
        clients = [ctx.Process(target=client_process, args=(urls[i % 2], k, clock, ready,
                                                            results), daemon=True)
                   for i, k in enumerate(per)]
        for c in clients:
            c.start()
        for _ in clients:
            if not ready.acquire(timeout=240):
                raise RuntimeError("clients did not connect")
        time.sleep(3.0)
        t0 = time.time()
        clock[STEADY0], clock[STEADY1] = t0, t0 + args.seconds
        https = [u.replace("ws://", "http://").rsplit("/ws", 1)[0] for u in urls]
        cpu0 = {p.pid: cpu_s(p.pid) for p in procs}
        ccpu0 = {c.pid: cpu_s(c.pid) for c in clients}
        load0 = os.getloadavg()[0]
        hist0 = [send_buckets(h) for h in https]
        time.sleep(args.seconds)
        cpu = {p.pid: (cpu_s(p.pid) - cpu0[p.pid]) / args.seconds for p in procs}
        ccpu = [(cpu_s(c.pid) - ccpu0[c.pid]) / args.seconds for c in clients]
        load = (load0 + os.getloadavg()[0]) / 2
        hist1 = [send_buckets(h) for h in https]
        clock[DOWN] = time.time()
        redis.send_signal(signal.SIGKILL)
        redis.wait()
        time.sleep(args.outage)
        clock[UP] = time.time()
        redis = start_redis(port)
        clock[END] = clock[UP] + 15.0
        outs = [results.get(timeout=120) for _ in clients]
        for c in clients:
            c.join(10)
    finally:
        for p in procs:
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        redis.kill()
        redis.wait()
    got = [g for o in outs for g in o["got"]]
    span = [s for o in outs for s in o["span"]]
    lat = [x for o in outs for x in o["lat"]]
    back = [b - clock[UP] if b else float("inf") for o in outs for b in o["back_at"]]
    finite = [b for b in back if b != float("inf")]
    result = {
        "subscribers": args.subscribers, "gateways": 2, "workers": 1,
        "source_fps": args.fps, "seconds": args.seconds,
        "rate_hz": round(sum(got) / max(1, len(got)) / args.seconds, 2),
        "min_rate_hz": round(min(got) / args.seconds, 2) if got else 0,
        "frames_missed": sum(s - g for s, g in zip(span, got, strict=True)),
        "drops": sum(d for o in outs for d in o["dropped"]),
        "p50_ms": round(percentile(lat, 50), 2), "p99_ms": round(percentile(lat, 99), 2),
        "gateway_send_p50_ms": bucket_quantile(hist0, hist1, 0.50),
        "gateway_send_p99_ms": bucket_quantile(hist0, hist1, 0.99),
        "cpu_cores": {"worker": round(cpu[procs[0].pid], 2),
                      "gateways": [round(cpu[p.pid], 2) for p in procs[1:]],
                      "client_processes": [round(c, 2) for c in ccpu]},
        "machine_cores": os.cpu_count(), "load_average": round(load, 1),
        "load_average_before": load_before, "load_average_after": load_average(),
        "redis_outage_s": args.outage,
        "recovered": len(finite), "recovered_within_5s": sum(b <= 5.0 for b in finite),
        "recovery_p50_s": round(percentile(finite, 50), 3),
        "recovery_p99_s": round(percentile(finite, 99), 3),
        "recovery_max_s": round(max(finite), 3) if finite else None,
        "stale_frames": sum(o["stale"] for o in outs),
    }
    # a latency tail means little without the machine's load at the time: said together
    result["p99_stated"] = (f"p99 {result['p99_ms']} ms at load average {result['load_average']}"
                            f" on {os.cpu_count()} cores ({args.subscribers} subscribers)")
    print(json.dumps(result) if args.json else json.dumps(result, indent=2), flush=True)


if __name__ == "__main__":
    main()

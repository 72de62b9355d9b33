"""Issue 39's attacker rows, measured: what an abusive client costs everyone else.

The server (a subprocess, a token, default limits) replays a 30 fps recording. A bystander
subscriber on 127.0.0.2 counts its frames per second, and ``/healthz`` is asked from
127.0.0.3 every 0.25 s, first with no attack (the baseline), then while the attack runs
(attackers in a child process, from addresses of their own: all of 127/8 is loopback):

* ``flood``: N connections, each from its own address (one per address: under every
  per-address limit), upgrade and then send subscribe messages as fast as the socket takes
  them, never reading; a connection the server drops is opened again. Reported: the
  bystander's fps, ``/healthz`` latency, the server's RSS and the bytes waiting in its
  sockets' receive queues (``ss``), and how many flood connections the server dropped.
* ``fill``: 16 addresses open 131 subscriptions each (2,096 > ``--max-subscribers`` 2,000),
  then a newcomer from another address subscribes: admitted or refused.
* ``guess``: one address sends wrong tokens as fast as it can while a client behind the same
  address (a NAT) uses the right token every 0.25 s: its answers, counted.
* ``hello``: one address, 8 connections resubscribing with a new rate each time (a hello
  per subscribe, with the model geometry) and 8 reconnecting and subscribing in a loop.

Usage: ``python benchmarks/abuse.py flood --connections 32 --seconds 10`` (``all``: every
attack in turn); ``--json`` prints the figures as JSON. Every figure is printed with the
machine's load average.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import Server, load_average, make_recording  # noqa: E402
from benchmarks.leanclient import client_frame, server_frames, upgrade_request  # noqa: E402

TOKEN = "abuse-benchmark-token-0123456789"
BYSTANDER, HEALTH, NEWCOMER, NAT = "127.0.0.2", "127.0.0.3", "127.0.0.4", "127.0.0.5"


def attacker_address(i: int) -> str:
    return f"127.0.{10 + i // 250}.{1 + i % 250}"


# ----------------------------------------------------------------------------- attackers
async def _upgrade(port: int, addr: str, path: str) -> tuple[Any, Any]:
    r, w = await asyncio.open_connection("127.0.0.1", port, local_addr=(addr, 0))
    w.write(upgrade_request(path))
    head = await asyncio.wait_for(r.readuntil(b"\r\n\r\n"), 10)
    if b" 101 " not in head.split(b"\r\n", 1)[0]:
        w.close()
        raise ConnectionRefusedError(head.split(b"\r\n", 1)[0].decode(errors="replace"))
    return r, w


async def _flooder(port: int, addr: str, stop_at: float, stats: dict[str, int]) -> None:
    chunk = client_frame(json.dumps({"type": "subscribe", "session": "rec",
                                     "geometry": False})) * 1000
    while time.time() < stop_at:
        w = None
        try:
            _, w = await _upgrade(port, addr, f"/ws?token={TOKEN}")
            stats["opened"] += 1
            while time.time() < stop_at:
                w.write(chunk)
                await asyncio.wait_for(w.drain(), max(0.01, stop_at - time.time()))
        except TimeoutError:
            pass
        except (OSError, asyncio.IncompleteReadError):
            stats["dropped"] += 1
            await asyncio.sleep(0.05)
        finally:
            if w is not None:
                w.transport.abort()


def flood_process(port: int, n: int, seconds: float, out: Any) -> None:
    stats = {"opened": 0, "dropped": 0}

    async def go() -> None:
        stop_at = time.time() + seconds
        await asyncio.gather(*(_flooder(port, attacker_address(i), stop_at, stats)
                               for i in range(n)))

    asyncio.run(go())
    out.put(stats)


def _peek(head: bytes) -> dict[str, Any]:
    """A big message's type, read from its first bytes (an attacker does not parse hellos)."""
    return {"type": head.split(b'"type":"', 1)[-1].split(b'"', 1)[0].decode()}


async def _text_messages(r: Any, buf: bytearray) -> list[dict[str, Any]]:
    """The next text messages read from ``r`` (at least one, or [] at the end)."""
    while True:
        frames, used = server_frames(buf)
        msgs = [_peek(bytes(buf[a:min(b, a + 40)])) if b - a > 4096
                else json.loads(bytes(buf[a:b])) for op, a, b in frames if op == 1]
        closed = any(op == 8 for op, _, _ in frames)
        del buf[:used]
        if msgs or closed:
            return msgs
        data = await r.read(1 << 16)
        if not data:
            return []
        buf += data


async def _subscribe_until_answered(port: int, addr: str, stop_at: float,
                                    sub: dict[str, Any], delay: float = 0.0
                                    ) -> tuple[str, Any]:
    """A connection subscribing until it is answered hello or refused for good (a
    rate_limited refusal, and a handshake refused 429, are tried again); returns (answer,
    writer)."""
    await asyncio.sleep(delay)
    while True:
        try:
            r, w = await _upgrade(port, addr, f"/ws?token={TOKEN}")
            break
        except ConnectionRefusedError as exc:
            if " 429 " not in str(exc) or time.time() > stop_at:
                raise
            await asyncio.sleep(0.5 + random.random())
    buf = bytearray()
    while time.time() < stop_at:
        w.write(client_frame(json.dumps(sub)))
        while True:
            msgs = await asyncio.wait_for(_text_messages(r, buf), 30)
            if not msgs:
                return "closed", w
            kinds = [(m["type"], m.get("code")) for m in msgs]
            if ("hello", None) in kinds:
                return "hello", w
            codes = [c for t, c in kinds if t == "error"]
            if codes:
                break
        if codes[0] != "rate_limited":
            return codes[0], w
        await asyncio.sleep(0.5 + random.random())
    return "timeout", w


def fill_process(port: int, addresses: int, per_address: int, out: Any) -> None:
    sub = {"type": "subscribe", "session": "rec", "geometry": False, "rate": 1}

    async def go() -> None:
        stop_at = time.time() + 120
        # each address opens 15 connections a second: under the handshake limit (20/s)
        jobs = [_subscribe_until_answered(port, attacker_address(a), stop_at, sub, j / 15)
                for a in range(addresses) for j in range(per_address)]
        got = await asyncio.gather(*jobs, return_exceptions=True)
        answers: dict[str, int] = {}
        for g in got:
            k = g[0] if isinstance(g, tuple) else f"{type(g).__name__}: {g}"[:60]
            answers[k] = answers.get(k, 0) + 1
        newcomer = await _subscribe_until_answered(port, NEWCOMER, stop_at, sub)
        out.put({"attackers": answers, "newcomer": newcomer[0]})
        for g in got:
            if isinstance(g, tuple):
                g[1].transport.abort()

    asyncio.run(go())


def hello_process(port: int, seconds: float, out: Any) -> None:
    stats = {"hellos": 0, "refused": 0, "connections": 0}
    addr = attacker_address(0)

    async def resubscriber(stop_at: float) -> None:
        r, w = await _upgrade(port, addr, f"/ws?token={TOKEN}")
        buf = bytearray()
        while time.time() < stop_at:
            w.write(client_frame(json.dumps({"type": "subscribe", "session": "rec",
                                             "rate": round(random.uniform(1, 999), 3)})))
            for m in await asyncio.wait_for(_text_messages(r, buf), 30):
                stats["hellos" if m["type"] == "hello" else "refused"] += m["type"] != "frame"
        w.transport.abort()

    async def reconnecter(stop_at: float) -> None:
        while time.time() < stop_at:
            try:
                r, w = await _upgrade(port, addr, f"/ws?token={TOKEN}")
            except (OSError, ConnectionRefusedError):
                stats["refused"] += 1
                await asyncio.sleep(0.01)
                continue
            stats["connections"] += 1
            w.write(client_frame(json.dumps({"type": "subscribe", "session": "rec"})))
            buf = bytearray()
            msgs = await asyncio.wait_for(_text_messages(r, buf), 30)
            stats["hellos"] += sum(m["type"] == "hello" for m in msgs)
            w.transport.abort()

    async def go() -> None:
        stop_at = time.time() + seconds
        await asyncio.gather(*(resubscriber(stop_at) for _ in range(8)),
                             *(reconnecter(stop_at) for _ in range(8)),
                             return_exceptions=True)

    asyncio.run(go())
    out.put(stats)


# ----------------------------------------------------------------------------- observers
async def bystander(url: str, counts: list[float]) -> None:
    import websockets

    async with websockets.connect(url, max_size=2**26,
                                  local_addr=(BYSTANDER, 0)) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "rec", "geometry": False}))
        async for m in ws:
            if isinstance(m, str) and m.startswith('{"type":"frame"'):
                counts.append(time.monotonic())


async def health(http: str, lat: list[float], stop: asyncio.Event) -> None:
    import httpx

    async with httpx.AsyncClient(transport=httpx.AsyncHTTPTransport(local_address=HEALTH),
                                 timeout=5.0) as c:
        while not stop.is_set():
            t = time.monotonic()
            try:
                await c.get(http + "/healthz")
                lat.append(time.monotonic() - t)
            except httpx.HTTPError:
                lat.append(float("inf"))  # a time-out (5 s) or a refusal
            await asyncio.sleep(0.25)


def recv_queue_bytes(port: int) -> int:
    """Bytes waiting in the receive queues of the server's sockets (``ss``'s Recv-Q)."""
    out = subprocess.run(["ss", "-tnH", "state", "established", f"( sport = :{port} )"],
                         capture_output=True, text=True).stdout
    return sum(int(line.split()[0]) for line in out.splitlines() if line.split())


def fps_stats(times: list[float], t0: float, t1: float) -> dict[str, float]:
    bins = [0] * max(1, int(t1 - t0))
    for t in times:
        if t0 <= t < t0 + len(bins):
            bins[int(t - t0)] += 1
    return {"mean": round(sum(bins) / len(bins), 1), "min": min(bins)}


def lat_stats(lat: list[float]) -> dict[str, float]:
    ok = sorted(x for x in lat if x != float("inf"))
    return {"p50_ms": round(1000 * ok[len(ok) // 2], 1) if ok else None,
            "p95_ms": round(1000 * ok[min(len(ok) - 1, int(0.95 * len(ok)))], 1) if ok else None,
            "max_ms": round(1000 * ok[-1], 1) if ok else None,
            "timeouts": sum(x == float("inf") for x in lat), "n": len(lat)}


async def observe(srv: Server, port: int, attack: Any, seconds: float,
                  baseline_s: float = 5.0) -> dict[str, Any]:
    """Baseline, then the attack (a started child process); the observers' figures."""
    counts: list[float] = []
    lat0: list[float] = []
    lat1: list[float] = []
    by = asyncio.create_task(bystander(srv.url + f"?token={TOKEN}", counts))
    await asyncio.sleep(2.0)
    stop = asyncio.Event()
    t0, cpu0 = time.monotonic(), srv.cpu_s()
    h = asyncio.create_task(health(srv.http, lat0, stop))
    await asyncio.sleep(baseline_s)
    stop.set()
    await h
    t1, cpu1 = time.monotonic(), srv.cpu_s()
    attack.start()
    stop = asyncio.Event()
    h = asyncio.create_task(health(srv.http, lat1, stop))
    rss, rq = [], []
    while time.monotonic() < t1 + seconds:
        await asyncio.sleep(0.5)
        rss.append(srv.rss_mb())
        rq.append(recv_queue_bytes(port))
    t2, cpu2 = time.monotonic(), srv.cpu_s()
    stop.set()
    await h
    by.cancel()
    await asyncio.gather(by, return_exceptions=True)
    return {"bystander_fps_baseline": fps_stats(counts, t0, t1),
            "bystander_fps_attack": fps_stats(counts, t1, t2),
            "healthz_baseline": lat_stats(lat0), "healthz_attack": lat_stats(lat1),
            "server_cpu_baseline": round((cpu1 - cpu0) / (t1 - t0), 2),  # cores used
            "server_cpu_attack": round((cpu2 - cpu1) / (t2 - t1), 2),
            "server_rss_mb_max": round(max(rss), 1),
            "recv_queue_mb_max": round(max(rq) / 1e6, 2)}


def run_attack(name: str, args: Any, srv: Server, port: int) -> dict[str, Any]:
    out: Any = mp.Queue()
    if name == "flood":
        proc = mp.Process(target=flood_process,
                          args=(port, args.connections, args.seconds, out))
        figures = asyncio.run(observe(srv, port, proc, args.seconds))
        figures["flood"] = out.get(timeout=60)
        figures["connections"] = args.connections
    elif name == "hello":
        proc = mp.Process(target=hello_process, args=(port, args.seconds, out))
        figures = asyncio.run(observe(srv, port, proc, args.seconds))
        figures["hello"] = out.get(timeout=60)
    elif name == "fill":
        proc = mp.Process(target=fill_process, args=(port, 16, 131, out))
        proc.start()
        figures = out.get(timeout=300)
    elif name == "guess":
        figures = guess(srv)
    else:
        raise SystemExit(f"unknown attack {name!r}")
    if name in ("flood", "hello", "fill"):
        proc.join(60)
    return figures


def guess(srv: Server, seconds: float = 10.0, guessers: int = 4) -> dict[str, Any]:
    """``guessers`` threads send wrong tokens from NAT's address, each as soon as its last
    was answered; the right token from the same address every 0.25 s. A wrong token still
    held when the time is up is not counted."""
    import threading

    import httpx

    stop = time.time() + seconds
    wrong: dict[int, int] = {}
    right: dict[int, int] = {}

    def guesser() -> None:
        with httpx.Client(transport=httpx.HTTPTransport(local_address=NAT), timeout=None) as c:
            while time.time() < stop:
                tok = f"guess-{random.getrandbits(64):016x}-xxxxxxxx"
                s = c.get(srv.http + "/api/sessions",
                          headers={"Authorization": f"Bearer {tok}"}).status_code
                if time.time() < stop:
                    wrong[s] = wrong.get(s, 0) + 1

    for _ in range(guessers):
        threading.Thread(target=guesser, daemon=True).start()
    with httpx.Client(transport=httpx.HTTPTransport(local_address=NAT), timeout=30) as c:
        while time.time() < stop:
            s = c.get(srv.http + "/api/sessions",
                      headers={"Authorization": f"Bearer {TOKEN}"}).status_code
            right[s] = right.get(s, 0) + 1
            time.sleep(0.25)
    return {"seconds": seconds, "guessers": guessers, "wrong_token_answers": wrong,
            "right_token_answers": right}


def wait_running(srv: Server, timeout: float = 60.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            r = httpx.get(srv.http + "/healthz", timeout=2,
                          headers={"Authorization": f"Bearer {TOKEN}"})
            if r.json().get("sessions", {}).get("rec") == "running":
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError("the session did not start")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("attack", choices=("flood", "fill", "guess", "hello", "all"))
    ap.add_argument("--connections", type=int, default=32, help="flood connections (32)")
    ap.add_argument("--seconds", type=float, default=10.0, help="attack duration (10 s)")
    ap.add_argument("--points", type=int, default=500,
                    help="model points (the hello's geometry grows with them)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rec = make_recording(frames=300, fps=30.0, n_points=args.points)
    os.environ["ARTICAST_TOKEN"] = TOKEN
    names = ("flood", "fill", "guess", "hello") if args.attack == "all" else (args.attack,)
    results = {}
    for name in names:
        with Server({"rec": f"replay-record:{rec}?loop=yes"}) as srv:
            wait_running(srv)
            port = int(srv.http.rsplit(":", 1)[1])
            load = load_average()
            results[name] = {"load_before": load, **run_attack(name, args, srv, port),
                             "load_after": load_average()}
        if not args.json:
            print(f"{name}: {json.dumps(results[name])}", flush=True)
    if args.json:
        print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()

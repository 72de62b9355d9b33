"""An enrolled member's delegate shared through Redis (docs/ROOM.md, "Two room servers on one
Redis"): its size, and how long the other server takes to serve it.

A real ``redis-server`` and two ``articast room --hub`` servers on loopback, as
tests/test_room_redis.py starts them (members tracked by a processor that reads the image);
a copy of SPEAKER (an enrolled speaker folder, without its ``room-key``) is ann's, who joins
on A over WebRTC (aiortc); bob joins on B. Once ann's frames reach B: ``--gets`` requests of
``/room/api/delegate/ann`` on B (from Redis, bob's token) and on A (her session's own copy,
her token), the Redis ``GET`` alone, and the key's ``MEMORY USAGE``; then Redis is stopped
and B and A are asked again (B: a one-line 503, then 404 once ann has left its list; A: hers).

    python benchmarks/room_redis_delegate.py ~/.local/share/articast/rooms/ROOM/speakers/NAME
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("speaker", type=Path, help="an enrolled speaker folder with delegate.npz")
    ap.add_argument("--gets", type=int, default=20, help="requests per server (default 20)")
    args = ap.parse_args()
    if not (args.speaker / "delegate.npz").is_file():
        print(f"{args.speaker}: no delegate.npz", file=sys.stderr)
        return 2

    import httpx

    from articast.service.room import participant_token
    from tests.test_room_redis import ROOM, Page, Redis, base_url, room_server, stop_all, until

    folder = Path(tempfile.mkdtemp())
    shutil.copytree(args.speaker, folder / "ann", ignore=shutil.ignore_patterns("room-key"))
    redis = Redis()
    redis.start()
    servers = [room_server(redis.url, folder, "--log-level", "info") for _ in range(2)]

    def ms(ts: list[float]) -> str:
        return (f"median {1e3 * statistics.median(ts):.1f} ms, max {1e3 * max(ts):.1f} ms, "
                f"first {1e3 * ts[0]:.1f} ms")

    async def go() -> None:
        import redis.asyncio as aioredis

        a, b = (base_url(p) for p in servers)
        ann, bob = Page(a, "ann", participant_token(ROOM, "ann")), Page(b, "bob")
        client = aioredis.from_url(redis.url)
        await asyncio.gather(ann.join(), bob.join())
        async with bob.socket() as on_b, httpx.AsyncClient(timeout=20) as c:
            await until(on_b, lambda m: m["type"] == "frame" and m["session"] == "ann", 120)
            bodies = {}
            for where, url, token in (("B, from Redis", b, bob.token),
                                      ("A, its session's", a, ann.token)):
                ts = []
                for _ in range(args.gets):
                    t = time.perf_counter()
                    r = await c.get(f"{url}/room/api/delegate/ann",
                                    headers={"X-Participant-Token": token})
                    ts.append(time.perf_counter() - t)
                    assert r.status_code == 200, r.text
                bodies[where] = r.content
                print(f"{where}: {len(r.content)} bytes, {ms(ts)} ({args.gets} GETs; the "
                      "first was asked as soon as ann's frames reached B)")
            key = [k async for k in client.scan_iter("articast:room:t:delegate:ann:*")][0]
            ts = []
            for _ in range(args.gets):
                t = time.perf_counter()
                stored = await client.get(key)
                ts.append(time.perf_counter() - t)
            print(f"Redis GET alone: {ms(ts)}; MEMORY USAGE {await client.memory_usage(key)} "
                  f"bytes; the same bytes everywhere: "
                  f"{len(set(bodies.values()) | {stored}) == 1}")
            await client.aclose()
            redis.stop()
            for wait in (0.0, 3.0):
                await asyncio.sleep(wait)
                t = time.perf_counter()
                r = await c.get(f"{b}/room/api/delegate/ann",
                                headers={"X-Participant-Token": bob.token})
                print(f"Redis stopped {wait:g} s ago: B {r.status_code} {r.text} in "
                      f"{time.perf_counter() - t:.2f} s")
            r = await c.get(f"{a}/room/api/delegate/ann",
                            headers={"X-Participant-Token": ann.token})
            print(f"Redis stopped: A {r.status_code} ({len(r.content)} bytes); servers up: "
                  f"{[p.poll() is None for p in servers]}")
        for page in (ann, bob):
            await page.pc.close()

    try:
        asyncio.run(go())
    finally:
        stop_all(servers, redis, lambda line: "delegate" in line)
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

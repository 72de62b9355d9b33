"""A member's voice relayed to another room server through Redis (docs/ROOM.md, "Two room
servers on one Redis"): its packets and bytes a second, the Redis hop's delay, and how much
later it plays on the other server's page than on a page of its own server.

A real ``redis-server`` and two ``articast room --hub`` servers on loopback, as
tests/test_room_redis.py starts them (``--log-level info``: each media process says every
10 s what it relayed and read). ann joins on A and says a 440 Hz tone 200 ms of every second;
bob joins on B (his slot carries ann, through Redis), then carol on A (hers carries ann,
forwarded locally). For ``--seconds``, each page's slot is decoded (aiortc) and the onsets of
ann's tone are timed as they come: bob's minus carol's is what the relay through Redis adds.
Then Redis is stopped for 4 s (bob's slot falls silent, the servers stay up, their logs say
so) and started again (empty: the servers write the membership again, and the voice comes
back; carol leaves then, so that bob's one slot is ann's again).

    python benchmarks/room_redis_voice.py [--seconds 30]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def onsets(ear: object, since: float) -> list[float]:
    """When the tone began, each time (the arrival of its first loud frame after quiet)."""
    out, quiet = [], 0
    for at, pcm in ear.frames:  # type: ignore[attr-defined]
        rms = float(np.sqrt(np.mean(pcm * pcm)))
        if rms > 0.05 and quiet >= 5 and at > since:
            out.append(at)
        quiet = quiet + 1 if rms < 0.02 else 0
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    args = ap.parse_args()

    import tests.test_room_redis as T

    folder = Path(tempfile.mkdtemp())
    redis = T.Redis()
    redis.start()
    servers = [T.room_server(redis.url, folder, "--log-level", "info") for _ in range(2)]

    async def go() -> None:
        a, b = (T.base_url(p) for p in servers)
        ann = T.Page(a, "ann", tone=440.0, pulse=(10, 50))  # (10 frames of every 50)
        bob, carol = T.Page(b, "bob"), T.Page(a, "carol")
        await ann.join()
        await bob.join()
        bob_ear = T.Ear(bob.slot.receiver.track)
        async with bob.socket() as on_b:
            await T.until(on_b, lambda m: T.names(m) is not None and "ann" in T.names(m)
                          and T.names(m)["ann"]["slot"] is not None, 60)
            await carol.join()
            carol_ear = T.Ear(carol.slot.receiver.track)
            async with carol.socket() as on_c:
                await T.until(on_c, lambda m: T.names(m) is not None and "ann" in T.names(m)
                              and T.names(m)["ann"]["slot"] is not None, 60)
                t0 = time.monotonic() + 2.0
                await asyncio.sleep(2.0 + args.seconds)
                ob, oc = onsets(bob_ear, t0), onsets(carol_ear, t0)
                pairs = [x - min(oc, key=lambda y: abs(x - y)) for x in ob] if oc else []
                pairs = [d for d in pairs if abs(d) < 0.5]
                print(f"onsets of ann's tone: {len(ob)} on bob's page (B, through Redis), "
                      f"{len(oc)} on carol's (A)")
                if pairs:
                    q = np.percentile(pairs, [5, 50, 95])
                    print(f"bob's minus carol's: median {1e3 * statistics.median(pairs):.1f} "
                          f"ms, p5 {1e3 * q[0]:.1f} ms, p95 {1e3 * q[2]:.1f} ms, "
                          f"{len(pairs)} pairs")
                redis.stop()
                t_stop = time.monotonic()
                await asyncio.sleep(4.0)
                heard = [at for at, pcm in bob_ear.frames if at > t_stop + 1.0
                         and np.sqrt(np.mean(pcm * pcm)) > 0.05]
                print(f"Redis stopped 4 s: bob's slot played {len(heard)} loud frames after "
                      f"its first second; carol's {len(onsets(carol_ear, t_stop + 1.0))} "
                      f"onsets; servers up: {[p.poll() is None for p in servers]}")
                redis.start()
                # carol leaves: bob's one slot may have been given to her (silent) when the
                # remote members came back; it goes to ann then
                await on_c.close()
                await carol.pc.close()
                t_back = time.monotonic()
                deadline = t_back + 30.0
                while not onsets(bob_ear, t_back) and time.monotonic() < deadline:
                    await asyncio.sleep(0.2)
                back = onsets(bob_ear, t_back)
                print("Redis started again (empty): ann's tone on bob's page again after "
                      + (f"{back[0] - t_back:.1f} s" if back else "more than 30 s (never)"))
        for page in (ann, bob):
            await page.pc.close()

    try:
        asyncio.run(go())
    finally:
        T.stop_all(servers, redis, lambda line: "voice" in line or "redis" in line.lower())
    return 0


if __name__ == "__main__":
    sys.exit(main())

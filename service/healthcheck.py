"""``python -m articast.service.healthcheck``: the container's HEALTHCHECK (no curl needed).

Gateway / serve: ``GET http://127.0.0.1:$ARTICAST_PORT/healthz`` answers ``{"status": "ok"}``.
Worker (``--worker``): every session this host announces in Redis (``$ARTICAST_HUB``) was
rewritten within the last few seconds. Exit status 0 healthy, 1 not; one line on stderr.
"""

from __future__ import annotations

import json
import os
import sys
import urllib.request


def check_http(port: int, timeout: float = 3.0) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=timeout) as r:
        doc = json.loads(r.read())
    if doc.get("status") != "ok":
        raise RuntimeError(f"healthz says {doc.get('status')!r}")
    return "ok"


def check_worker(url: str, prefix: str, timeout: float = 3.0) -> str:
    import redis

    from articast.service.remote import STALE_S, from_redis_clock
    from articast.service.wire import now

    client = redis.Redis.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout)
    # (this machine's entries: their "t" back on this clock exactly, whatever Redis's says)
    entries = {(k.decode() if isinstance(k, bytes) else k): from_redis_clock(json.loads(v))
               for k, v in client.hgetall(prefix + "sessions").items()}
    mine = {n: e for n, e in entries.items() if e.get("host") in (None, os.uname().nodename)}
    if not mine:
        raise RuntimeError("no session announced in Redis")
    stale = [n for n, e in mine.items() if now() - float(e.get("t", 0)) > STALE_S]
    if stale:
        raise RuntimeError(f"sessions not announced for {STALE_S:g} s: {stale}")
    return f"{len(mine)} session(s) announced"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        if "--worker" in argv:
            check_worker(os.environ.get("ARTICAST_HUB", "redis://127.0.0.1:6379/0"),
                         os.environ.get("ARTICAST_HUB_PREFIX", "articast:"))
        else:
            check_http(int(os.environ.get("ARTICAST_PORT", "8765")))
    except Exception as exc:  # noqa: BLE001 - any failure is "unhealthy", said in one line
        print(f"unhealthy: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A room member's video through Redis, so that their tracker runs on another machine than
their connection (``articast room --hub redis://… --remote-trackers`` and ``articast
room-tracker``; issue 41, item 5).

**Frames.** The server's media process decodes the member's video as always; their feed's
forwarder (:class:`articast.service.webrtc.Feed`), which writes the newest frame into a local
worker's pipe, writes it instead to a :class:`FramePublisher`: the frame as a **JPEG** (colour,
quality :data:`JPEG_QUALITY`) appended to a Redis stream of its own, ``PREFIX
room:ROOM:frames:NAME:JOINED``, one per membership (:func:`frames_key`), capped at :data:`KEEP`
entries (``XADD … MAXLEN``: only the newest are kept, whoever reads them), each with its media
time, its capture time (when the server received it, in Redis's clock:
:mod:`articast.service.clock`) and its size; the stream's key lapses :data:`STREAM_TTL_MS` after
its last frame. The member leaving appends an ``end`` entry. Why JPEG and not the decoded
picture: a 640x480 frame is 460 kB as I420 and 307 kB as grey (the tracker needs colour: its
appearance maps are YCrCb), ~14 MB/s per member at 30 fps through one Redis; as a JPEG it is
~30-60 kB for a few ms of one core (docs/ROOM.md, "Trackers on other machines", measured).

**Tracker's side.** :class:`RedisInlet` reads that stream where a worker reads its pipe (the
``webrtc:NAME`` source's ``inlet``: ``poll``, ``recv``, ``close``), always the newest entry
(one ``XREAD BLOCK`` of the entries after the last one taken: their last), decoding the JPEG
in the worker process; it holds only the URL and the key until it is first read, so it is
handed to a worker process as a pipe is.

**Leases.** A tracker takes a member with ``SET PREFIX room:ROOM:tracker:NAME HOLDER|JOINED
NX PX ttl`` (JOINED: the membership's ``joined``, so that a lease of a former membership of
the name is never taken for the present one's) and renews it every third of the TTL (a Lua
script: only while it is still the holder), in Redis's own clock: a tracker that dies stops
renewing and the key lapses; another tracker then takes the member. The room's server reads
the holders each half second: a member whom no tracker holds for ``--tracker-wait`` seconds
is told so in one line and leaves (their page joins again by itself).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from articast.service.clock import CLOCK, wall

log = logging.getLogger("articast.room")

KEEP = 2
"""Entries a member's frame stream keeps (the newest): a tracker never reads an older one."""
STREAM_TTL_MS = 10_000
"""A frame stream nobody writes lapses this long after its last frame."""
JPEG_QUALITY = 80


def frames_key(prefix: str, room: str, name: str, joined: float) -> str:
    """One membership's frame stream: ``joined`` (the membership's join time, as the
    membership hash holds it) in the key, so that a tracker of a name that joins again never
    reads the former membership's last frames or its ``end`` (it ended the new session
    before any video). Written with 14 significant digits, as Redis's Lua (cjson) rewrites
    the hash's numbers: the server's and the tracker's keys are the same string."""
    return f"{prefix}room:{room}:frames:{name}:{joined:.14g}"


def lease_key(prefix: str, room: str, name: str) -> str:
    return f"{prefix}room:{room}:tracker:{name}"


# ----------------------------------------------------------------------------- the media process
class FramePublisher:
    """Where a member's feed writes their frames when their tracker is elsewhere: the
    ``send``/``close`` of a pipe's writing end (:meth:`articast.service.webrtc.Feed.attach`),
    on the feed's forwarder thread (blocking there only: a synchronous Redis client). A
    Redis error drops that frame and is said once (and once when it works again); it never
    ends the feed."""

    def __init__(self, url: str, key: str, quality: int = JPEG_QUALITY,
                 keep: int = KEEP) -> None:
        import redis

        self.key, self.quality, self.keep = key, quality, keep
        self._redis = redis.Redis.from_url(url, socket_connect_timeout=1.0, socket_timeout=2.0)
        CLOCK.start(url, quiet=True)
        self._failing = False
        self.frames = self.bytes = 0
        self.encode_s = 0.0
        """Counted since :meth:`counts` was last read."""

    def send(self, item: tuple[Any, ...]) -> None:
        if item[0] == "end":
            fields: dict[Any, Any] = {"end": str(item[1])}
        else:
            t, width, height, i420, arrived = item[:5]
            t0 = time.perf_counter()
            data = encode_jpeg(width, height, i420, self.quality)
            self.encode_s += time.perf_counter() - t0
            self.frames += 1
            self.bytes += len(data)
            # the capture time in Redis's clock (the tracker's machine has another monotonic
            # and maybe another wall clock), with the clock it was converted from
            offset, stamp = CLOCK.outgoing()
            fields = {"t": repr(float(t)),
                      "a": repr(wall() - (time.monotonic() - arrived) + offset),
                      "w": width, "h": height, "img": data}
            if stamp is not None:
                fields["c"], fields["o"] = stamp[0], repr(stamp[1])
        try:
            pipe = self._redis.pipeline(transaction=False)
            pipe.xadd(self.key, fields, maxlen=self.keep, approximate=False)
            pipe.pexpire(self.key, STREAM_TTL_MS)
            pipe.execute()
        except Exception as exc:  # noqa: BLE001 - Redis away: this frame is lost, not the feed
            if not self._failing:
                log.warning("%s: frames cannot be put in Redis (%r): dropped until it is back",
                            self.key, exc)
            self._failing = True
            time.sleep(0.2)
            return
        if self._failing:
            log.warning("%s: frames go to Redis again", self.key)
        self._failing = False

    def counts(self) -> tuple[int, int, float]:
        """(frames, bytes, encoding seconds) since the last call."""
        out = (self.frames, self.bytes, self.encode_s)
        self.frames = self.bytes = 0
        self.encode_s = 0.0
        return out

    def close(self) -> None:
        self._redis.close()


def encode_jpeg(width: int, height: int, i420: bytes, quality: int = JPEG_QUALITY) -> bytes:
    import cv2
    import numpy as np

    yuv = np.frombuffer(i420, np.uint8).reshape(height * 3 // 2, width)
    bgr = cv2.cvtColor(yuv, cv2.COLOR_YUV2BGR_I420)
    ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - cv2 encodes any 8-bit picture
        raise ValueError("the frame could not be encoded as JPEG")
    return jpg.tobytes()


# ----------------------------------------------------------------------------- the tracker
class RedisInlet:
    """A worker's inlet (``poll``, ``recv``, ``close``: a pipe's reading end) on a member's
    frame stream: items ``(t, width, height, jpeg, arrived, "jpeg")`` (``arrived`` on this
    machine's ``time.monotonic()``, from the entry's capture time in Redis's clock) and
    ``("end", reason)``. Picklable until first read."""

    def __init__(self, url: str, key: str) -> None:
        self.url, self.key = url, key
        self._redis: Any = None
        self._last: tuple[int, int] = (0, 0)
        self._item: Any = None
        self._failing = False

    def __getstate__(self) -> dict[str, Any]:
        return {"url": self.url, "key": self.key}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["url"], state["key"])  # type: ignore[misc]

    def _client(self) -> Any:
        if self._redis is None:
            import redis

            self._redis = redis.Redis.from_url(self.url, socket_connect_timeout=1.0,
                                               socket_timeout=10.0)
            CLOCK.start(self.url, quiet=True)
        return self._redis

    def _newest(self, block_s: float) -> Any:
        """The newest entry newer than the last one taken (waiting up to ``block_s`` for
        one; None if none came): one ``XREAD`` of the entries after it (at most
        :data:`KEEP`: the stream holds no more), its last."""
        last = f"{self._last[0]}-{self._last[1]}"
        got = self._client().xread({self.key: last}, count=KEEP,
                                   block=max(1, int(1000 * block_s)) if block_s > 0 else None)
        if not got:
            return None
        raw_id, fields = got[0][1][-1]
        sid = raw_id.decode() if isinstance(raw_id, bytes) else str(raw_id)
        ms, _, seq = sid.partition("-")
        self._last = (int(ms), int(seq or 0))
        return fields

    def poll(self, wait: float) -> bool:
        if self._item is not None:
            return True
        deadline = time.monotonic() + max(wait, 0.0)
        while True:
            left = deadline - time.monotonic()
            try:
                fields = self._newest(min(max(left, 0.0), 1.0))
            except Exception as exc:  # noqa: BLE001 - Redis away: no frame (the source says so)
                if not self._failing:
                    log.warning("%s: cannot read frames from Redis (%r)", self.key, exc)
                self._failing = True
                time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
                if time.monotonic() >= deadline:
                    return False
                continue
            self._failing = False
            if fields is None:
                if time.monotonic() >= deadline:
                    return False
                continue
            self._item = self._decode(fields)
            return True

    @staticmethod
    def _decode(fields: dict[bytes, bytes]) -> tuple[Any, ...]:
        if b"end" in fields:
            return ("end", fields[b"end"].decode("utf-8", "replace"))
        stamp = ([fields[b"c"].decode("utf-8", "replace"), float(fields[b"o"])]
                 if b"c" in fields else None)
        arrived = time.monotonic() - (wall() - CLOCK.local(float(fields[b"a"]), stamp))
        return (float(fields[b"t"]), int(fields[b"w"]), int(fields[b"h"]), fields[b"img"],
                arrived, "jpeg")

    def recv(self) -> tuple[Any, ...]:
        if self._item is None and not self.poll(3600.0):
            raise EOFError("no frame")
        item, self._item = self._item, None
        return item

    def close(self) -> None:
        if self._redis is not None:
            self._redis.close()
            self._redis = None


class RedisFeed:
    """A member's frames as a tracker's :class:`articast.service.session.SessionManager`
    sees them (its ``feeds``): each worker gets a fresh :class:`RedisInlet`."""

    def __init__(self, url: str, key: str) -> None:
        self.url, self.key = url, key
        self.ended = ""

    def new_inlet(self) -> RedisInlet:
        return RedisInlet(self.url, self.key)

    def close(self, reason: str) -> None:
        self.ended = self.ended or reason


# ----------------------------------------------------------------------------- leases
RENEW = """
-- 1: renewed; 2: it had lapsed and nobody had taken it: taken again; 0: another holds it
local holder = redis.call('GET', KEYS[1])
if holder == ARGV[1] then
  redis.call('PEXPIRE', KEYS[1], tonumber(ARGV[2]))
  return 1
end
if not holder then
  redis.call('SET', KEYS[1], ARGV[1], 'PX', tonumber(ARGV[2]))
  return 2
end
return 0
"""

RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


class Leases:
    """A tracker's leases on a room's members (see the module's docstring)."""

    def __init__(self, redis: Any, prefix: str, room: str, holder: str, ttl_s: float) -> None:
        self.redis, self.prefix, self.room, self.holder = redis, prefix, room, holder
        self.ttl_ms = max(100, round(1000 * ttl_s))
        self._renew = redis.register_script(RENEW)
        self._release = redis.register_script(RELEASE)
        self._values: dict[str, str] = {}

    def key(self, name: str) -> str:
        return lease_key(self.prefix, self.room, name)

    async def claim(self, name: str, joined: float) -> bool:
        """Take ``name``'s membership of ``joined`` (False: another tracker has it)."""
        value = f"{self.holder}|{joined!r}"
        if await self.redis.set(self.key(name), value, nx=True, px=self.ttl_ms):
            self._values[name] = value
            return True
        return False

    async def renew(self, names: list[str]) -> list[str]:
        """Renew these leases: the names another tracker holds now. A lease that lapsed
        (this tracker renewed it too late: its loop was held) and that nobody took is taken
        again, in one line of the log."""
        lost = []
        for name in names:
            value = self._values.get(name, self.holder)
            kept = await self._renew(keys=[self.key(name)], args=[value, self.ttl_ms])
            if not kept:
                lost.append(name)
                self._values.pop(name, None)
            elif kept == 2:
                log.warning("room %s: the lease on %s lapsed before this tracker renewed it "
                            "(nobody had taken it: kept)", self.room, name)
        return lost

    async def release(self, name: str) -> None:
        value = self._values.pop(name, None)
        if value is not None:
            await self._release(keys=[self.key(name)], args=[value])


async def holders(redis: Any, prefix: str, room: str,
                  members: dict[str, float]) -> dict[str, str]:
    """Which tracker tracks each of these members (``{name: joined}``) in that membership
    ("" for none): the room's server asks."""
    if not members:
        return {}
    names = list(members)
    values = await redis.mget([lease_key(prefix, room, n) for n in names])
    out = {}
    for name, raw in zip(names, values, strict=True):
        value = raw.decode() if isinstance(raw, bytes) else (raw or "")
        holder, _, joined = value.rpartition("|")
        try:
            # (the membership's Lua scripts keep 14 digits of ``joined``: 0.1 ms here)
            ours = bool(holder) and abs(float(joined) - members[name]) < 1e-3
        except ValueError:
            ours = False
        out[name] = holder if ours else ""
    return out

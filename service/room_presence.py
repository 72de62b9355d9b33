"""A room's membership in Redis, so that every server of the room (``articast room --hub
redis://…``) knows who is in it, whichever server holds each member's connection.

One hash per room, ``PREFIX room:ROOM:members``: a field per member, its value a JSON object
``{"name", "slot", "joined", "server", "delegate", "tracking", "expires"}``:

* ``slot`` the member's seat in the room (the lowest free one, ``0 .. max - 1``, taken
  atomically with the name: the room's limit holds across servers);
* ``joined`` when they joined (wall clock of the server that took them: the pages' order);
* ``server`` which server holds their connection (:data:`articast.service.remote.RUN`);
* ``tracking`` ``local`` (their server tracks them) or ``remote`` (an ``articast
  room-tracker`` does, from their frames in Redis: :mod:`articast.service.room_frames`);
* ``delegate`` whether they are shown as an enrolled delegate (their server rewrites it
  false when it cannot share that delegate: then the other servers show the generic head);
* ``expires`` when the entry lapses, in **Redis's own clock** (``TIME``, milliseconds): the
  server holding the member rewrites it every ``ttl / 3``; if that server dies, the entry
  lapses ``ttl`` after its last rewrite whatever the servers' clocks say. Redis 7.0 has no
  per-field TTL (``HEXPIRE`` is 7.4), so every script below treats a lapsed entry as absent and
  deletes it; the hash itself expires ``ttl`` after the last rewrite of any member.

Every change is one Lua script (atomic in Redis): two servers cannot both take a name or the
last seat. The local room (``articast room`` without ``--hub``) does not use this module.

A **wrong token** counts against its address room-wide: ``PREFIX room:ROOM:wrong:ADDRESS``,
a counter that lapses ``forget_s`` (10 minutes) after the address's last wrong token, so the
back-off (:class:`articast.service.security.FailedAttempts`) is the same on every server of the
room (a guesser spreading over N servers gets the free tries once, not N times).

A member's **delegate** (their enrolled face: the JSON ``/room/api/delegate/NAME`` serves,
~0.5 MB with its 256-pixel texture) is a string key of its own, ``PREFIX
room:ROOM:delegate:NAME:SERVER``, bound to the server holding the member (another server
reads the key the member's entry names, so a key left by a former holder is never served).
It is written once per session run, only while that server holds the member's entry (one
script: a member who left meanwhile leaves no key), with the membership's TTL, renewed with
it; it goes with the member's entry when they leave (the same script), and lapses a TTL after
its server stopped renewing it.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Any

from articast.service.jsonsafe import dumps

log = logging.getLogger("articast.room")

_NOW = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
"""

_PRUNE = _NOW + """
local live = {}
local all = redis.call('HGETALL', KEYS[1])
for i = 1, #all, 2 do
  local ok, e = pcall(cjson.decode, all[i + 1])
  if ok and type(e) == 'table' and tonumber(e.expires) and tonumber(e.expires) >= now then
    live[all[i]] = e
  else
    redis.call('HDEL', KEYS[1], all[i])
  end
end
"""

CLAIM = _PRUNE + """
-- ARGV: name, entry (JSON, without slot/expires), ttl ms, max members
local name, ttl, max = ARGV[1], tonumber(ARGV[3]), tonumber(ARGV[4])
if live[name] then return {'taken', live[name].server or ''} end
local used, n = {}, 0
for _, e in pairs(live) do used[tonumber(e.slot) or -1] = true; n = n + 1 end
if n >= max then return {'full', tostring(n)} end
local slot = 0
while used[slot] do slot = slot + 1 end
local e = cjson.decode(ARGV[2])
e.slot, e.expires = slot, now + ttl
redis.call('HSET', KEYS[1], name, cjson.encode(e))
redis.call('PEXPIRE', KEYS[1], ttl)
return {'ok', tostring(slot)}
"""

REFRESH = _PRUNE + """
-- ARGV: server, ttl ms, then name, entry (JSON) pairs: this server's members. An entry
-- still here is extended; a lapsed one is put back (the server still holds that member)
-- unless another server has the name now: those names are returned.
local server, ttl = ARGV[1], tonumber(ARGV[2])
local lost = {}
for i = 3, #ARGV, 2 do
  local name, e = ARGV[i], live[ARGV[i]]
  if e and e.server ~= server then
    table.insert(lost, name)
  else
    local new = cjson.decode(ARGV[i + 1])
    if e then e.delegate = new.delegate else e = new end
    e.expires = now + ttl
    redis.call('HSET', KEYS[1], name, cjson.encode(e))
  end
end
if #ARGV > 2 then redis.call('PEXPIRE', KEYS[1], ttl) end
return lost
"""

LEAVE = _PRUNE + """
-- KEYS: the hash, the member's delegate key on this server. ARGV: name, server: the entry
-- goes if this server holds it; this server's copy of their delegate goes in any case
redis.call('DEL', KEYS[2])
local e = live[ARGV[1]]
if e and e.server == ARGV[2] then redis.call('HDEL', KEYS[1], ARGV[1]); return 1 end
return 0
"""

SHARE = _PRUNE + """
-- KEYS: the hash, the member's delegate key on this server. ARGV: name, server, the
-- delegate's JSON, ttl ms: written only while this server holds the member's entry
local e = live[ARGV[1]]
if not e or e.server ~= ARGV[2] then return 0 end
redis.call('SET', KEYS[2], ARGV[3], 'PX', tonumber(ARGV[4]))
return 1
"""

LIVE = _PRUNE + """
local out = {}
for name, e in pairs(live) do table.insert(out, cjson.encode(e)) end
return out
"""


class Refused(Exception):
    """A name or seat the room's Redis did not give: ``status`` (409, 429) and one line."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status, self.detail = status, detail


@dataclass
class Presence:
    """This server's side of a room's membership hash (see the module's docstring)."""

    redis: Any
    key: str
    server: str
    ttl_s: float = 10.0

    def __post_init__(self) -> None:
        self._scripts = {name: self.redis.register_script(text) for name, text in (
            ("claim", CLAIM), ("refresh", REFRESH), ("leave", LEAVE), ("live", LIVE),
            ("share", SHARE))}
        self.delegates = self.key.removesuffix("members") + "delegate:"
        """The prefix of the members' delegate keys (``PREFIX room:ROOM:delegate:``)."""

    def delegate_key(self, name: str, server: str = "") -> str:
        """The key of ``name``'s delegate as ``server`` (default: this one) shares it."""
        return f"{self.delegates}{name}:{server or self.server}"

    @property
    def ttl_ms(self) -> int:
        return max(100, round(1000 * self.ttl_s))

    async def claim(self, name: str, joined: float, delegate: bool, max_members: int,
                    tracking: str = "local") -> int:
        """Take ``name`` and a seat for this server: the seat (``slot``); :class:`Refused`
        when the name is in the room (on any server) or the room is full. ``tracking``:
        ``remote`` when a room tracker is to take them (``--remote-trackers``)."""
        entry = dumps({"name": name, "joined": joined, "server": self.server,
                       "delegate": delegate, "tracking": tracking})
        out = await self._scripts["claim"](keys=[self.key],
                                           args=[name, entry, self.ttl_ms, max_members])
        kind, value = (x.decode() if isinstance(x, bytes) else str(x) for x in out)
        if kind == "taken":
            raise Refused(409, f"{name!r} is in the room already (on another of the room's "
                          "servers): choose another name, or leave there first")
        if kind == "full":
            raise Refused(429, f"the room is full ({max_members} participants)")
        return int(value)

    async def refresh(self, members: dict[str, dict[str, Any]]) -> list[str]:
        """Extend this server's members' entries (``{name: entry}``); the names another
        server holds now (this server lost them while Redis or it was away)."""
        args: list[Any] = [self.server, self.ttl_ms]
        for name, entry in members.items():
            args += [name, dumps({**entry, "name": name, "server": self.server})]
        lost = await self._scripts["refresh"](keys=[self.key], args=args)
        return [x.decode() if isinstance(x, bytes) else str(x) for x in lost]

    async def leave(self, name: str) -> None:
        """``name``'s entry goes if this server holds it, and this server's copy of their
        delegate in any case."""
        await self._scripts["leave"](keys=[self.key, self.delegate_key(name)],
                                     args=[name, self.server])

    async def share_delegate(self, name: str, body: bytes) -> bool:
        """Put ``name``'s delegate (its JSON) where the room's other servers read it, for a
        TTL; False when this server no longer holds ``name`` (nothing written)."""
        return bool(await self._scripts["share"](
            keys=[self.key, self.delegate_key(name)],
            args=[name, self.server, body, self.ttl_ms]))

    async def keep_delegates(self, names: list[str]) -> list[str]:
        """Renew the TTL of these members' delegates (this server's copies): the names whose
        key is gone (lapsed while Redis or this server was away: to be written again)."""
        if not names:
            return []
        pipe = self.redis.pipeline(transaction=False)
        for name in names:
            pipe.pexpire(self.delegate_key(name), self.ttl_ms)
        return [n for n, kept in zip(names, await pipe.execute(), strict=True) if not kept]

    async def drop_delegate(self, name: str) -> None:
        """This server's copy of ``name``'s delegate goes (their entry is left as it is)."""
        await self.redis.delete(self.delegate_key(name))

    async def delegate(self, name: str, server: str) -> bytes | None:
        """``name``'s delegate as ``server`` (the one holding them) shared it, or None."""
        body = await self.redis.get(self.delegate_key(name, server))
        return None if body is None else bytes(body)

    async def wrong_token(self, address: str, forget_s: float) -> int:
        """Count a wrong token from ``address`` (:func:`articast.service.security.client_key`)
        room-wide: how many this address sent to any of the room's servers, none of them
        more than ``forget_s`` after the one before (the count lapses then, in Redis's
        clock)."""
        key = f"{self.key.removesuffix('members')}wrong:{address}"
        pipe = self.redis.pipeline(transaction=True)
        pipe.incr(key)
        pipe.pexpire(key, max(1, round(1000 * forget_s)))
        count, _ = await pipe.execute()
        return int(count)

    async def live(self) -> dict[str, dict[str, Any]]:
        """Every member whose entry has not lapsed, on any server: ``{name: entry}``."""
        out: dict[str, dict[str, Any]] = {}
        for raw in await self._scripts["live"](keys=[self.key]):
            try:
                e = json.loads(raw)
            except (ValueError, RecursionError):
                continue
            if isinstance(e, dict) and isinstance(e.get("name"), str):
                out[e["name"]] = e
        return out

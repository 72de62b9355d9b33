"""``articast room-tracker ROOM --hub redis://…``: tracks a room's members on any machine.

The room's servers run with ``--remote-trackers``: their media processes put each member's
frames in Redis (:mod:`articast.service.room_frames`) and their membership entries say
``"tracking": "remote"``. This process reads the room's membership every half second, takes
members with a lease (``SET NX PX``, renewed every third of its TTL), and tracks each taken
member as a session of its own, with the same worker code a room server uses
(:mod:`articast.service.worker`, a worker process per member, the ``webrtc:NAME`` source
reading the member's stream instead of a pipe). Its sessions publish on the Redis hub and
are announced in the sessions hash exactly as ``articast track-worker``'s
(:mod:`articast.service.worker_role`), which is where every room server's pages read every
member's frames: nothing on the servers or the pages changes.

A member leaves (their entry goes, or is taken by another run of the name): their session is
stopped and the lease released. A session that ends or fails is not started again for that
membership: it is kept, with its lease, its state announced, until the member leaves (their
server tells them why, from that state). A lease this tracker finds another holds (it was too
late renewing it, and another took it) stops its session: one tracker per member.
This process killed: its leases lapse after their TTL and another tracker takes its members;
with none left, the room's servers tell the members (``--tracker-wait``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable
from typing import Any

from articast.service.remote import RUN
from articast.service.room_frames import Leases, RedisFeed, frames_key
from articast.service.room_presence import Presence
from articast.service.session import TERMINAL, SessionManager
from articast.service.settings import CaptureSettings, SessionPolicy
from articast.service.worker import SessionSpec
from articast.service.worker_role import publishing_manager, stop_on_signals

log = logging.getLogger("articast.room_tracker")

POLL_S = 0.5
"""How often the membership is read."""


async def run_room_tracker(url: str, prefix: str, room: str, speakers: str = "",
                           processor: str = "auto", seed: int = 1, lease_s: float = 6.0,
                           max_members: int = 8, capture: CaptureSettings | None = None,
                           policy: SessionPolicy | None = None,
                           started: Callable[[], None] | None = None,
                           stop: asyncio.Event | None = None) -> None:
    """Track ``room``'s remote-tracked members until SIGTERM/SIGINT (or ``stop``)."""
    from articast.service.room import RoomConfig

    stop = stop_on_signals(stop)
    config = RoomConfig(name=room, speakers=speakers, seed=seed)
    policy = policy or SessionPolicy()
    # (delegates: an enrolled member's hello says they have one; the room's servers serve it,
    # from the speakers folder they share with this tracker)
    manager, hub, announcer = publishing_manager(url, prefix, capture or CaptureSettings(),
                                                 policy, delegates=True)
    presence = Presence(hub.redis, f"{prefix}room:{room}:members", RUN)
    leases = Leases(hub.redis, prefix, room, RUN, lease_s)
    mine: dict[str, float] = {}
    """Members this tracker holds -> when they joined (their membership's run)."""
    finished: set[tuple[str, float]] = set()
    """Memberships whose session ended or failed here: not taken again."""
    renewed = 0.0
    failing = False

    async def drop(name: str, why: str, release: bool = True) -> None:
        mine.pop(name, None)
        if name in manager.sessions:
            await manager.remove(name)
        if release:
            with contextlib.suppress(Exception):
                await leases.release(name)
        log.warning("room %s: no longer tracking %s (%s)", room, name, why)

    log.warning("room tracker %s for room %s on %s (lease %g s)", RUN, room, url.split("@")[-1],
                lease_s)
    if started:
        started()
    try:
        while not stop.is_set():
            t = time.monotonic()
            try:
                if mine and t - renewed >= lease_s / 3:
                    renewed = t
                    for name in await leases.renew(list(mine)):
                        await drop(name, "another tracker holds them now", release=False)
                entries = await presence.live()
                if failing:
                    log.warning("room %s: Redis is back", room)
                failing = False
            except Exception as exc:  # noqa: BLE001 - Redis away: keep tracking, retry
                if not failing:
                    log.warning("room %s: Redis cannot be reached (%r)", room, exc)
                failing = True
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), POLL_S)
                continue
            wanted = {n: float(e.get("joined", 0.0)) for n, e in entries.items()
                      if e.get("tracking") == "remote"}
            for name, joined in list(mine.items()):
                session = manager.sessions.get(name)
                if wanted.get(name) != joined:
                    await drop(name, "they left the room")
                elif session is not None and session.state in TERMINAL and \
                        (name, joined) not in finished:
                    # kept, with its lease (its state announced under this tracker's run:
                    # their server tells them why), until they leave; not restarted
                    finished.add((name, joined))
                    log.warning("room %s: %s's session %s: %s", room, name, session.state,
                                session.detail)
            finished = {(n, j) for n, j in finished if mine.get(n) == j}
            for name, joined in sorted(wanted.items(), key=lambda kv: kv[1]):
                if name in mine or (name, joined) in finished or len(mine) >= max_members:
                    continue
                if name in manager.sessions:  # (a former membership's session, stopping)
                    continue
                try:
                    if not await leases.claim(name, joined):
                        continue
                except Exception:  # noqa: BLE001 - Redis away: next round
                    break
                mine[name] = joined
                await _track(manager, config, url, prefix, name, joined, processor)
                log.warning("room %s: tracking %s", room, name)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), POLL_S)
            held = time.monotonic() - t - POLL_S
            if held > lease_s / 3:
                log.warning("room %s: this tracker's loop was held for %.1f s (its leases "
                            "last %g s)", room, held, lease_s)
    finally:
        for name in list(mine):
            with contextlib.suppress(Exception):
                await drop(name, "the tracker is stopping")
        await manager.close(policy.restart_max_s)
        await asyncio.sleep(0.1)  # the writer publishes the last status messages
        await announcer.close()
        hub.close()


async def _track(manager: SessionManager, config: Any, url: str, prefix: str, name: str,
                 joined: float, processor: str) -> None:
    """``name``'s session here: as a room server starts it, frames from Redis."""
    speaker = config.speaker_of(name)
    spec = SessionSpec(name, f"webrtc:{name}" + ("" if speaker else f"?seed={config.seed}"),
                       speaker=speaker, processor=processor,
                       media_roots=(os.path.realpath(config.speakers),) if speaker else ())
    manager.feeds[name] = RedisFeed(url, frames_key(prefix, config.name, name, joined))
    await manager.add(spec)

"""``articast track-worker``: sessions that publish to Redis, with no socket of their own."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
from collections.abc import Callable

from articast.service.redis_hub import RedisHub
from articast.service.remote import Announcer, Directory, EventCodec
from articast.service.session import SessionManager
from articast.service.settings import CaptureSettings, SessionPolicy
from articast.service.worker import SessionSpec

log = logging.getLogger("articast.worker_role")


def stop_on_signals(stop: asyncio.Event | None) -> asyncio.Event:
    """``stop`` (a new event if None), set by SIGTERM or SIGINT where the loop can say so."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    return stop


def publishing_manager(url: str, prefix: str, capture: CaptureSettings, policy: SessionPolicy,
                       record_dir: str = "", delegates: bool = False
                       ) -> tuple[SessionManager, RedisHub[object], Announcer]:
    """Sessions with no socket of their own: a manager whose frames go out on the Redis hub
    and whose sessions are announced in its sessions hash (the announcer started)."""
    manager = SessionManager(None, capture, policy, record_dir)  # type: ignore[arg-type]
    manager.delegates = delegates
    hub: RedisHub[object] = RedisHub(url, EventCodec(Directory(), manager.sessions.get),
                                     prefix=prefix)
    manager.hub = hub
    announcer = Announcer(hub.redis, prefix + "sessions", lambda: manager.sessions)
    announcer.start()
    return manager, hub, announcer


async def run_track_worker(url: str, prefix: str, specs: list[SessionSpec],
                           capture: CaptureSettings, policy: SessionPolicy, record_dir: str,
                           started: Callable[[], None] | None = None,
                           stop: asyncio.Event | None = None) -> None:
    """Run ``specs`` until SIGTERM/SIGINT (or ``stop``), publishing on the Redis hub."""
    stop = stop_on_signals(stop)
    # (no delegates: the gateway serves subscribers and cannot read our folders)
    manager, hub, announcer = publishing_manager(url, prefix, capture, policy, record_dir)
    try:
        for spec in specs:
            await manager.add(spec)
        if started:
            started()
        await stop.wait()
    finally:
        await manager.close(policy.restart_max_s)
        await asyncio.sleep(0.1)  # let the writer publish the last status messages
        await announcer.close()
        hub.close()

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


async def run_track_worker(url: str, prefix: str, specs: list[SessionSpec],
                           capture: CaptureSettings, policy: SessionPolicy, record_dir: str,
                           started: Callable[[], None] | None = None,
                           stop: asyncio.Event | None = None) -> None:
    """Run ``specs`` until SIGTERM/SIGINT (or ``stop``), publishing on the Redis hub."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    directory = Directory()
    manager = SessionManager(None, capture, policy, record_dir)  # type: ignore[arg-type]
    manager.delegates = False  # the gateway serves subscribers and cannot read our folders
    hub: RedisHub[object] = RedisHub(url, EventCodec(directory, manager.sessions.get),
                                     prefix=prefix)
    manager.hub = hub
    announcer = Announcer(hub.redis, prefix + "sessions", lambda: manager.sessions)
    announcer.start()
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

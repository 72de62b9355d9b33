"""What the app holds (:class:`Service`): its configuration, the hub, the sessions, the open
connections, the per-address budgets, the hello cache and the stall watchdog; and the
configuration itself (:class:`ServiceConfig`)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from articast.client import protocol as P
from articast.service.admission import AddressBudgets
from articast.service.hub import InMemoryHub
from articast.service.jsonsafe import dumps
from articast.service.metrics import render
from articast.service.security import AccessPolicy
from articast.service.session import SessionManager
from articast.service.settings import CaptureSettings, HubSettings, ServerSettings, SessionPolicy
from articast.service.wire import hello
from articast.service.worker import SessionSpec

if TYPE_CHECKING:  # the connections it holds: types only, no import at run time
    from articast.service.subscribe import Connection, Subscriber

log = logging.getLogger("articast.app")
HELLO_OPTIONS = '"streams":[],"encoding":"json","rate":null,'
"""The per-subscription fields of a hello encoded for no subscription (see hello_text)."""


@dataclass(frozen=True)
class ServiceConfig:
    server: ServerSettings = field(default_factory=ServerSettings)
    hub: HubSettings = field(default_factory=HubSettings)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    policy: SessionPolicy = field(default_factory=SessionPolicy)
    sessions: tuple[SessionSpec, ...] = ()
    access: AccessPolicy = field(default_factory=AccessPolicy)
    """Token, Host and Origin rules, media roots and devices allowed over HTTP."""
    hub_url: str = ""
    """"" = the in-memory hub; ``redis://HOST:PORT/DB`` = Redis (sessions of every worker)."""
    role: str = "serve"
    """``serve`` (sessions here, and subscribers) or ``gateway`` (subscribers only)."""
    hub_prefix: str = "articast:"
    """Redis key and channel prefix (several deployments may share one Redis)."""
    http_processors: tuple[str, ...] = ("auto", "truth", "tracker", "live")
    """Processors a session added over HTTP may name: importing ``module:callable`` on a
    client's word would run the client's choice of code, so only these are accepted."""
    delegates: bool = True
    """Serve each speaker's delegate to token holders (False: ``serve --no-delegate``)."""
    room: Any = None
    """A :class:`articast.service.room.RoomConfig`: the meeting room's routes under ``/room``
    (``articast room``), which check the room's own tokens."""


class Service:
    """What the app holds: the hub, the sessions, the open connections."""

    def __init__(self, config: ServiceConfig,
                 on_live: Callable[[dict[str, str]], None] | None = None) -> None:
        self.config = config
        self.on_live = on_live
        self._announce_task: asyncio.Task[None] | None = None
        self.hub: Any = InMemoryHub()  # a RedisHub replaces it in start() with --hub redis://
        self.manager = SessionManager(self.hub, config.capture, config.policy,
                                      config.server.record)
        self.manager.delegates = config.delegates
        self.directory: Any = None  # articast.service.remote.Directory on Redis
        self._remote: list[Any] = []
        if config.server.vmc:
            from articast.service.vmc import VmcSender, parse_host_port

            self.manager.vmc = VmcSender(*parse_host_port(config.server.vmc),
                                         names=config.server.vmc_names)
        self.connections: set[Connection] = set()
        self.budgets = AddressBudgets(config.hub)
        self._hellos: dict[tuple[Any, ...], tuple[Any, Any, str]] = {}
        self._watchdog: asyncio.Task[None] | None = None
        self.media: Any = None
        """The media process (:class:`articast.service.media.MediaProcess`): participants'
        WebRTC connections, started on the first offer."""
        self.room: Any = None
        """The meeting room (:class:`articast.service.room.Room`) when the app has one."""

    def media_process(self) -> Any:
        if self.media is None:
            from articast.service.media import MediaProcess

            # (with Redis, the media process relays the room's voices there itself)
            self.media = MediaProcess(self.config.hub_url, self.config.hub_prefix)
        return self.media

    def lookup(self, name: str) -> Any:
        """The session a subscriber means: local, or (on Redis) any worker's."""
        if self.directory is not None:
            return self.directory.get(name)
        return self.manager.sessions.get(name)

    def session_names(self) -> list[str]:
        names = set(self.manager.sessions)
        if self.directory is not None:
            names |= set(self.directory.sessions)
        return sorted(names)

    def session_dicts(self) -> list[dict[str, Any]]:
        out = [s.to_dict() for s in self.manager.sessions.values()]
        if self.directory is not None:
            out += [s.to_dict(self.hub.subscriber_count(n))
                    for n, s in sorted(self.directory.sessions.items())
                    if n not in self.manager.sessions]
        return out

    def states(self) -> dict[str, str]:
        out = {n: s.state for n, s in self.manager.sessions.items()}
        if self.directory is not None:
            for n, s in self.directory.sessions.items():
                out.setdefault(n, s.state)
        return out

    def subscriber_total(self) -> int:
        return sum(len(c.subs) for c in self.connections)

    def subscriptions_of(self, key: str) -> int:
        """Subscriptions of one client address, over all its connections."""
        return sum(len(c.subs) for c in self.connections if c.key == key)

    def hello_text(self, req: P.Subscribe, session: Any, streams: list[Any]) -> str:
        """The hello of a subscription. The costly part (the model geometry, ~250 kB of JSON
        for 500 points: ~5 ms) is encoded once per session run, state and ``geometry``
        flag; the subscription's own ``streams``, ``encoding`` and ``rate`` are written into
        it (issue 39: a client resubscribing with a new rate each time missed the cache and
        cost an encode per subscribe, 40 in a burst stalling every bystander)."""
        key = (req.session, session.sid, session.state, req.geometry)
        hit = self._hellos.get(key)
        if hit is None or hit[0] is not session.description or hit[1] is not session.source_info:
            scan_url = (f"/api/sessions/{req.session}/scan"
                        if self.config.server.scan and (session.description or {}).get("geometry")
                        else None)
            plain = P.Subscribe(session=req.session, geometry=req.geometry)
            text = hello(req.session, session.sid, session.description, session.source_info,
                         plain, session.state, [], scan_url)
            if HELLO_OPTIONS not in text:
                raise AssertionError("the hello's fields moved: update HELLO_OPTIONS")
            if len(self._hellos) >= 256:
                self._hellos.pop(next(iter(self._hellos)))
            hit = self._hellos[key] = (session.description, session.source_info, text)
        rate = "null" if req.rate is None else dumps(float(req.rate))
        options = (f'"streams":{dumps([str(x) for x in streams], separators=(",", ":"))},'
                   f'"encoding":{dumps(str(req.encoding))},"rate":{rate},')
        return hit[2].replace(HELLO_OPTIONS, options, 1)

    def count_drops(self, s: Subscriber) -> None:
        """Add an ending subscription's drops to its session's total (once)."""
        session = self.lookup(s.req.session)
        if session is not None and not s.counted:
            session.metrics.subscriber_dropped += s.sub.dropped
        s.counted = True

    async def start(self) -> None:
        if self.config.hub_url:
            await self._start_redis()
        for spec in self.config.sessions:
            await self.manager.add(spec)
        if self.room is not None:
            self.room.start()  # its watcher; with Redis, the room's membership from now on
            if self.room.config.warm_media:  # in a thread: the fork server imports ~5 s
                asyncio.get_running_loop().run_in_executor(None, self.media_process().start)
        self._watchdog = asyncio.create_task(self._watch(), name="stall watchdog")
        if self.on_live is not None:
            self._announce_task = asyncio.create_task(self._announce(), name="announce")

    async def _announce(self) -> None:
        """Call ``on_live`` once every initial session streams (its first frame is on the
        hub) or has said why it cannot, and a face streams (a session held for its first
        subscriber counts as streaming): a URL printed then shows a moving face, not an
        empty page. It is told which sessions have failed already ({name: reason}): no URL
        is printed for those."""
        sessions = list(self.manager.sessions.values())
        shown = [s for s in sessions if not s.spec.wait_for_subscriber]
        await asyncio.gather(*(s.settled.wait() for s in shown))
        # a URL only once a face streams (issue 39: it was printed for a missing camera and
        # after a crash, over an empty page): a session that said why it cannot is waited
        # for, its reason on the console; when every one has failed, nothing is served
        while shown and len(shown) == len(sessions) and not any(
                s.streaming.is_set() for s in shown) and not all(
                s.state in ("failed", "ended", "stopped") for s in shown):
            await asyncio.sleep(0.1)
        assert self.on_live is not None
        self.on_live({n: s.detail for n, s in self.manager.sessions.items()
                      if s.state == "failed"})

    async def _watch(self) -> None:
        limit = self.config.hub.stall_timeout_s
        while True:
            await asyncio.sleep(min(1.0, limit / 4))
            t = time.monotonic()
            for c in list(self.connections):
                if c.sending_since and t - c.sending_since > limit:
                    log.info("disconnecting a subscriber stalled for %.1f s", t - c.sending_since)
                    c.sending_since = 0.0
                    c.abort()

    async def _start_redis(self) -> None:
        from articast.service.redis_hub import RedisHub
        from articast.service.remote import Announcer, Directory, EventCodec, Poller

        self.directory = Directory()
        codec = EventCodec(self.directory, self.manager.sessions.get)
        self.hub = self.manager.hub = RedisHub(self.config.hub_url, codec,
                                               prefix=self.config.hub_prefix)
        key = self.config.hub_prefix + "sessions"
        poller = Poller(self.hub.redis, key, self.directory, self.hub.publish_local)
        poller.start()
        self._remote.append(poller)
        if self.config.role == "serve":
            announcer = Announcer(self.hub.redis, key, lambda: self.manager.sessions)
            announcer.start()
            self._remote.append(announcer)

    async def stop(self) -> None:
        if self._watchdog:
            self._watchdog.cancel()
        if self._announce_task:
            self._announce_task.cancel()
        if self.room is not None:
            await self.room.close()
        await self.manager.close(self.config.server.shutdown_timeout_s)
        if self.media is not None:
            await asyncio.to_thread(self.media.close)
        for r in self._remote:
            if asyncio.iscoroutinefunction(r.close):
                await r.close()
            else:
                r.close()
        self.hub.close()

    def metrics_text(self) -> str:
        subs: dict[str, int] = {}
        live_dropped: dict[str, int] = {}
        for c in self.connections:
            for name, sub in c.subs.items():
                subs[name] = subs.get(name, 0) + 1
                live_dropped[name] = live_dropped.get(name, 0) + sub.sub.dropped
        every = dict(self.directory.sessions) if self.directory is not None else {}
        every.update(self.manager.sessions)
        rows = {name: (sess.metrics, subs.get(name, 0), sess.up,
                       sess.metrics.subscriber_dropped + live_dropped.get(name, 0))
                for name, sess in every.items()}
        return render(rows, len(self.connections))


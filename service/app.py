"""The FastAPI application: ``WS /ws`` and the HTTP API.

``WS /ws``                     subscribe to sessions (protocol v1, :mod:`articast.client.protocol`)
``GET /api/sessions``          the sessions and their state
``POST /api/sessions``         start one: ``{"name", "source", "model"?, "appearance"?,
                               "camera"?, "processor"?, "wait_for_subscriber"?, "preview"?}``
``DELETE /api/sessions/{name}`` stop one
``GET /api/protocol``          the JSON Schema of the protocol
``GET /healthz``               liveness and session states
``GET /metrics``               Prometheus text

Access (:mod:`articast.service.security`): every request must name this server in ``Host``
and, from a browser, come from an allowed ``Origin`` (403 otherwise); with a token configured,
everything but ``/healthz``, ``/api/protocol`` and the avatar's static files needs it (401);
the session API (POST/DELETE) needs a token always (403 when none is configured).

Each WebSocket connection has one receive loop (client messages, every bad one answered by an
``error``) and one sender task per subscription, which awaits only its own hub queue and its
own socket: a stalled client stalls nobody else, and one stalled for longer than
``stall_timeout_s`` is disconnected by a watchdog.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi import FastAPI, HTTPException, Request, WebSocket
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from articast.client import protocol as P
from articast.core.errors import ArticastError, InputError
from articast.service.hub import HubClosed, InMemoryHub
from articast.service.jsonsafe import dumps
from articast.service.metrics import render
from articast.service.middleware import (
    BodyLimit,
    BodyTimeout,
    BodyTooLarge,
    Guard,
    MessageBucket,
    TokenGate,
    deny,
)
from articast.service.security import AccessPolicy, FailedAttempts, Forbidden, client_key
from articast.service.session import SessionManager
from articast.service.settings import CaptureSettings, HubSettings, ServerSettings, SessionPolicy
from articast.service.wire import (
    FrameEvent,
    ReadyEvent,
    StatusEvent,
    error_text,
    hello,
    now,
    status_text,
)
from articast.service.worker import SessionSpec

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


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    source: str = Field(min_length=1, max_length=4096)
    model: str = ""
    appearance: str = ""
    camera: str = ""
    processor: str = "auto"
    wait_for_subscriber: bool = False
    speaker: str = ""
    preview: bool = False


def path_name_problem(path: str) -> str:
    """Why ``path`` cannot name a file on this system ("" if it can): a NUL byte, a name
    over 255 bytes or a path over 4096 (the kernel's limits), said before anything opens it."""
    if "\0" in path:
        return "a file name cannot contain a NUL byte"
    encoded = path.encode("utf-8", "surrogateescape")
    if len(encoded) > 4096:
        return f"a path of {len(encoded)} bytes is over the limit of 4096"
    longest = max((len(part) for part in encoded.split(b"/")), default=0)
    if longest > 255:
        return f"a file name of {longest} bytes is over the limit of 255"
    return ""


def confined_spec(access: AccessPolicy, body: SessionCreate) -> SessionSpec:
    """The spec of a session asked for over HTTP, its files resolved inside the media roots.

    Raises :class:`Forbidden` for a device not allowed or a path outside the roots (the same
    answer whether the path exists or not) and ``HTTPException(400)`` for a malformed URI.
    """
    from articast.service.sources import SOURCE_KINDS, parse_uri

    try:
        p = parse_uri(body.source)
    except ArticastError as exc:
        raise HTTPException(400, str(exc)) from None
    files = {"model": body.model, "appearance": body.appearance, "camera": body.camera,
             "speaker": body.speaker}
    for field_name, path in (("source", p.target), *files.items()):
        problem = path_name_problem(path)
        if problem:
            raise HTTPException(400, f"{field_name}: {problem}")
    access.check_session_files(p.kind, p.target, files)
    if p.kind in ("file", "images", "replay-record"):
        query = body.source.partition("?")[2]
        source = f"{p.kind}:{access.resolve(p.target)}" + (f"?{query}" if query else "")
    else:
        source = body.source
    assert p.kind in SOURCE_KINDS
    resolved = {k: access.resolve(v) if v else "" for k, v in files.items()}
    return SessionSpec(body.name, source, resolved["model"], resolved["appearance"],
                       resolved["camera"], body.processor, body.wait_for_subscriber,
                       speaker=resolved["speaker"], preview=body.preview,
                       media_roots=tuple(os.path.realpath(r) for r in access.media_roots))


class ConnectionDropped(Exception):
    """The connection was aborted: its receive loop ends."""


class Subscriber:
    """One subscription of one connection."""

    def __init__(self, conn: Connection, req: P.Subscribe, sub: Any) -> None:
        self.conn, self.req, self.sub = conn, req, sub
        self.view = (tuple(sorted(set(req.streams))), req.encoding)
        self.task: asyncio.Task[None] | None = None
        self.counted = False


class Connection:
    def __init__(self, ws: WebSocket, svc: Service) -> None:
        self.ws, self.svc = ws, svc
        self.subs: dict[str, Subscriber] = {}
        self.sending_since = 0.0
        self._send_lock = asyncio.Lock()
        self.closed = asyncio.Event()
        self.task: asyncio.Task[Any] | None = None
        rate = svc.config.hub.max_messages_per_s
        self._bucket = MessageBucket(rate, 2 * rate)
        self.key = client_key((ws.scope.get("client") or ("?",))[0])
        self._refused = 0
        self._last_refusal_error = 0.0

    async def send(self, data: str | bytes) -> None:
        msg = {"type": "websocket.send", "text": data} if isinstance(data, str) else \
            {"type": "websocket.send", "bytes": data}
        async with self._send_lock:
            self.sending_since = time.monotonic()
            try:
                await self.ws.send(msg)
            finally:
                self.sending_since = 0.0

    def abort(self) -> None:
        """Drop the connection now (a stalled peer cannot complete a closing handshake)."""
        abort = self.ws.scope.get("extensions", {}).get("articast.abort")
        if abort is not None:
            abort()  # the blocked send and receive then end with a disconnect
        elif self.task is not None:
            self.task.cancel()

    async def error(self, code: str, reason: str, session: str | None = None) -> None:
        """Answer a client message with an error. A client that does not read its answers
        (the write buffer stays full for ``close_timeout_s``) while it keeps sending is
        dropped: its receive loop would otherwise wait on it, holding the connection."""
        try:
            await asyncio.wait_for(self.send(error_text(code, reason, session)),
                                   self.svc.config.hub.close_timeout_s)
        except TimeoutError:
            log.info("dropping a connection from %s that does not read its answers", self.key)
            self.abort()
            raise ConnectionDropped from None

    async def run(self) -> None:
        limit = self.svc.config.hub.max_message_bytes
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                if not self._bucket.take(time.monotonic()):
                    if await self._over_rate():
                        return
                    continue
                text = msg.get("text")
                if text is None:
                    await self.error("binary_not_accepted",
                                     "clients send JSON text messages; binary is server->client")
                    continue
                if len(text) > limit or len(text.encode("utf-8", "replace")) > limit:
                    await self.error("too_large", f"message of {len(text)} characters exceeds "
                                     f"the limit of {limit} bytes")
                    continue
                try:
                    req = P.parse_client_message(text)
                except P.ProtocolError as exc:
                    await self.error(exc.code, exc.reason)
                    continue
                except RecursionError:
                    await self.error("bad_json", "JSON nested too deeply")
                    continue
                if isinstance(req, P.Subscribe):
                    await self.subscribe(req)
                else:
                    await self.unsubscribe(req.session)
        finally:
            for s in list(self.subs.values()):
                self._drop(s)
            self.closed.set()

    async def _over_rate(self) -> bool:
        """A message over the rate limit: dropped, said once a second; True = close now.

        A client far over the limit (ten seconds' worth refused in a row) is closed with
        1008: parsing even a refused message costs the server, and bystanders come first.
        """
        self._refused += 1
        limit = self.svc.config.hub.max_messages_per_s
        if self._refused > 10 * limit:
            log.info("closing a connection sending over %.0f messages/s", limit)
            try:
                # the WebSocket protocol drops it shortly after (close_timeout_s), without
                # parsing what it still sends: nothing more is read here
                await self.ws.close(1008, f"over {limit:g} messages per second")
            except Exception as exc:  # noqa: BLE001 - the peer may be gone already
                log.debug("closing an over-rate connection: %r", exc)
            return True
        t = time.monotonic()
        if t - self._last_refusal_error >= 1.0:
            self._last_refusal_error = t
            await self.error("rate_limited", f"over {limit:g} messages per second: "
                             "messages dropped")
        return False

    async def subscribe(self, req: P.Subscribe) -> None:
        self._refused = 0
        svc, name = self.svc, req.session
        limits = svc.config.hub
        if not svc.subscribe_bucket(self.key).take(time.monotonic()):
            await self.error("rate_limited", f"over {limits.max_subscribes_per_client_s:g} "
                             "subscribe requests per second from this address: refused", name)
            return
        session = svc.lookup(name)
        if session is None:
            await self.error("unknown_session", f"no session {name!r}; sessions: "
                             f"{svc.session_names()[:20]}", name)
            return
        bad = [s for s in req.streams if s in ("fap", "arkit")]
        if bad and session.description is not None and session.outputs is None:
            await self.error("unavailable_stream", f"session {name!r} does not produce "
                             f"{bad}: its model lacks the MPEG-4 feature points or units they need",
                             name)
            return
        if name in self.subs:
            self._drop(self.subs.pop(name))
        elif len(self.subs) >= svc.config.hub.max_subscriptions_per_connection:
            await self.error("too_many_subscriptions", "subscription limit per connection "
                             f"({svc.config.hub.max_subscriptions_per_connection}) reached", name)
            return
        held = svc.subscriptions_of(self.key)
        if name not in self.subs and held >= limits.max_subscriptions_per_client:
            await self.error("too_many_subscriptions", "subscription limit per client address "
                             f"({limits.max_subscriptions_per_client}) reached", name)
            return
        total = svc.subscriber_total()
        if total >= limits.max_subscribers:
            await self.error("too_many_subscriptions", "the server is at its subscriber limit "
                             f"({limits.max_subscribers})", name)
            return
        reserve = svc.reserve()
        if total >= limits.max_subscribers - reserve and held >= limits.reserved_per_client:
            # the last places are kept for addresses that hold few (issue 39: 16 addresses
            # filled the server and a newcomer was refused)
            await self.error("too_many_subscriptions", "the server is nearly full: its last "
                             f"{reserve} subscriptions are kept for addresses holding fewer "
                             f"than {limits.reserved_per_client}", name)
            return
        depth = min(req.queue, limits.max_queue_limit) if req.queue else limits.max_queue
        sub = svc.hub.subscribe(name, max_queue=depth, max_rate=req.rate)
        s = Subscriber(self, req, sub)
        self.subs[name] = s
        local = svc.manager.sessions.get(name)
        (local or session).subscriber_arrived()
        s.task = asyncio.create_task(self._pump(s), name=f"pump {name}")

    async def unsubscribe(self, name: str) -> None:
        s = self.subs.pop(name, None)
        if s is None:
            await self.error("not_subscribed", f"not subscribed to {name!r}", name)
            return
        self._drop(s)

    def _drop(self, s: Subscriber) -> None:
        self.svc.count_drops(s)
        s.sub.close()
        if s.task is not None and s.task is not asyncio.current_task():
            s.task.cancel()

    def _hello(self, s: Subscriber) -> str | None:
        session = self.svc.lookup(s.req.session)
        if session is None or session.description is None:
            return None
        streams = [x for x in s.req.streams if x != "mesh" or session.description["geometry"]]
        return self.svc.hello_text(s.req, session, streams)

    async def _pump(self, s: Subscriber) -> None:
        """Sends one subscription's messages; awaits only its queue and this socket."""
        name = s.req.session
        helloed = False
        said: tuple[int, int] | None = None  # (sid, description) of the last hello sent

        def described() -> tuple[int, int] | None:
            now_session = self.svc.lookup(name)
            if now_session is None or now_session.description is None:
                return None
            return now_session.sid, id(now_session.description)

        try:
            session = self.svc.lookup(name)
            if session is not None:
                text = self._hello(s)
                if text is not None:
                    await self.send(text)
                    helloed, said = True, described()
                else:
                    await self.send(status_text(StatusEvent(name, session.state,
                                                            session.detail, now())))
                if text is not None and session.state in ("ended", "failed"):
                    # a subscriber arriving after the end: say so (final for clients),
                    # instead of a hello followed by silence
                    await self.send(status_text(StatusEvent(name, session.state,
                                                            session.detail, now())))
            while True:
                ev = await s.sub.get()
                if isinstance(ev, FrameEvent):
                    if not helloed:
                        text = self._hello(s)
                        if text is None:
                            continue
                        await self.send(text)
                        helloed, said = True, described()
                    await self.send(ev.for_subscriber(s.view, s.sub.dropped))
                    session = self.svc.lookup(name)
                    if session is not None:
                        session.metrics.send_latency.observe(now() - ev.record.t_tracked)
                elif isinstance(ev, ReadyEvent):
                    if helloed and described() == said:
                        continue  # this run's hello was sent already
                    text = self._hello(s)
                    if text is not None:
                        await self.send(text)
                        helloed, said = True, described()
                elif isinstance(ev, StatusEvent):
                    await self.send(status_text(ev, s.sub.dropped))
                    if ev.state == "stopped":
                        break
        except (HubClosed, asyncio.CancelledError):
            pass
        except Exception as exc:  # noqa: BLE001 - a dead socket ends only this subscription
            log.debug("subscription %s ended: %r", name, exc)
        finally:
            if self.subs.get(name) is s:
                del self.subs[name]
                self.svc.count_drops(s)
                s.sub.close()


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
        self._buckets: dict[tuple[str, str], MessageBucket] = {}
        self._hellos: dict[tuple[Any, ...], tuple[Any, Any, str]] = {}
        self._watchdog: asyncio.Task[None] | None = None
        self.media: Any = None
        """The media process (:class:`articast.service.media.MediaProcess`): participants'
        WebRTC connections, started on the first offer."""

    def media_process(self) -> Any:
        if self.media is None:
            from articast.service.media import MediaProcess

            self.media = MediaProcess()
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

    def reserve(self) -> int:
        """Subscriptions kept for addresses holding fewer than ``reserved_per_client``: at
        most half the server's limit."""
        h = self.config.hub
        return max(0, min(h.reserved_subscribers, h.max_subscribers // 2))

    def subscribe_bucket(self, key: str) -> MessageBucket:
        """The subscribe-rate budget of one client address."""
        return self._bucket("subscribe", key, self.config.hub.max_subscribes_per_client_s)

    def handshake_bucket(self, key: str) -> MessageBucket:
        """The WebSocket-connection-rate budget of one client address."""
        return self._bucket("handshake", key, self.config.hub.max_handshakes_per_client_s)

    def _bucket(self, kind: str, key: str, rate: float) -> MessageBucket:
        """A rate budget of one client address, bursts of twice the rate (bounded: the
        least recently used addresses are forgotten first)."""
        bucket = self._buckets.pop((kind, key), None)
        if bucket is None:
            bucket = MessageBucket(rate, 2 * rate)
            if len(self._buckets) >= 65536:
                self._buckets.pop(next(iter(self._buckets)))
        self._buckets[(kind, key)] = bucket
        return bucket

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


def create_app(config: ServiceConfig | None = None,
               on_live: Callable[[dict[str, str]], None] | None = None) -> FastAPI:
    """The app. ``on_live(failed)`` is called once the initial sessions stream (see
    :meth:`Service._announce`)."""
    config = config or ServiceConfig()
    svc = Service(config, on_live)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await svc.start()
        try:
            yield
        finally:
            await svc.stop()

    app = FastAPI(title="articast", version=str(P.PROTOCOL_VERSION), lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    app.state.service = svc
    from articast.service.avatar import mount_avatar

    mount_avatar(app)
    if config.room is not None:
        from articast.service.room import mount_room

        mount_room(app, svc, config.room)

    app.add_middleware(BodyLimit, limit=config.hub.max_message_bytes,
                       timeout_s=config.hub.header_timeout_s)
    app.add_middleware(TokenGate, access=config.access,
                       attempts=FailedAttempts(free=config.hub.max_token_failures,
                                               max_s=config.hub.token_delay_max_s))
    app.add_middleware(Guard, access=config.access)

    @app.exception_handler(BodyTooLarge)
    async def too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 413, headers={"Connection": "close"})

    @app.exception_handler(BodyTimeout)
    async def too_slow(request: Request, exc: BodyTimeout) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 408, headers={"Connection": "close"})

    @app.exception_handler(Exception)
    async def internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("internal error on %s", request.url.path)
        return JSONResponse({"detail": "internal error (see the server log)"}, 500)

    access = config.access

    def authorise(request: Request) -> None:
        """Reading faces: the token when one is configured."""
        if not access.token_ok(request.headers.get("authorization"),
                               request.scope.get("query_string", b"")):
            raise HTTPException(401, "this server needs a token: Authorization: Bearer TOKEN "
                                "(or ?token=TOKEN)")

    def authorise_admin(request: Request) -> None:
        """Starting and stopping sessions: always the token."""
        if not access.token:
            raise HTTPException(403, "the session API needs a token: start the server with "
                                "ARTICAST_TOKEN or --token-file")
        authorise(request)

    @app.exception_handler(Forbidden)
    async def forbidden(request: Request, exc: Forbidden) -> JSONResponse:
        return JSONResponse({"detail": exc.reason}, exc.status)

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        key = client_key((websocket.scope.get("client") or ("?",))[0])
        if not svc.handshake_bucket(key).take(time.monotonic()):
            # each connection costs a handshake and, once subscribed, a hello (issue 39:
            # one address reconnecting in a loop slowed every bystander)
            rate = config.hub.max_handshakes_per_client_s
            await deny(websocket.scope, websocket.receive, websocket.send, 429,
                       f"over {rate:g} WebSocket connections per second from this address",
                       [(b"connection", b"close"), (b"retry-after", b"1")])
            return
        if not access.token_ok(websocket.headers.get("authorization"),
                               websocket.scope.get("query_string", b"")):
            await deny(websocket.scope, websocket.receive, websocket.send, 401,
                       "this server needs a token: Authorization: Bearer TOKEN or ?token=TOKEN")
            return
        await websocket.accept()
        conn = Connection(websocket, svc)
        conn.task = asyncio.current_task()
        svc.connections.add(conn)
        try:
            await conn.run()
        except asyncio.CancelledError:
            pass
        except Exception as exc:  # noqa: BLE001 - one broken connection, never the server
            log.debug("connection ended: %r", exc)
        finally:
            svc.connections.discard(conn)
            for s in list(conn.subs.values()):
                conn._drop(s)

    @app.get("/api/sessions")
    async def list_sessions(request: Request) -> list[dict[str, Any]]:
        authorise(request)
        return svc.session_dicts()

    @app.post("/api/sessions", status_code=201)
    async def create_session(body: SessionCreate, request: Request) -> dict[str, Any]:
        authorise_admin(request)
        if config.role == "gateway":
            raise HTTPException(409, "this is a gateway: sessions run in 'articast "
                                "track-worker' processes")
        if body.processor not in config.http_processors:
            raise HTTPException(400, f"processor {body.processor!r} is not allowed over HTTP "
                                f"(allowed: {list(config.http_processors)}; start the server "
                                "with --processor to allow another)")
        if len(svc.manager.sessions) >= config.policy.max_sessions:
            raise HTTPException(429, f"the server runs its maximum of "
                                f"{config.policy.max_sessions} sessions (--max-sessions)")
        spec = confined_spec(access, body)
        try:
            s = await svc.manager.add(spec)
        except KeyError:
            raise HTTPException(409, f"session {body.name!r} exists") from None
        except ArticastError as exc:
            raise HTTPException(400, str(exc)) from None
        except (OSError, ValueError) as exc:  # a file the checks above let through
            raise HTTPException(400, f"cannot start session {body.name!r}: "
                                f"{type(exc).__name__}: {getattr(exc, 'strerror', '') or exc}"
                                ) from None
        return s.to_dict()

    @app.delete("/api/sessions/{name}")
    async def delete_session(name: str, request: Request) -> dict[str, Any]:
        authorise_admin(request)
        if name not in svc.manager.sessions:
            raise HTTPException(404, f"no session {name!r}")
        await svc.manager.remove(name)
        return {"name": name, "state": "stopped"}

    @app.post("/api/sessions/{name}/recentre")
    async def recentre_session(name: str, request: Request) -> dict[str, Any]:
        """Take the session's next good frame as the speaker's neutral head pose."""
        authorise_admin(request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        session.recentre()
        return {"name": name, "recentred": True}

    @app.post("/api/sessions/{name}/webrtc")
    async def webrtc_offer(name: str, request: Request) -> dict[str, Any]:
        """A participant's browser joins as session NAME: ``{"type": "offer", "sdp": ...,
        "speaker"?: DIR}`` answered with ``{"type": "answer", "sdp": ..., "session": ...}``.
        Their camera becomes the session's source (:mod:`articast.service.webrtc`), tracked
        as the speaker (a folder under the media roots) or, without one, with the synthetic
        speaker's assets (``seed``, default 1) as ``demo`` does. A session of that name that
        ended (the participant left) is replaced; one still running is not (409)."""
        authorise_admin(request)  # a face enters the server: as starting any session
        if config.role == "gateway":
            raise HTTPException(409, "this is a gateway: sessions run in 'articast "
                                "track-worker' processes")
        from articast.service import webrtc
        from articast.service.session import NAME_RE, TERMINAL

        reason = webrtc.missing()
        if reason:
            raise HTTPException(501, reason)
        if not NAME_RE.match(name):
            raise HTTPException(400, f"session name {name!r}: 1-64 of letters, digits, _ . -")
        offer = await _offer(request, webrtc.MAX_SDP_CHARS)
        old = svc.manager.sessions.get(name)
        if old is not None and (old.state not in TERMINAL or name not in svc.manager.feeds):
            raise HTTPException(409, f"session {name!r} exists" + (
                " and has a participant" if name in svc.manager.feeds else ""))
        if old is None and len(svc.manager.sessions) >= config.policy.max_sessions:
            raise HTTPException(429, f"the server runs its maximum of "
                                f"{config.policy.max_sessions} sessions (--max-sessions)")
        speaker = offer["speaker"]
        if speaker:
            problem = path_name_problem(speaker)
            if problem:
                raise HTTPException(400, f"speaker: {problem}")
            access.check_session_files("webrtc", "", {"speaker": speaker})
            speaker = access.resolve(speaker)
        try:
            sdp, _, feed = await svc.media_process().answer(offer["sdp"], name)
        except ValueError as exc:
            raise HTTPException(400, str(exc)) from None
        if old is not None:
            await svc.manager.remove(name)
        source = f"webrtc:{name}" + ("" if speaker else f"?seed={offer['seed']}")
        spec = SessionSpec(name, source, speaker=speaker,
                           media_roots=tuple(os.path.realpath(r) for r in access.media_roots)
                           if speaker else ())
        svc.manager.feeds[name] = feed
        try:
            s = await svc.manager.add(spec)
        except (KeyError, ArticastError) as exc:
            svc.manager.feeds.pop(name, None)
            feed.close("the session could not start")
            raise HTTPException(409 if isinstance(exc, KeyError) else 400,
                                f"session {name!r} exists" if isinstance(exc, KeyError)
                                else str(exc)) from None
        return {"type": "answer", "sdp": sdp, "session": s.to_dict()}

    async def _offer(request: Request, limit: int) -> dict[str, Any]:
        """The join page's offer, checked; HTTPException(400) in one line otherwise."""

        try:
            body = json.loads(await request.body())
        except (ValueError, RecursionError):
            raise HTTPException(400, "the body is not JSON: send {\"type\": \"offer\", "
                                "\"sdp\": ...}") from None
        if not isinstance(body, dict):
            raise HTTPException(400, "the body must be a JSON object {\"type\": \"offer\", "
                                "\"sdp\": ...}")
        unknown = sorted(set(body) - {"type", "sdp", "speaker", "seed"})
        if unknown:
            raise HTTPException(400, f"unknown field(s) {unknown}: type, sdp, speaker, seed")
        if body.get("type") != "offer":
            raise HTTPException(400, f"type must be \"offer\", not {body.get('type')!r}")
        sdp = body.get("sdp")
        if not isinstance(sdp, str) or not sdp.startswith("v=0") or len(sdp) > limit:
            raise HTTPException(400, "sdp must be the offer's SDP text (starting v=0, at most "
                                f"{limit} characters)")
        speaker = body.get("speaker", "")
        if not isinstance(speaker, str):
            raise HTTPException(400, "speaker must be a folder name (a string)")
        seed = body.get("seed", 1)
        if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**31:
            raise HTTPException(400, "seed must be a whole number >= 0 (the synthetic "
                                "speaker whose assets track a participant without a speaker)")
        return {"sdp": sdp, "speaker": speaker, "seed": seed}

    @app.get("/api/sessions/{name}/preview.jpg")
    async def preview(name: str, request: Request) -> Response:
        """The newest tracking preview of a session that opted in (404 otherwise): a picture
        of a face, so the token is needed like for subscribing."""
        authorise(request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if not session.spec.preview:
            raise HTTPException(404, f"session {name!r} has no preview (off by default for "
                                "privacy: start it with --preview or \"preview\": true)")
        if session.preview is None:
            raise HTTPException(409, f"session {name!r} has no preview frame yet")
        seq, jpeg = session.preview
        return Response(jpeg, media_type="image/jpeg",
                        headers={"Cache-Control": "no-store", "X-Articast-Seq": str(seq)})

    @app.get("/api/sessions/{name}/dense")
    def dense_mesh(name: str, request: Request) -> Response:
        """The session's dense face mesh and dense modes (METHOD.md §5), built once per model
        (a fraction of a second, in the thread pool) and served as JSON:
        ``{n_points, mean (3M), basis (K*3M), triangles (3T), linearity_error_mm}``."""
        authorise(request)
        session = svc.lookup(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if session.description is None or not session.description.get("geometry"):
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        return Response(session.dense_json(), media_type="application/json")

    def delegate_session(name: str, request: Request) -> Any:
        """The session whose speaker's face a request asks for (their delegate or VRM): the
        token checked as for subscribing, 404 when there is none or the server serves none."""
        authorise(request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r} on this server")
        if not config.delegates:
            raise HTTPException(404, "this server serves no delegate (--no-delegate)")
        return session

    @app.get("/api/sessions/{name}/delegate")
    def delegate(name: str, request: Request) -> Response:
        """The speaker's delegate (:mod:`articast.service.delegate`): a picture of their face,
        so the token is needed like for subscribing; never cached, never logged."""
        session = delegate_session(name, request)
        if session.description is None:
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        try:
            body = session.delegate_json()
        except ArticastError as exc:
            raise HTTPException(404, str(exc)) from None
        return Response(body, media_type="application/json",
                        headers={"Cache-Control": "no-store"})

    @app.get("/api/sessions/{name}/vrm")
    def speaker_vrm(name: str, request: Request) -> Response:
        """The speaker's face as a VRM 1.0 avatar (service/vrm.py): token, no-store, as the
        delegate."""
        session = delegate_session(name, request)
        desc = session.description
        path = session.delegate_file() if desc is not None else None
        if desc is None or path is None:
            raise HTTPException(404, f"session {name!r} has no delegate to make a VRM of")
        from articast.service.vrm import vrm_bytes

        try:
            body = vrm_bytes(path, desc)
        except ArticastError as exc:
            raise HTTPException(404, str(exc)) from None
        return Response(body, media_type="model/gltf-binary",
                        headers={"Cache-Control": "no-store"})

    from articast.service.scan import ScanAsset

    scan = ScanAsset(config.server.scan) if config.server.scan else None

    @app.get("/api/sessions/{name}/scan")
    def scan_mesh(name: str, request: Request) -> Response:
        """The server's bound head scan (``--scan``) animated by this session's model: dense
        modes and the render mesh as JSON (service/scan.py); 404 without ``--scan``."""
        authorise(request)
        session = _scan_session(name)
        from articast.service.wire import model_from_description

        assert scan is not None
        try:
            body = scan.json_for(model_from_description(session.description))
        except InputError as exc:
            raise HTTPException(409, str(exc)) from None
        return Response(body, media_type="application/json")

    @app.get("/api/sessions/{name}/scan/texture")
    def scan_texture(name: str, request: Request) -> Response:
        """The scan's texture image: a picture of a face, so the token is needed."""
        authorise(request)
        _scan_session(name)
        assert scan is not None
        return Response(scan.texture.image, media_type=scan.texture.mime,
                        headers={"Cache-Control": "private, max-age=3600"})

    def _scan_session(name: str) -> Any:
        if scan is None:
            raise HTTPException(404, "this server shows no head scan (start it with --scan "
                                "BINDING)")
        session = svc.lookup(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if session.description is None or not session.description.get("geometry"):
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        return session

    @app.get("/api/protocol")
    async def protocol_schema() -> dict[str, Any]:
        return P.protocol_schema()

    @app.get("/healthz")
    async def healthz(request: Request) -> dict[str, Any]:
        out: dict[str, Any] = {"status": "ok", "protocol": P.PROTOCOL_VERSION}
        if access.token_ok(request.headers.get("authorization"),
                           request.scope.get("query_string", b"")):
            out["sessions"] = svc.states()
            out["connections"] = len(svc.connections)
        return out

    @app.get("/metrics", response_class=PlainTextResponse)
    async def metrics(request: Request) -> PlainTextResponse:
        authorise(request)
        return PlainTextResponse(svc.metrics_text(),
                                 media_type="text/plain; version=0.0.4; charset=utf-8")

    return app

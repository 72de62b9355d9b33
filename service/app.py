"""The FastAPI application: ``WS /ws`` and the HTTP API.

``WS /ws``                     subscribe to sessions (protocol v1, :mod:`articast.client.protocol`)
``GET /api/sessions``          the sessions and their state
``POST /api/sessions``         start one: ``{"name", "source", "model"?, "appearance"?,
                               "camera"?, "processor"?, "wait_for_subscriber"?, "preview"?}``
``DELETE /api/sessions/{name}`` stop one
``GET /api/protocol``          the JSON Schema of the protocol
``GET /healthz``               liveness and session states
``GET /metrics``               Prometheus text

Each WebSocket connection has one receive loop (client messages, every bad one answered by an
``error``) and one sender task per subscription, which awaits only its own hub queue and its
own socket: a stalled client stalls nobody else, and one stalled for longer than
``stall_timeout_s`` is disconnected by a watchdog.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi import FastAPI, HTTPException, Request, WebSocket
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from articast.client import protocol as P
from articast.core.errors import ArticastError
from articast.service.hub import HubClosed, InMemoryHub
from articast.service.metrics import render
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


@dataclass(frozen=True)
class ServiceConfig:
    server: ServerSettings = field(default_factory=ServerSettings)
    hub: HubSettings = field(default_factory=HubSettings)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    policy: SessionPolicy = field(default_factory=SessionPolicy)
    sessions: tuple[SessionSpec, ...] = ()
    api_token: str = ""
    """If set, POST and DELETE need ``Authorization: Bearer <token>``."""
    http_processors: tuple[str, ...] = ("auto", "truth", "tracker")
    """Processors a session added over HTTP may name: importing ``module:callable`` on a
    client's word would run the client's choice of code, so only these are accepted."""


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    source: str = Field(min_length=1, max_length=4096)
    model: str = ""
    appearance: str = ""
    camera: str = ""
    processor: str = "auto"
    wait_for_subscriber: bool = False
    preview: bool = False


class Subscriber:
    """One subscription of one connection."""

    def __init__(self, conn: Connection, req: P.Subscribe, sub: Any) -> None:
        self.conn, self.req, self.sub = conn, req, sub
        self.view = (tuple(sorted(req.streams)), req.encoding)
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
        await self.send(error_text(code, reason, session))

    async def run(self) -> None:
        limit = self.svc.config.hub.max_message_bytes
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
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
                if isinstance(req, P.Subscribe):
                    await self.subscribe(req)
                else:
                    await self.unsubscribe(req.session)
        finally:
            for s in list(self.subs.values()):
                self._drop(s)
            self.closed.set()

    async def subscribe(self, req: P.Subscribe) -> None:
        svc, name = self.svc, req.session
        session = svc.manager.sessions.get(name)
        if session is None:
            await self.error("unknown_session", f"no session {name!r}; sessions: "
                             f"{sorted(svc.manager.sessions)}", name)
            return
        bad = [s for s in req.streams if s in ("fap", "arkit")]
        if bad and session.description is not None and session.outputs is None:
            await self.error("unavailable_stream", f"session {name!r} does not produce "
                             f"{bad}: its model labels no MPEG-4 feature points", name)
            return
        if name in self.subs:
            self._drop(self.subs.pop(name))
        elif len(self.subs) >= svc.config.hub.max_subscriptions_per_connection:
            await self.error("too_many_subscriptions", "subscription limit per connection "
                             f"({svc.config.hub.max_subscriptions_per_connection}) reached", name)
            return
        if svc.subscriber_total() >= svc.config.hub.max_subscribers:
            await self.error("too_many_subscriptions", "the server is at its subscriber limit "
                             f"({svc.config.hub.max_subscribers})", name)
            return
        limits = svc.config.hub
        depth = min(req.queue, limits.max_queue_limit) if req.queue else limits.max_queue
        sub = svc.hub.subscribe(name, max_queue=depth, max_rate=req.rate)
        s = Subscriber(self, req, sub)
        self.subs[name] = s
        session.subscriber_arrived()
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
        session = self.svc.manager.sessions.get(s.req.session)
        if session is None or session.description is None:
            return None
        streams = [x for x in s.req.streams if x != "mesh" or session.description["geometry"]]
        return hello(session.spec.name, session.sid, session.description, session.source_info,
                     s.req, session.state, streams)

    async def _pump(self, s: Subscriber) -> None:
        """Sends one subscription's messages; awaits only its queue and this socket."""
        name = s.req.session
        helloed = False
        try:
            session = self.svc.manager.sessions.get(name)
            if session is not None:
                text = self._hello(s)
                if text is not None:
                    await self.send(text)
                    helloed = True
                else:
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
                        helloed = True
                    await self.send(ev.for_subscriber(s.view, s.sub.dropped))
                    session = self.svc.manager.sessions.get(name)
                    if session is not None:
                        session.metrics.send_latency.observe(now() - ev.record.t_tracked)
                elif isinstance(ev, ReadyEvent):
                    text = self._hello(s)
                    if text is not None:
                        await self.send(text)
                        helloed = True
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
                 on_live: Callable[[], None] | None = None) -> None:
        self.config = config
        self.on_live = on_live
        self._announce_task: asyncio.Task[None] | None = None
        self.hub: InMemoryHub[Any] = InMemoryHub()
        self.manager = SessionManager(self.hub, config.capture, config.policy,
                                      config.server.record)
        if config.server.vmc:
            from articast.service.vmc import VmcSender, parse_host_port

            self.manager.vmc = VmcSender(*parse_host_port(config.server.vmc),
                                         names=config.server.vmc_names)
        self.connections: set[Connection] = set()
        self._watchdog: asyncio.Task[None] | None = None

    def subscriber_total(self) -> int:
        return sum(len(c.subs) for c in self.connections)

    def count_drops(self, s: Subscriber) -> None:
        """Add an ending subscription's drops to its session's total (once)."""
        session = self.manager.sessions.get(s.req.session)
        if session is not None and not s.counted:
            session.metrics.subscriber_dropped += s.sub.dropped
        s.counted = True

    async def start(self) -> None:
        for spec in self.config.sessions:
            await self.manager.add(spec)
        self._watchdog = asyncio.create_task(self._watch(), name="stall watchdog")
        if self.on_live is not None:
            self._announce_task = asyncio.create_task(self._announce(), name="announce")

    async def _announce(self) -> None:
        """Call ``on_live`` once every initial session streams (its first frame is on the
        hub) or has said why it cannot (a session held for its first subscriber counts as
        ready): a URL printed then shows a moving face, not an empty page."""
        waits = [s.settled.wait() for s in self.manager.sessions.values()
                 if not s.spec.wait_for_subscriber]
        await asyncio.gather(*waits)
        assert self.on_live is not None
        self.on_live()

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

    async def stop(self) -> None:
        if self._watchdog:
            self._watchdog.cancel()
        if self._announce_task:
            self._announce_task.cancel()
        await self.manager.close(self.config.server.shutdown_timeout_s)
        self.hub.close()

    def metrics_text(self) -> str:
        subs: dict[str, int] = {}
        live_dropped: dict[str, int] = {}
        for c in self.connections:
            for name, sub in c.subs.items():
                subs[name] = subs.get(name, 0) + 1
                live_dropped[name] = live_dropped.get(name, 0) + sub.sub.dropped
        rows = {name: (sess.metrics, subs.get(name, 0), sess.up,
                       sess.metrics.subscriber_dropped + live_dropped.get(name, 0))
                for name, sess in self.manager.sessions.items()}
        return render(rows, len(self.connections))


class BodyTooLarge(Exception):
    pass


class BodyLimit:
    """ASGI middleware: HTTP bodies over ``limit`` bytes get 413, declared or chunked."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            await JSONResponse({"detail": f"request body over {self.limit} bytes or "
                                "malformed length"}, 413)(scope, receive, send)
            return
        seen = 0

        async def limited() -> Any:
            nonlocal seen
            msg = await receive()
            seen += len(msg.get("body", b""))
            if seen > self.limit:
                raise BodyTooLarge(f"request body over {self.limit} bytes")
            return msg

        await self.app(scope, limited, send)


def create_app(config: ServiceConfig | None = None,
               on_live: Callable[[], None] | None = None) -> FastAPI:
    """The app. ``on_live()`` is called once the initial sessions stream (see
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

    app.add_middleware(BodyLimit, limit=config.hub.max_message_bytes)

    @app.exception_handler(BodyTooLarge)
    async def too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 413)

    @app.exception_handler(Exception)
    async def internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("internal error on %s", request.url.path)
        return JSONResponse({"detail": "internal error (see the server log)"}, 500)

    def authorise(request: Request) -> None:
        if config.api_token and request.headers.get("authorization") != \
                f"Bearer {config.api_token}":
            raise HTTPException(401, "this server needs Authorization: Bearer <token>")

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
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
    async def list_sessions() -> list[dict[str, Any]]:
        return [s.to_dict() for s in svc.manager.sessions.values()]

    @app.post("/api/sessions", status_code=201)
    async def create_session(body: SessionCreate, request: Request) -> dict[str, Any]:
        authorise(request)
        if body.processor not in config.http_processors:
            raise HTTPException(400, f"processor {body.processor!r} is not allowed over HTTP "
                                f"(allowed: {list(config.http_processors)}; start the server "
                                "with --processor to allow another)")
        spec = SessionSpec(body.name, body.source, body.model, body.appearance, body.camera,
                           body.processor, body.wait_for_subscriber, preview=body.preview)
        try:
            s = await svc.manager.add(spec)
        except KeyError:
            raise HTTPException(409, f"session {body.name!r} exists") from None
        except ArticastError as exc:
            raise HTTPException(400, str(exc)) from None
        return s.to_dict()

    @app.delete("/api/sessions/{name}")
    async def delete_session(name: str, request: Request) -> dict[str, Any]:
        authorise(request)
        if name not in svc.manager.sessions:
            raise HTTPException(404, f"no session {name!r}")
        await svc.manager.remove(name)
        return {"name": name, "state": "stopped"}

    @app.post("/api/sessions/{name}/recentre")
    async def recentre_session(name: str, request: Request) -> dict[str, Any]:
        """Take the session's next good frame as the speaker's neutral head pose."""
        authorise(request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        session.recentre()
        return {"name": name, "recentred": True}

    @app.get("/api/sessions/{name}/preview.jpg")
    async def preview(name: str) -> Response:
        """The newest tracking preview of a session that opted in (404 otherwise)."""
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
    def dense_mesh(name: str) -> Response:
        """The session's dense face mesh and dense modes (METHOD.md §5), built once per model
        (a fraction of a second, in the thread pool) and served as JSON:
        ``{n_points, mean (3M), basis (K*3M), triangles (3T), linearity_error_mm}``."""
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if session.description is None or not session.description.get("geometry"):
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        return Response(session.dense_json(), media_type="application/json")

    @app.get("/api/protocol")
    async def protocol_schema() -> dict[str, Any]:
        return P.protocol_schema()

    @app.get("/healthz")
    async def healthz() -> dict[str, Any]:
        return {"status": "ok", "protocol": P.PROTOCOL_VERSION,
                "sessions": {n: s.state for n, s in svc.manager.sessions.items()},
                "connections": len(svc.connections)}

    @app.get("/metrics", response_class=PlainTextResponse)
    async def metrics() -> PlainTextResponse:
        return PlainTextResponse(svc.metrics_text(),
                                 media_type="text/plain; version=0.0.4; charset=utf-8")

    return app

"""The WebSocket subscribe protocol (``WS /ws``, protocol v1: :mod:`articast.client.protocol`).

Each connection has one receive loop (:meth:`Connection.run`: client messages, every bad one
answered by an ``error``) and one sender task per subscription (:meth:`Connection._pump`),
which awaits only its own hub queue and its own socket: a stalled client stalls nobody else,
and one stalled for longer than ``stall_timeout_s`` is disconnected by the service's watchdog.
What a subscription may be admitted to is :mod:`articast.service.admission`'s to say.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Any

from fastapi import WebSocket

from articast.client import protocol as P
from articast.service.admission import subscription_refusal
from articast.service.hub import HubClosed
from articast.service.middleware import MessageBucket, deny
from articast.service.security import client_key
from articast.service.wire import (
    FrameEvent,
    ReadyEvent,
    StatusEvent,
    error_text,
    now,
    status_text,
)

if TYPE_CHECKING:  # the service that holds the connections (service/state.py)
    from articast.service.state import Service

log = logging.getLogger("articast.app")


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
        self._last_refusal = self._last_refusal_error = 0.0

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
                # one message per turn of the event loop: a read that waits in the socket's
                # queue is taken without a pause (asyncio.Queue.get does not yield when it
                # has one), so a flooding connection would otherwise handle its whole
                # backlog at once; 32 of them starting together held the loop ~300 ms and
                # /healthz waited behind them (issue 39)
                await asyncio.sleep(0)
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

        A client far over the limit (ten seconds' worth refused, with no quiet second
        between two refusals) is closed with 1008: parsing even a refused message costs the
        server, and bystanders come first. A message let through by the bucket meanwhile does
        not clear the count: a flood is let through at the limit's rate, and with one message
        per turn of the loop it would otherwise never be closed.
        """
        t = time.monotonic()
        if t - self._last_refusal > 1.0:
            self._refused = 0
        self._last_refusal = t
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
        if t - self._last_refusal_error >= 1.0:
            self._last_refusal_error = t
            await self.error("rate_limited", f"over {limit:g} messages per second: "
                             "messages dropped")
        return False

    async def subscribe(self, req: P.Subscribe) -> None:
        svc, name = self.svc, req.session
        limits = svc.config.hub
        if not svc.budgets.subscribe(self.key).take(time.monotonic()):
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
        if name in self.subs:  # a new subscription to the same session replaces the old
            self._drop(self.subs.pop(name))
        refusal = subscription_refusal(limits, on_connection=len(self.subs),
                                       by_address=svc.subscriptions_of(self.key),
                                       total=svc.subscriber_total())
        if refusal:
            await self.error("too_many_subscriptions", refusal, name)
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


async def serve_connection(svc: Service, websocket: WebSocket) -> None:
    """``WS /ws``: admit the handshake (its address's rate, the token), then run the
    connection's receive loop until it ends."""
    config, access = svc.config, svc.config.access
    key = client_key((websocket.scope.get("client") or ("?",))[0])
    if not svc.budgets.handshake(key).take(time.monotonic()):
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


"""Running the app under uvicorn, with a clean shutdown.

SIGTERM or Ctrl-C: uvicorn stops accepting, closes the WebSocket connections, waits up to
``shutdown_timeout_s`` for them, then the app's lifespan stops every session (workers are told
to stop, joined with a timeout, processes terminated if they do not).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
from collections.abc import Callable
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from articast.service.app import ServiceConfig, create_app
from articast.service.security import client_key, install_log_redaction

ABORT_EXTENSION = "articast.abort"
"""ASGI scope extension: a callable that aborts the connection's transport at once."""
log = logging.getLogger("articast.server")


class ClientConnections:
    """Open TCP connections per client address (both protocols of one connection count once)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.by_address: dict[str, int] = {}
        self._open: dict[int, str] = {}

    def admit(self, transport: Any) -> bool:
        key = id(transport)
        if key in self._open:
            return True
        peer = transport.get_extra_info("peername")
        address = client_key(str(peer[0])) if peer else "?"
        if self.by_address.get(address, 0) >= self.limit:
            return False
        self.by_address[address] = self.by_address.get(address, 0) + 1
        self._open[key] = address
        return True

    def release(self, transport: Any) -> None:
        address = self._open.pop(id(transport), None)
        if address is not None:
            n = self.by_address[address] - 1
            if n:
                self.by_address[address] = n
            else:
                del self.by_address[address]


def _refuse(transport: Any, status: bytes, text: str) -> None:
    body = text.encode()
    transport.write(b"HTTP/1.1 " + status + b"\r\ncontent-type: text/plain; charset=utf-8\r\n"
                    b"content-length: " + str(len(body)).encode() + b"\r\n"
                    b"connection: close\r\n\r\n" + body)
    transport.close()


def http_protocol(clients: ClientConnections, max_header_bytes: int,
                  header_timeout_s: float, receive_buffer_bytes: int = 0
                  ) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol with the limits uvicorn lacks.

    * connections per client address (``clients``): over it, 503 and close;
    * the request head (request line + headers) is at most ``max_header_bytes``: 431;
    * the head must be complete ``header_timeout_s`` after its first byte (or after the
      connection opened): else the connection is closed. Slowloris (many connections that
      send a header line now and then) otherwise holds file descriptors for ever;
    * the kernel's receive buffer of every connection (HTTP and, after the upgrade,
      WebSocket) is ``receive_buffer_bytes`` (0: the system's, which grows to megabytes):
      what a client sends faster than the server reads waits in the client's own buffers,
      not the server's (issue 39: 32 flooding connections held ~56 MB here).
    """

    class ArticastHttpProtocol(HttpToolsProtocol):
        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            sock = transport.get_extra_info("socket")
            if receive_buffer_bytes and sock is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer_bytes)
            self._head_bytes = 0
            self._head_tail = b""
            self._in_head = True
            self._head_timer: Any = None
            if not clients.admit(transport):
                log.info("refusing a connection from %s: over %d connections",
                         self.client, clients.limit)
                _refuse(transport, b"503 Service Unavailable",
                        "too many connections from this address")
                return
            self._arm_head_timer()

        def _arm_head_timer(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
            self._head_timer = self.loop.call_later(header_timeout_s, self._head_timeout)

        def _head_timeout(self) -> None:
            self._head_timer = None
            if self._in_head and not self.transport.is_closing():
                _refuse(self.transport, b"408 Request Timeout", "request head too slow")

        def connection_lost(self, exc: Exception | None) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
            clients.release(self.transport)
            super().connection_lost(exc)

        def data_received(self, data: bytes) -> None:
            if self._in_head:
                # only the head counts: a body's first bytes often come in the same read
                # (a large upload's: the room's enrolment clips)
                seen = getattr(self, "_head_tail", b"") + data
                end = seen.find(b"\r\n\r\n")
                self._head_tail = seen[-3:]
                self._head_bytes += len(data) if end < 0 else \
                    max(0, end + 4 - (len(seen) - len(data)))
                if self._head_bytes > max_header_bytes:
                    self._in_head = False
                    _refuse(self.transport, b"431 Request Header Fields Too Large",
                            f"request head over {max_header_bytes} bytes")
                    return
            super().data_received(data)

        def on_message_begin(self) -> None:
            super().on_message_begin()
            if not self._in_head:  # a next request on a kept-alive connection
                self._in_head, self._head_bytes, self._head_tail = True, 0, b""
                self._arm_head_timer()

        def on_headers_complete(self) -> None:
            self._in_head = False
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None
            super().on_headers_complete()

    return ArticastHttpProtocol


def websocket_protocol(socket_buffer_bytes: int, clients: ClientConnections | None = None,
                       close_timeout_s: float = 2.0, drain_bytes: int = 65536,
                       max_queue: int = 16, feed_bytes: int = 4096
                       ) -> type[WebSocketsSansIOProtocol]:
    """uvicorn's sans-I/O WebSocket protocol with bounded buffers and an abort handle.

    Newest-wins only bounds a slow client's lag if little can pile up *after* the hub queue:
    the transport's write buffer and the kernel's send buffer are capped at
    ``socket_buffer_bytes``, so a client that reads too slowly blocks its own sender (and
    then loses frames in its hub queue) instead of receiving stale frames seconds late.
    ``scope["extensions"]["articast.abort"]`` lets the stall watchdog drop a client that stopped
    reading without waiting for a closing handshake it can never complete. An upgrade request
    the WebSocket parser refuses (too many headers) is answered with 400 and closed (uvicorn
    leaves it unanswered).

    Once the app has closed a connection (or returned), the connection is dropped
    promptly (issue 39: a subscribe flood closed with 1008 went on being read and parsed,
    megabytes per connection, and stalled every other client): what the peer sends after our
    close frame is parsed only up to ``drain_bytes`` (enough to see an honest client's close
    reply), then no longer read at all, and the transport is aborted ``close_timeout_s``
    after the close whether or not the peer answered (uvicorn waits 10 s, reading and
    parsing all along, then only closes: a peer that does not read keeps it for ever).

    The bytes read are parsed ``feed_bytes`` at a time, and only while fewer than
    ``max_queue`` messages wait for the app: uvicorn parses all it reads at once (a 128 kB
    read of tiny frames is ~2,000 messages queued, and parsed, before the app has looked at
    the first and decided to close the connection); the rest waits, unparsed, reading paused.
    """

    class ArticastWebSocketProtocol(WebSocketsSansIOProtocol):
        _after_close: int | None = None
        _drop_timer: Any = None
        _backlog = b""
        _offset = 0

        def connection_lost(self, exc: Exception | None) -> None:
            if clients is not None:
                clients.release(self.transport)
            if self._drop_timer is not None:
                self._drop_timer.cancel()
            super().connection_lost(exc)

        def data_received(self, data: bytes) -> None:
            if self._after_close is not None:
                self._after_close += len(data)
                if self._after_close > drain_bytes:
                    # a peer still sending after our close: not read, not parsed; the
                    # drop timer aborts the connection
                    self.read_paused = False  # uvicorn's receive() must not resume it
                    self.transport.pause_reading()
                    return
            if self.handshake_complete and not self.close_sent:
                self._backlog = self._backlog[self._offset:] + data
                self._offset = 0
                self._feed()
                return
            super().data_received(data)
            if (not self.handshake_initiated and self.conn.handshake_exc is not None
                    and not self.transport.is_closing()):
                self.handshake_complete = self.close_sent = True
                _refuse(self.transport, b"400 Bad Request", "malformed WebSocket upgrade "
                        "request (too many headers, or a header line over the limit)")

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            transport.set_write_buffer_limits(high=socket_buffer_bytes)
            sock = transport.get_extra_info("socket")
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, socket_buffer_bytes)

        def _feed(self) -> None:
            """Parse backlog while the app keeps up; reading stays paused while some is left."""
            view = memoryview(self._backlog)
            while (self._offset < len(view) and self.queue.qsize() < max_queue
                   and not self.close_sent):
                chunk = bytes(view[self._offset:self._offset + feed_bytes])
                self._offset += len(chunk)
                WebSocketsSansIOProtocol.data_received(self, chunk)
            view.release()
            if self.close_sent or self._offset >= len(self._backlog):
                self._backlog, self._offset = b"", 0
            elif not self.read_paused:
                self.read_paused = True
                self.transport.pause_reading()

        async def receive(self) -> Any:
            message = await self.queue.get()
            if self._backlog:
                self._feed()
            if self.read_paused and self.queue.empty() and not self._backlog:
                self.read_paused = False
                self.transport.resume_reading()
            return message

        def _drop_soon(self) -> None:
            """Abort the transport ``close_timeout_s`` from now (once)."""
            if self._after_close is None:
                self._after_close = 0
            self._backlog, self._offset = b"", 0
            if self.disconnected or self._drop_timer is not None:
                return
            if self.close_timer is not None:
                # uvicorn's timer closes (not aborts) after 10 s; ours stands in for it (so
                # that uvicorn still waits for the peer's close reply, then closes at once)
                self.close_timer.cancel()
                self.close_timer = self._drop_timer = self.loop.call_later(
                    close_timeout_s, self._drop)
            else:
                self._drop_timer = self.loop.call_later(close_timeout_s, self._drop)

        def _drop(self) -> None:
            self._drop_timer = None
            if not self.disconnected:
                self.transport.abort()

        async def send(self, message: Any) -> None:
            if (message["type"] == "websocket.close" and self.handshake_complete
                    and not self.close_sent and not self.writable.is_set()):
                # a peer that does not read cannot get a close frame: dropped, not waited
                # for (uvicorn waits for the write buffer to drain: for ever)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self.writable.wait(), close_timeout_s)
                if not self.writable.is_set():
                    self.transport.abort()
                    return
            await super().send(message)
            if (message["type"] == "websocket.http.response.body"
                    and not message.get("more_body", False)):
                # the refusal (401/403) is a complete answer: uvicorn would otherwise log
                # "ASGI callable returned without completing handshake" and try a 500
                self.handshake_complete = True
            elif message["type"] == "websocket.close" and self.close_sent:
                self._drop_soon()

        async def run_asgi(self) -> None:
            await super().run_asgi()
            # the app is done: uvicorn closed the transport, which still waits for its
            # write buffer to drain (a peer that does not read: for ever)
            self._drop_soon()

        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            scope = getattr(self, "scope", None)
            if scope is not None:
                scope.setdefault("extensions", {})[ABORT_EXTENSION] = self.transport.abort

    return ArticastWebSocketProtocol


def uvicorn_config(config: ServiceConfig,
                   on_live: Callable[[dict[str, str]], None] | None = None) -> uvicorn.Config:
    s, h = config.server, config.hub
    install_log_redaction(config.access.token)
    clients = ClientConnections(h.max_connections_per_client)
    # the WebSocket upgrade's parser (websockets) allows 8 kB per header line, less than the
    # head limit every other request has (issue 39: a 15 kB line was refused under the 16 kB
    # limit): one limit for both, the request head's
    import websockets.http11

    websockets.http11.MAX_LINE_LENGTH = max(8192, h.max_header_bytes)
    return uvicorn.Config(
        create_app(config, on_live), host=s.host, port=s.port, log_level=s.log_level,
        http=http_protocol(clients, h.max_header_bytes, h.header_timeout_s,
                           h.receive_buffer_bytes),
        ws=websocket_protocol(h.socket_buffer_bytes, clients, h.close_timeout_s),
        ws_max_size=config.hub.ws_max_size,
        # no permessage-deflate: it compresses every message once per connection, which
        # would undo encode-once fan-out (frames are small; loopback and LANs do not need it)
        ws_per_message_deflate=False,
        ws_ping_interval=20.0, ws_ping_timeout=20.0,
        timeout_graceful_shutdown=max(1, math.ceil(s.shutdown_timeout_s)), lifespan="on",
        access_log=False, server_header=False,
    )


def bound_socket(host: str, port: int) -> socket.socket:
    """A listening socket (port 0: any free port), so the URL is known before serving."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def raise_file_limit() -> None:
    """Soft open-file limit up to the hard one: each connection is a descriptor."""
    with contextlib.suppress(ImportError, ValueError, OSError):
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if hard == resource.RLIM_INFINITY or hard > 65536:
            hard = 65536
        if soft < hard:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def serve(config: ServiceConfig,
          on_listening: Callable[[str, dict[str, str]], None] | None = None) -> None:
    """Serve until SIGTERM/SIGINT. ``on_listening(ws_url, failed)`` is called once the port is
    bound and the initial sessions stream (their first frame is out, or they said why not),
    so a URL printed then never shows an empty page; ``failed`` names the sessions that
    failed already (their reason was logged). When every initial session failed there is
    nothing to serve: no URL, and one error (InputError) once the server has stopped."""
    raise_file_limit()
    try:
        sock = bound_socket(config.server.host, config.server.port)
    except OSError as exc:
        from articast.core.errors import InputError

        raise InputError(f"cannot listen on {config.server.host}:{config.server.port}: "
                         f"{exc.strerror or exc}") from None
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    url = f"ws://{shown}:{port}/ws"
    nothing: list[str] = []

    def live(failed: dict[str, str]) -> None:
        if config.sessions and len(failed) == len(config.sessions):
            nothing.extend(failed)
            server.should_exit = True
        elif on_listening is not None:
            on_listening(url, failed)

    server = uvicorn.Server(uvicorn_config(config, live))
    server.run(sockets=[sock])
    if nothing:
        from articast.core.errors import InputError

        raise InputError(f"nothing to serve: {', '.join(nothing)} failed (the reason is above)")

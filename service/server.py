"""Running the app under uvicorn, with a clean shutdown.

SIGTERM or Ctrl-C: uvicorn stops accepting, closes the WebSocket connections, waits up to
``shutdown_timeout_s`` for them, then the app's lifespan stops every session (workers are told
to stop, joined with a timeout, processes terminated if they do not).
"""

from __future__ import annotations

import contextlib
import math
import socket
from collections.abc import Callable
from typing import Any

import uvicorn
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from articast.service.app import ServiceConfig, create_app

ABORT_EXTENSION = "articast.abort"
"""ASGI scope extension: a callable that aborts the connection's transport at once."""


def websocket_protocol(socket_buffer_bytes: int) -> type[WebSocketsSansIOProtocol]:
    """uvicorn's sans-I/O WebSocket protocol with bounded buffers and an abort handle.

    Newest-wins only bounds a slow client's lag if little can pile up *after* the hub queue:
    the transport's write buffer and the kernel's send buffer are capped at
    ``socket_buffer_bytes``, so a client that reads too slowly blocks its own sender (and
    then loses frames in its hub queue) instead of receiving stale frames seconds late.
    ``scope["extensions"]["articast.abort"]`` lets the stall watchdog drop a client that stopped
    reading without waiting for a closing handshake it can never complete.
    """

    class ArticastWebSocketProtocol(WebSocketsSansIOProtocol):
        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            transport.set_write_buffer_limits(high=socket_buffer_bytes)
            sock = transport.get_extra_info("socket")
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, socket_buffer_bytes)

        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            scope = getattr(self, "scope", None)
            if scope is not None:
                scope.setdefault("extensions", {})[ABORT_EXTENSION] = self.transport.abort

    return ArticastWebSocketProtocol


def uvicorn_config(config: ServiceConfig,
                   on_live: Callable[[], None] | None = None) -> uvicorn.Config:
    s = config.server
    return uvicorn.Config(
        create_app(config, on_live), host=s.host, port=s.port, log_level=s.log_level,
        ws=websocket_protocol(config.hub.socket_buffer_bytes),
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


def serve(config: ServiceConfig, on_listening: Callable[[str], None] | None = None) -> None:
    """Serve until SIGTERM/SIGINT. ``on_listening(ws_url)`` is called once the port is bound
    and the initial sessions stream (their first frame is out, or they said why not), so a
    URL printed then never shows an empty page."""
    sock = bound_socket(config.server.host, config.server.port)
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    url = f"ws://{shown}:{port}/ws"
    live = None if on_listening is None else (lambda: on_listening(url))
    server = uvicorn.Server(uvicorn_config(config, live))
    server.run(sockets=[sock])

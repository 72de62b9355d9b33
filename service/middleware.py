"""ASGI guards in front of the app, and the per-connection message budget.

* :class:`Guard` refuses a foreign ``Host`` (DNS rebinding) or browser ``Origin`` with 403,
  before a WebSocket handshake too (:func:`deny`);
* :class:`BodyLimit` answers 413 to HTTP bodies over the limit, declared or chunked;
* :class:`MessageBucket` is the token bucket of ``--max-messages-per-s``.
"""

from __future__ import annotations

import math
import time
from typing import Any

from fastapi.responses import JSONResponse

from articast.service.security import AccessPolicy


class MessageBucket:
    """Token bucket: ``rate`` messages per second on average, bursts up to ``burst``."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, max(1.0, burst)
        self.tokens, self.t = self.burst, time.monotonic()

    def take(self, t: float) -> bool:
        if not math.isfinite(self.rate) or self.rate <= 0:
            return True
        self.tokens = min(self.burst, self.tokens + (t - self.t) * self.rate)
        self.t = t
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


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


class Guard:
    """ASGI middleware: refuse a foreign ``Host`` (DNS rebinding) or ``Origin`` with 403.

    WebSocket upgrades are refused before the handshake with an HTTP answer (the denial
    response extension), so a browser page learns nothing but the refusal.
    """

    def __init__(self, app: Any, access: AccessPolicy) -> None:
        self.app, self.access = app, access

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        host, origin = headers.get("host"), headers.get("origin")
        reason = ""
        if not self.access.host_ok(host):
            reason = ("this server does not answer to that Host name (DNS rebinding guard; "
                      "its operator can allow it with --allowed-host)")
        elif not self.access.origin_ok(origin, host):
            reason = "requests from this Origin are not allowed (--allowed-origin)"
        if reason:
            await deny(scope, receive, send, 403, reason)
            return
        await self.app(scope, receive, send)


async def deny(scope: Any, receive: Any, send: Any, status: int, reason: str) -> None:
    """An HTTP refusal, also before a WebSocket handshake (else close 1008 after it)."""
    response = JSONResponse({"detail": reason}, status)
    if scope["type"] == "http" or "websocket.http.response" in scope.get("extensions", {}):
        await response(scope, receive, send)
        return
    await send({"type": "websocket.accept"})
    await send({"type": "websocket.close", "code": 1008, "reason": reason[:120]})

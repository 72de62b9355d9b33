"""ASGI guards in front of the app, and the per-connection message budget.

* :class:`Guard` refuses a foreign ``Host`` (DNS rebinding) or browser ``Origin`` with 403,
  before a WebSocket handshake too (:func:`deny`);
* :class:`TokenGate` checks the token before anything else reads the request (so a POST
  without the token never has its body read or parsed: no schema in a 422), backs off an
  address that keeps sending wrong tokens (429), and logs each refusal once, as a refusal;
* :class:`BodyLimit` answers 413 to HTTP bodies over the limit, declared or chunked, and 408
  to a body that does not arrive within the time limit (slow bodies hold no connection);
* :class:`MessageBucket` is the token bucket of ``--max-messages-per-s``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any, NoReturn

from fastapi.responses import JSONResponse

from articast.service.security import AccessPolicy, FailedAttempts, client_key

log = logging.getLogger("articast.access")
OPEN_PATHS = ("/healthz", "/api/protocol", "/avatar", "/room")
"""Routes that answer without the token (``/healthz`` says more with it); ``/room``'s check
the room's own tokens (service/room.py)."""
CLOSE = [(b"connection", b"close")]


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


class BodyTimeout(Exception):
    pass


class BodyLimit:
    """ASGI middleware: HTTP bodies over ``limit`` bytes get 413, declared or chunked; a
    body still incomplete ``timeout_s`` after the app first asked for it gets 408.
    ``uploads``: ``(method, path prefix, limit, timeout_s)`` of the routes that take larger
    bodies (the room's enrolment clips), with their own bounds."""

    def __init__(self, app: Any, limit: int, timeout_s: float = 10.0,
                 uploads: tuple[tuple[str, str, int, float], ...] = ()) -> None:
        self.app, self.limit, self.timeout_s = app, limit, timeout_s
        self.uploads = uploads

    def bounds(self, scope: Any) -> tuple[int, float]:
        for method, prefix, limit, timeout_s in self.uploads:
            if scope.get("method") == method and scope.get("path", "").startswith(prefix):
                return limit, timeout_s
        return self.limit, self.timeout_s

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, timeout_s = self.bounds(scope)
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > limit):
            await JSONResponse({"detail": f"request body over {limit} bytes or "
                                "malformed length"}, 413)(scope, receive, send)
            return
        seen = 0
        deadline = 0.0
        started = answered = complete = False

        async def answer(status: int, reason: str, exc: Exception) -> NoReturn:
            # answered here: the framework turns an error while it reads the body into a
            # 400 of its own, which ``guarded`` then swallows
            nonlocal answered
            if not started and not answered:
                answered = True
                await JSONResponse({"detail": reason}, status,
                                   headers={"Connection": "close"})(scope, receive, send)
            raise exc

        async def guarded(msg: Any) -> None:
            nonlocal started
            if answered:
                return
            started = started or msg["type"] == "http.response.start"
            await send(msg)

        async def limited() -> Any:
            nonlocal seen, deadline, complete
            if complete:  # after the body: a disconnect, whenever it comes
                return await receive()
            t = time.monotonic()
            deadline = deadline or t + timeout_s
            try:
                msg = await asyncio.wait_for(receive(), max(0.0, deadline - t))
            except TimeoutError:
                reason = f"request body not complete within {timeout_s:g} s"
                await answer(408, reason, BodyTimeout(reason))
            seen += len(msg.get("body", b""))
            if seen > limit:
                reason = f"request body over {limit} bytes"
                await answer(413, reason, BodyTooLarge(reason))
            complete = msg["type"] != "http.request" or not msg.get("more_body", False)
            return msg

        await self.app(scope, limited, guarded)


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


async def deny(scope: Any, receive: Any, send: Any, status: int, reason: str,
               headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """An HTTP refusal, also before a WebSocket handshake (else close 1008 after it)."""
    response = JSONResponse({"detail": reason}, status)
    response.raw_headers.extend(headers or [])
    if scope["type"] == "http" or "websocket.http.response" in scope.get("extensions", {}):
        await response(scope, receive, send)
        return
    await send({"type": "websocket.accept"})
    await send({"type": "websocket.close", "code": 1008, "reason": reason[:120]})


class TokenGate:
    """ASGI middleware: the token first, before any route reads the request.

    * no token configured: everything passes but the session API (POST/DELETE under
      ``/api/``), which answers 403 with the way to enable it;
    * a token configured: every route but ``OPEN_PATHS`` needs it (401);
    * the right token always passes; past ``FailedAttempts.free`` wrong tokens from an
      address, each further wrong one is answered 429 after a growing delay, one at a time
      (guessing slowed to one answer a minute); the right token from the same address (a
      NAT) and every other address are unaffected.

    Refusals close the connection (an unread body is never read) and are logged at info:
    the first of a series per address, and when a lock-out starts.
    """

    def __init__(self, app: Any, access: AccessPolicy,
                 attempts: FailedAttempts | None = None) -> None:
        self.app, self.access = app, access
        self.attempts = attempts or FailedAttempts()

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        admin = kind == "http" and scope.get("method") not in ("GET", "HEAD", "OPTIONS") \
            and path.startswith("/api/")
        if admin and not self.access.token:
            await deny(scope, receive, send, 403, "the session API needs a token: start the "
                       "server with ARTICAST_TOKEN or --token-file", CLOSE)
            return
        headers = dict(scope.get("headers") or ())
        authorization = headers.get(b"authorization", b"").decode("latin-1")
        offered = bool(authorization) or b"token=" in scope.get("query_string", b"")
        open_path = not admin and path.startswith(OPEN_PATHS)
        if not self.access.token or (open_path and not offered):
            await self.app(scope, receive, send)
            return
        key = client_key((scope.get("client") or ("?",))[0])
        if self.access.token_ok(authorization, scope.get("query_string", b"")):
            # the right token is never held, whatever else this address sends
            await self.app(scope, receive, send)
            return
        wait = 0.0
        if offered:
            # a wrong guess counts, on open routes too (/healthz says less without the
            # token: an oracle otherwise); no token at all is no guess. Past the free
            # ones, its answer waits its turn and its delay: guessing gets one answer per
            # delay per address, and nobody else waits for it
            async with self.attempts.turn(key):
                wait = self.attempts.failed(key, time.monotonic())
                if wait:
                    await asyncio.sleep(wait)
        what = "WebSocket connection" if kind == "websocket" else f"{scope.get('method')} {path}"
        if wait:
            if wait == self.attempts.initial_s:  # the first held: said once
                log.info("refused a %s from %s: wrong tokens again; answering each after "
                         "%.0f s", what, key, wait)
            await deny(scope, receive, send, 429, "too many wrong tokens from this address: "
                       f"each is answered after {wait:g} s", CLOSE)
            return
        if open_path:
            await self.app(scope, receive, send)
            return
        log.info("refused a %s from %s: %s token (401)", what, key,
                 "wrong" if offered else "no")
        await deny(scope, receive, send, 401, "this server needs a token: Authorization: "
                   "Bearer TOKEN (or ?token=TOKEN)", CLOSE)

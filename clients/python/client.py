"""An async subscriber with automatic reconnection, and a synchronous iterator over it.

::

    async with Client("ws://127.0.0.1:8765/ws", "demo") as client:
        async for frame in client.frames():
            print(frame.seq, frame.values.articulatory)

A lost connection (server restart, network) is retried with exponential backoff; each
reconnection subscribes again and receives a fresh ``hello`` (``client.hello``), after which
frames continue. Only what can recover is retried (connection refused or reset, a timeout, an
HTTP 5xx, a connection closed mid-stream). A refusal is final: a missing or wrong token (HTTP
401/403 before the handshake) raises :class:`ClientRefused`, a protocol error from the server
(unknown session, bad stream) raises :class:`ClientError`; both say what to do in one line.

The token comes from ``token=`` or, by default, the ``ARTICAST_TOKEN`` environment variable,
and travels as ``Authorization: Bearer TOKEN``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import queue
import threading
from collections.abc import AsyncIterator, Iterator, Sequence
from typing import Any

import websockets

from articast.client import protocol as P


class ClientClosed(Exception):
    """The client was closed, or gave up reconnecting."""


class ClientError(Exception):
    """The server refused the subscription (an ``error`` message); not retried."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(f"{code}: {reason}")
        self.code, self.reason = code, reason


class ClientRefused(ClientError):
    """The server refused the connection itself (HTTP 401/403/4xx before the WebSocket
    handshake): retrying cannot help, so it is final and says what to do."""

    def __init__(self, url: str, status: int, detail: str = "") -> None:
        if status == 401:
            fix = ("the server needs a token, and none or a wrong one was given: set "
                   "ARTICAST_TOKEN or pass --token (the server's ARTICAST_TOKEN or --token-file)")
        elif status == 403:
            fix = ("the server does not accept this client (its Host/Origin rules"
                   + (f": {detail}" if detail else "") + ")")
        elif status == 429:
            fix = "too many failed attempts from this address: wait, then fix the token"
        else:
            fix = detail or "the server refused the connection"
        super().__init__("refused", f"{url}: HTTP {status}: {fix}")
        self.status = status


def _redact(url: str) -> str:
    """``url`` without a ``token=`` query value (messages never show the secret)."""
    head, sep, query = url.partition("?")
    if not sep:
        return url
    parts = [("token=…" if q.startswith("token=") else q) for q in query.split("&")]
    return head + "?" + "&".join(parts)


def _refusal_detail(exc: Any) -> str:
    body = getattr(getattr(exc, "response", None), "body", b"") or b""
    try:
        detail = json.loads(body).get("detail", "")
    except (ValueError, AttributeError):
        return ""
    return str(detail)[:200] if isinstance(detail, str) else ""


class Client:
    """Subscribe to one session of an articast server.

    url : ``ws://host:port/ws``. streams : among articulatory, pose, fap, arkit, mesh.
    rate : max frames/s (None: every frame). encoding : "json" or "binary".
    backoff_initial_s, backoff_max_s : reconnection delays (doubling); max_retries : give up
    after this many failed attempts in a row (None: never). token : the server's token
    (default: ``ARTICAST_TOKEN``; "" for none).
    """

    def __init__(self, url: str, session: str,
                 streams: Sequence[str] = ("articulatory", "pose"), *,
                 rate: float | None = None, encoding: str = "json", geometry: bool = True,
                 backoff_initial_s: float = 0.2, backoff_max_s: float = 5.0,
                 max_retries: int | None = None, open_timeout_s: float = 5.0,
                 token: str | None = None) -> None:
        self.url, self.session = url, session
        self.token = (os.environ.get("ARTICAST_TOKEN", "") if token is None else token).strip()
        self.subscribe_msg = P.Subscribe.model_validate(
            {"session": session, "streams": list(streams), "rate": rate, "encoding": encoding,
             "geometry": geometry})
        self.backoff = (backoff_initial_s, backoff_max_s)
        self.max_retries = max_retries
        self.open_timeout_s = open_timeout_s
        self.hello: P.Hello | None = None
        self.last_status: P.Status | None = None
        self.connects = 0
        self._ws: Any = None
        self._closed = False

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    async def close(self) -> None:
        self._closed = True
        if self._ws is not None:
            await self._ws.close()

    async def _connect(self) -> None:
        delay, failures = self.backoff[0], 0
        while not self._closed:
            try:
                headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
                self._ws = await websockets.connect(self.url, open_timeout=self.open_timeout_s,
                                                    max_size=2**26, close_timeout=1,
                                                    additional_headers=headers)
                await self._ws.send(self.subscribe_msg.model_dump_json())
                self.connects += 1
                return
            except websockets.InvalidStatus as exc:
                status = exc.response.status_code
                if 400 <= status < 500 and status != 408:
                    raise ClientRefused(_redact(self.url), status, _refusal_detail(exc)) from None
                failures += 1  # 5xx, 408: the server may recover
                if self.max_retries is not None and failures > self.max_retries:
                    raise ClientClosed(f"{_redact(self.url)}: gave up after {failures} attempts "
                                       f"(last: HTTP {status})") from None
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.backoff[1])
            except (TimeoutError, OSError, websockets.WebSocketException):
                failures += 1
                if self.max_retries is not None and failures > self.max_retries:
                    raise ClientClosed(f"{_redact(self.url)}: gave up after {failures} "
                                       "attempts") from None
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.backoff[1])
        raise ClientClosed("closed")

    async def frames(self) -> AsyncIterator[P.Frame]:
        """Frames of the session, across reconnections, until :meth:`close` (or the session
        ends: a ``status`` of ended/failed/stopped finishes the iteration)."""
        sids: dict[int, str] = {}
        names: dict[int, list[str]] = {}
        while not self._closed:
            await self._connect()
            try:
                async for data in self._ws:
                    msg = P.parse_server_message(data, sids, names)
                    if isinstance(msg, P.Hello):
                        self.hello = msg
                        sids[msg.sid], names[msg.sid] = msg.session, list(msg.param_names)
                    elif isinstance(msg, P.Frame):
                        yield msg
                    elif isinstance(msg, P.Status):
                        self.last_status = msg
                        if msg.state in ("ended", "failed", "stopped"):
                            return
                    elif isinstance(msg, P.Error):
                        raise ClientError(msg.code, msg.reason)
            except websockets.ConnectionClosed as exc:
                if exc.rcvd is not None and exc.rcvd.code == 1008:  # policy: final
                    raise ClientError("refused", exc.rcvd.reason or "closed by the server's "
                                      "policy (1008)") from None
                # anything else closed mid-stream: reconnect below
            finally:
                if self._ws is not None:
                    await self._ws.close()


class SyncSubscription:
    """Frames of a :class:`Client` for scripts without asyncio: a background thread runs the
    client; iterate it, read ``.hello``, and ``close()`` it (or use it in a ``with``)."""

    _DONE = object()

    def __init__(self, client: Client) -> None:
        self.client = client
        self._q: queue.Queue[Any] = queue.Queue(maxsize=256)
        self._loop = asyncio.new_event_loop()
        self._task = self._loop.create_task(self._pump())
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            self._loop.run_until_complete(self._task)
        # what the connection left running (its keepalive, its reader) is cancelled and
        # awaited before the loop closes, as asyncio.run does: else each is destroyed
        # pending, and Python says so on stderr when a script stops after --frames N
        rest = asyncio.all_tasks(self._loop)
        for task in rest:
            task.cancel()
        if rest:
            self._loop.run_until_complete(asyncio.gather(*rest, return_exceptions=True))
        self._loop.run_until_complete(self._loop.shutdown_asyncgens())
        self._loop.close()

    @property
    def hello(self) -> P.Hello | None:
        return self.client.hello

    async def _pump(self) -> None:
        try:
            async for frame in self.client.frames():
                await asyncio.to_thread(self._q.put, frame)
        except asyncio.CancelledError:
            self._offer(self._DONE)  # closed by close(): the consumer has stopped
            raise
        except Exception as exc:  # noqa: BLE001 - handed to the consumer thread
            await asyncio.to_thread(self._q.put, exc)
            return
        await asyncio.to_thread(self._q.put, self._DONE)

    def _offer(self, item: Any) -> None:
        with contextlib.suppress(queue.Full):
            self._q.put_nowait(item)

    def __iter__(self) -> Iterator[P.Frame]:
        while True:
            item = self._q.get()
            if item is self._DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        """Stop the client: its task is cancelled in its own loop (its ``finally`` closes the
        socket), so no coroutine is left un-awaited however far the client had got."""
        self.client._closed = True
        if self._thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop has just finished
                self._loop.call_soon_threadsafe(self._task.cancel)
            self._thread.join(2.0)

    def __enter__(self) -> SyncSubscription:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def subscribe_sync(url: str, session: str, streams: Sequence[str] = ("articulatory", "pose"),
                   **options: Any) -> SyncSubscription:
    """Frames from a script without asyncio::

        with subscribe_sync("ws://127.0.0.1:8765/ws", "demo") as sub:
            for frame in sub:
                print(frame.values.articulatory["jaw1"])
    """
    return SyncSubscription(Client(url, session, streams, **options))


def frame_record(frame: P.Frame) -> dict[str, Any]:
    """A frame as a recording line (what ``serve --record`` writes, replayable by the server)."""
    v = frame.values
    pose = v.pose.model_dump() if v.pose else None
    return {"type": "frame", "seq": frame.seq, "frame": frame.frame, "t": frame.t,
            "t_capture": frame.t_capture, "t_tracked": frame.t_tracked,
            "alpha": v.articulatory or {}, "pose": pose, "quality": frame.quality.model_dump()}


def header_record(hello: P.Hello) -> dict[str, Any]:
    """A recording header from ``hello`` (model, camera, source)."""
    doc = json.loads(hello.model_dump_json())
    return {"type": "header", "format": "articast-record", "version": 1,
            "session": hello.session, "source": doc.get("source") or {},
            "param_names": doc["param_names"], "param_stats": doc.get("param_stats"),
            "geometry": doc.get("geometry"), "camera": doc.get("camera")}

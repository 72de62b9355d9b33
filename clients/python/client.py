"""An async subscriber with automatic reconnection, and a synchronous iterator over it.

::

    async with Client("ws://127.0.0.1:8765/ws", "demo") as client:
        async for frame in client.frames():
            print(frame.seq, frame.values.articulatory)

A lost connection (server restart, network) is retried with exponential backoff; each
reconnection subscribes again and receives a fresh ``hello`` (``client.hello``), after which
frames continue. Protocol errors from the server (unknown session, bad stream) are not
retried: they raise :class:`ClientError`.
"""

from __future__ import annotations

import asyncio
import json
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


class Client:
    """Subscribe to one session of an articast server.

    url : ``ws://host:port/ws``. streams : among articulatory, pose, fap, arkit, mesh.
    rate : max frames/s (None: every frame). encoding : "json" or "binary".
    backoff_initial_s, backoff_max_s : reconnection delays (doubling); max_retries : give up
    after this many failed attempts in a row (None: never).
    """

    def __init__(self, url: str, session: str,
                 streams: Sequence[str] = ("articulatory", "pose"), *,
                 rate: float | None = None, encoding: str = "json", geometry: bool = True,
                 backoff_initial_s: float = 0.2, backoff_max_s: float = 5.0,
                 max_retries: int | None = None, open_timeout_s: float = 5.0) -> None:
        self.url, self.session = url, session
        self.subscribe_msg = P.Subscribe(session=session, streams=list(streams), rate=rate,
                                         encoding=encoding, geometry=geometry)
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
                self._ws = await websockets.connect(self.url, open_timeout=self.open_timeout_s,
                                                    max_size=2**26, close_timeout=1)
                await self._ws.send(self.subscribe_msg.model_dump_json())
                self.connects += 1
                return
            except (TimeoutError, OSError, websockets.WebSocketException):
                failures += 1
                if self.max_retries is not None and failures > self.max_retries:
                    raise ClientClosed(f"{self.url}: gave up after {failures} attempts") from None
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
            except websockets.ConnectionClosed:
                pass  # reconnect below
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
        self._thread = threading.Thread(target=self._loop.run_until_complete,
                                        args=(self._pump(),), daemon=True)
        self._thread.start()

    @property
    def hello(self) -> P.Hello | None:
        return self.client.hello

    async def _pump(self) -> None:
        try:
            async for frame in self.client.frames():
                await asyncio.to_thread(self._q.put, frame)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer thread
            self._q.put(exc)
            return
        self._q.put(self._DONE)

    def __iter__(self) -> Iterator[P.Frame]:
        while True:
            item = self._q.get()
            if item is self._DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        if self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self.client.close(), self._loop)
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

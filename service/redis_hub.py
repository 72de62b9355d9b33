"""The :class:`~articast.service.hub.Hub` protocol over Redis pub/sub, for more than one machine.

Tracker workers publish on any host; WebSocket gateways subscribe on any host. Each process
keeps an :class:`~articast.service.hub.InMemoryHub` for its local subscribers (bounded queues,
newest
wins, drops and throttling per subscriber, exactly as in-memory) and bridges it to Redis:

* ``publish`` encodes the message (``codec.encode``) and appends it to a bounded local buffer
  that a writer task drains into ``PUBLISH``; it never awaits Redis. If Redis is slower than
  the publisher, the oldest pending messages are dropped (:attr:`RedisHub.publish_dropped`).
  Messages come back to this process's own subscribers through Redis, like everyone else's.
* ``subscribe`` registers locally at once; a reader task joins the Redis channel. Messages
  published before the join completes are not seen (pub/sub semantics); :meth:`ready` waits
  for the joins.

Redis going away and coming back: the reader reconnects with backoff (0.1 s doubling to
``reconnect_max_s``) and joins its channels again; the writer drops what it cannot publish
and, once Redis is back, everything older than ``max_age_s``: frames from before the outage
are never replayed (a subscriber wants the face now, not 1,024 old frames). ``decode`` may
return None for a message this process cannot use yet (it is skipped).

Needs ``redis`` (``pip install articast[redis]``). Selected with ``--hub redis://HOST:PORT/DB``
(``serve``, ``track-worker``, ``gateway``); session descriptions travel with it
(:mod:`articast.service.remote`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar

from articast.service.hub import HubClosed, InMemoryHub, MemorySubscription

T = TypeVar("T")
log = logging.getLogger("articast.redis_hub")


class Codec(Protocol[T]):
    def encode(self, message: T) -> bytes: ...

    def decode(self, data: bytes) -> T: ...


class JSONCodec:
    """Messages that are JSON values."""

    def encode(self, message: Any) -> bytes:
        return json.dumps(message, separators=(",", ":")).encode()

    def decode(self, data: bytes) -> Any:
        return json.loads(data)


class RedisHub(Generic[T]):
    def __init__(self, url: str, codec: Codec[T], *, prefix: str = "articast:",
                 max_pending: int = 1024, max_age_s: float = 0.5,
                 reconnect_max_s: float = 2.0,
                 client: Callable[..., Any] | None = None) -> None:
        if client is None:
            import redis.asyncio as redis

            from articast.service.clock import CLOCK

            client = redis.from_url
            CLOCK.start(url)  # (times that cross machines go in Redis's clock)
        # short timeouts: a Redis that went away must not hold the writer for long
        self._redis = client(url, socket_connect_timeout=1.0, socket_timeout=5.0,
                             health_check_interval=0)
        self._codec, self._prefix = codec, prefix
        self._max_age, self._reconnect_max = max_age_s, reconnect_max_s
        self._local: InMemoryHub[T] = InMemoryHub()
        self._pending: deque[tuple[float, str, bytes]] = deque(maxlen=max_pending)
        self._wake = asyncio.Event()
        self._channels_changed = asyncio.Event()
        self._joined: set[str] = set()
        self._wanted: set[str] = set()
        self._joined_event = asyncio.Event()
        self._closed = False
        self.publish_dropped = 0
        self.stale_dropped = 0
        self.reconnects = 0
        self.connected = False
        self._tasks = [asyncio.create_task(self._writer(), name="redis hub writer"),
                       asyncio.create_task(self._reader(), name="redis hub reader")]

    # ------------------------------------------------------------------ the Hub protocol
    def publish(self, topic: str, message: T) -> int:
        if self._closed:
            return 0
        if len(self._pending) == self._pending.maxlen:
            self.publish_dropped += 1
        self._pending.append((time.monotonic(), topic, self._codec.encode(message)))
        self._wake.set()
        return self._local.subscriber_count(topic)

    def publish_local(self, topic: str, message: T) -> int:
        """Offer to this process's subscribers only (events a gateway makes itself)."""
        return self._local.publish(topic, message)

    @property
    def redis(self) -> Any:
        """The client (for the session directory's hash)."""
        return self._redis

    def subscribe(self, topic: str, *, max_queue: int = 4,
                  max_rate: float | None = None) -> MemorySubscription[T]:
        if self._closed:
            raise HubClosed("hub is closed")
        sub = self._local.subscribe(topic, max_queue=max_queue, max_rate=max_rate)
        if topic not in self._wanted:
            self._wanted.add(topic)
            self._joined_event.clear()
            self._channels_changed.set()
        return sub

    def subscriber_count(self, topic: str) -> int:
        return self._local.subscriber_count(topic)

    def close(self) -> None:
        self._closed = True
        self._local.close()
        for t in self._tasks:
            t.cancel()
        with contextlib.suppress(RuntimeError):
            asyncio.get_running_loop().create_task(self._redis.aclose())

    async def ready(self) -> None:
        """Wait until every subscribed topic has joined its Redis channel."""
        while self._wanted - self._joined:
            self._channels_changed.set()
            await self._joined_event.wait()

    # ------------------------------------------------------------------ tasks
    async def _writer(self) -> None:
        failing = False
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._pending:
                t, topic, data = self._pending.popleft()
                if time.monotonic() - t > self._max_age:
                    self.stale_dropped += 1  # too old to be worth sending: never replayed
                    continue
                try:
                    await self._redis.publish(self._prefix + topic, data)
                except Exception as exc:  # noqa: BLE001 - Redis down: drop, say so, go on
                    self.publish_dropped += 1
                    if not failing:
                        log.warning("redis publish failed (dropping until it is back): %r",
                                    exc)
                    failing = True
                    await asyncio.sleep(0.2)
                else:
                    if failing:
                        log.warning("redis publish works again")
                    failing = False

    async def _sync_channels(self, pubsub: Any) -> None:
        # leave channels nobody here follows any more, join the new ones
        for topic in list(self._wanted):
            if not self._local.subscriber_count(topic):
                self._wanted.discard(topic)
        leave = self._joined - self._wanted
        join = self._wanted - self._joined
        if leave:
            await pubsub.unsubscribe(*(self._prefix + t for t in leave))
            self._joined -= leave
        if join:
            await pubsub.subscribe(*(self._prefix + t for t in join))
            self._joined |= join
        self._joined_event.set()

    async def _reader(self) -> None:
        """Read channels; on any Redis error, reconnect with backoff and join them again."""
        delay = 0.1
        while True:
            pubsub = self._redis.pubsub(ignore_subscribe_messages=True)
            try:
                await self._read(pubsub)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - Redis away: reconnect, never die
                if self.connected:
                    log.warning("redis connection lost (%r); reconnecting", exc)
                self.connected = False
                self._joined = set()
                self._channels_changed.set()
                await asyncio.sleep(delay)
                delay = min(delay * 2, self._reconnect_max)
                self.reconnects += 1
            else:
                delay = 0.1
            finally:
                with contextlib.suppress(Exception):
                    await pubsub.aclose()

    async def _read(self, pubsub: Any) -> None:
        n = len(self._prefix)
        await self._redis.ping()  # fails fast while Redis is away
        self.connected = True
        while True:
            if self._channels_changed.is_set():
                self._channels_changed.clear()
                await self._sync_channels(pubsub)
            if not self._joined:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._channels_changed.wait(), 1.0)
                if not self._channels_changed.is_set():
                    await self._redis.ping()  # notice an outage even with nothing to read
                continue
            msg = await pubsub.get_message(timeout=0.05)
            if msg is None or msg.get("type") != "message":
                if not self._local_has_subscribers():
                    self._channels_changed.set()
                continue
            channel = msg["channel"]
            topic = (channel.decode() if isinstance(channel, bytes) else channel)[n:]
            try:
                message = self._codec.decode(msg["data"])
            except Exception as exc:  # noqa: BLE001 - one bad message, not the hub
                log.warning("undecodable message on %s: %r", topic, exc)
                continue
            if message is not None:
                self._local.publish(topic, message)

    def _local_has_subscribers(self) -> bool:
        return all(self._local.subscriber_count(t) for t in self._joined)

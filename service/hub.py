"""Publish/subscribe with a bounded queue per subscriber: the newest message wins.

The :class:`Hub` protocol is deliberately small so a Redis-backed hub can implement it later
(messages then travel as bytes through a codec given to that hub). Rules every hub keeps:

* ``publish`` never blocks and never awaits a subscriber: it appends to each subscriber's
  queue and, when a queue is full, drops that queue's *oldest* message and counts the drop
  against that subscriber only.
* ``Subscription.get`` is the only await; a stalled reader delays nobody but itself.
* ``max_rate`` throttles per subscriber at publish time (by the hub's monotonic clock), so
  a 30 Hz subscriber of a 60 Hz topic costs nothing for the frames it does not want; frames
  skipped by the throttle are not drops.

All methods of :class:`InMemoryHub` must be called from the event loop that owns it; a
thread or process that produces messages hands them over with
``loop.call_soon_threadsafe(hub.publish, topic, message)``.

Notes for the Redis hub (same protocol, messages through a codec to bytes): keep an
:class:`InMemoryHub` for the local fan-out (queues, drops, throttle stay per subscriber);
``publish`` puts the encoded message on a bounded local buffer drained by a writer task (it
must not await Redis) and returns the number of *local* subscribers offered; ``subscribe``
registers locally at once and joins the Redis channel from a reader task (messages published
before the join completes are not seen: pub/sub semantics). The contract tests in
``tests/test_hub.py`` then need a short wait after ``subscribe`` for that backend.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)


class HubClosed(Exception):
    """The subscription (or the whole hub) was closed while waiting for a message."""


class Subscription(Protocol[T_co]):
    topic: str

    @property
    def dropped(self) -> int: ...

    async def get(self) -> T_co: ...

    def get_nowait(self) -> T_co | None: ...

    def close(self) -> None: ...


class Hub(Protocol[T]):
    def publish(self, topic: str, message: T) -> int:
        """Offer ``message`` to every subscriber of ``topic``; returns how many took it."""
        ...

    def subscribe(
        self, topic: str, *, max_queue: int = 4, max_rate: float | None = None
    ) -> Subscription[T]: ...

    def subscriber_count(self, topic: str) -> int: ...

    def close(self) -> None: ...


class MemorySubscription(Generic[T]):
    """One subscriber's queue. Created by :meth:`InMemoryHub.subscribe`."""

    __slots__ = ("topic", "_queue", "_dropped", "_waiter", "_closed", "_hub", "_interval",
                 "_next_due", "delivered")

    def __init__(self, hub: InMemoryHub[T], topic: str, max_queue: int,
                 max_rate: float | None) -> None:
        if max_queue < 1:
            raise ValueError("max_queue must be at least 1")
        if max_rate is not None and max_rate <= 0:
            raise ValueError("max_rate must be positive")
        self.topic = topic
        self._hub = hub
        self._queue: deque[T] = deque(maxlen=max_queue)
        self._dropped = 0
        self._waiter: asyncio.Future[None] | None = None
        self._closed = False
        self._interval = 1.0 / max_rate if max_rate else 0.0
        self._next_due = 0.0
        self.delivered = 0

    @property
    def dropped(self) -> int:
        """Messages this subscriber lost because its queue was full."""
        return self._dropped

    @property
    def closed(self) -> bool:
        return self._closed

    def _offer(self, message: T, now: float) -> bool:
        if self._interval:
            # due times advance by whole intervals (no drift: 60 -> 50 Hz gives 50, not 30);
            # a quarter interval of slack absorbs source jitter; more than an interval late
            # (a pause, the first message) restarts the schedule from now
            if now < self._next_due - 0.25 * self._interval:
                return False
            late = now - self._next_due
            self._next_due = (self._next_due if late < self._interval else now) + self._interval
        if len(self._queue) == self._queue.maxlen:
            self._dropped += 1  # deque(maxlen) discards the oldest on append
        self._queue.append(message)
        self.delivered += 1
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)
        return True

    def get_nowait(self) -> T | None:
        """The oldest queued message, or None."""
        if self._queue:
            return self._queue.popleft()
        if self._closed:
            raise HubClosed(self.topic)
        return None

    async def get(self) -> T:
        """Wait for the next message; raises :class:`HubClosed` once closed and drained."""
        while not self._queue:
            if self._closed:
                raise HubClosed(self.topic)
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._queue.popleft()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._hub._remove(self)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)


class InMemoryHub(Generic[T]):
    """The embedded hub: topics are strings, messages any object (shared, never copied)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._topics: dict[str, list[MemorySubscription[T]]] = {}
        self._clock = clock
        self._closed = False
        self.published = 0

    def publish(self, topic: str, message: T) -> int:
        subs = self._topics.get(topic)
        self.published += 1
        if not subs:
            return 0
        now = self._clock()
        return sum(1 for s in tuple(subs) if s._offer(message, now))

    def subscribe(
        self, topic: str, *, max_queue: int = 4, max_rate: float | None = None
    ) -> MemorySubscription[T]:
        if self._closed:
            raise HubClosed("hub is closed")
        sub = MemorySubscription(self, topic, max_queue, max_rate)
        self._topics.setdefault(topic, []).append(sub)
        return sub

    def subscriber_count(self, topic: str) -> int:
        return len(self._topics.get(topic, ()))

    def subscriptions(self, topic: str) -> tuple[MemorySubscription[T], ...]:
        return tuple(self._topics.get(topic, ()))

    def _remove(self, sub: MemorySubscription[T]) -> None:
        subs = self._topics.get(sub.topic)
        if subs and sub in subs:
            subs.remove(sub)
            if not subs:
                del self._topics[sub.topic]

    def close(self) -> None:
        """Close every subscription: waiting readers get :class:`HubClosed`."""
        self._closed = True
        for subs in list(self._topics.values()):
            for s in list(subs):
                s.close()
        self._topics.clear()

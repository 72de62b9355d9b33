"""The hub contract: bounded queues, newest wins, drops counted per subscriber, isolation.

Written against the Hub protocol with the in-memory hub as the backend; a Redis hub is to be
added to ``HUBS`` and must pass the same tests.
"""

import asyncio
import inspect
import shutil
import socket
import subprocess
import time

import pytest

from articast.service.hub import HubClosed, InMemoryHub


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 10))


class Memory:
    """Backend adapter: build a hub inside the running loop; settle = let deliveries land."""

    def __call__(self):
        return InMemoryHub()

    async def settle(self, hub):
        pass


class Redis:
    def __init__(self, url):
        self.url = url

    def __call__(self):
        from articast.service.redis_hub import JSONCodec, RedisHub

        return RedisHub(self.url, JSONCodec(), prefix=f"test{time.monotonic_ns()}:")

    async def settle(self, hub):
        await hub.ready()


@pytest.fixture(scope="module")
def redis_url():
    if not shutil.which("redis-server"):
        pytest.skip("redis-server is not installed")
    pytest.importorskip("redis")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(["redis-server", "--port", str(port), "--save", "",
                             "--appendonly", "no"], stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), 0.2).close()
            break
        except OSError:
            assert time.monotonic() < deadline, "redis-server did not start"
            time.sleep(0.05)
    yield f"redis://127.0.0.1:{port}/0"
    proc.terminate()
    proc.wait(10)


@pytest.fixture(params=["memory", "redis"])
def make_hub(request):
    if request.param == "memory":
        return Memory()
    return Redis(request.getfixturevalue("redis_url"))


def test_fan_out_in_order(make_hub):
    async def go():
        hub = make_hub()
        a, b = hub.subscribe("s", max_queue=10), hub.subscribe("s", max_queue=10)
        await make_hub.settle(hub)
        for i in range(5):
            assert hub.publish("s", i) == 2
        assert [await a.get() for _ in range(5)] == list(range(5))
        assert [await b.get() for _ in range(5)] == list(range(5))
        assert a.dropped == b.dropped == 0
    run(go())


def test_topics_are_separate(make_hub):
    async def go():
        hub = make_hub()
        a = hub.subscribe("a")
        await make_hub.settle(hub)
        assert hub.publish("b", 1) == 0
        hub.publish("a", 2)
        assert await a.get() == 2
        await asyncio.sleep(0.05)  # a message on "b" would have arrived by now
        assert a.get_nowait() is None
    run(go())


def test_full_queue_drops_oldest_and_counts_for_that_subscriber_only(make_hub):
    async def go():
        hub = make_hub()
        slow, fast = hub.subscribe("s", max_queue=3), hub.subscribe("s", max_queue=3)
        await make_hub.settle(hub)
        got = []
        for i in range(10):
            hub.publish("s", i)
            got.append(await fast.get())
        assert got == list(range(10)) and fast.dropped == 0
        assert slow.dropped == 7
        assert [await slow.get() for _ in range(3)] == [7, 8, 9]  # the newest won
    run(go())


def test_publish_never_waits_for_a_stalled_subscriber(make_hub):
    async def go():
        hub = make_hub()
        hub.subscribe("s", max_queue=1)  # never read
        await make_hub.settle(hub)
        ticks = []

        async def other():
            ticks.append(1)

        task = asyncio.create_task(other())
        for i in range(10000):
            # publish is a plain call: it returns nothing to await and never yields to the
            # loop (the other task cannot run in between), however full the reader's queue
            assert not inspect.isawaitable(hub.publish("s", i))
        assert ticks == []
        await task
        assert ticks == [1]
    run(go())


def test_get_waits_then_wakes(make_hub):
    async def go():
        hub = make_hub()
        sub = hub.subscribe("s")
        await make_hub.settle(hub)
        task = asyncio.create_task(sub.get())
        await asyncio.sleep(0.01)
        assert not task.done()
        hub.publish("s", "x")
        assert await task == "x"
    run(go())


def test_close_wakes_a_waiting_reader_and_unsubscribes(make_hub):
    async def go():
        hub = make_hub()
        sub = hub.subscribe("s")
        await make_hub.settle(hub)
        task = asyncio.create_task(sub.get())
        await asyncio.sleep(0.01)
        sub.close()
        with pytest.raises(HubClosed):
            await task
        assert hub.subscriber_count("s") == 0
        assert hub.publish("s", 1) == 0
    run(go())


def test_hub_close_closes_everyone(make_hub):
    async def go():
        hub = make_hub()
        subs = [hub.subscribe("s") for _ in range(3)]
        hub.close()
        for s in subs:
            with pytest.raises(HubClosed):
                await s.get()
        await asyncio.sleep(0)
    run(go())


def test_max_rate_throttles_without_counting_drops():
    clock = [0.0]
    hub = InMemoryHub(clock=lambda: clock[0])
    sub = hub.subscribe("s", max_queue=1000, max_rate=30)
    every = hub.subscribe("s", max_queue=1000)
    delivered = 0
    for i in range(600):  # 10 s at 60 Hz, with +-3 ms of jitter
        clock[0] = i / 60 + (0.003 if i % 3 == 0 else -0.002)
        hub.publish("s", i)
    while sub.get_nowait() is not None:
        delivered += 1
    assert 290 <= delivered <= 310  # 30 Hz, not 20 (jitter) and not 60
    assert sub.dropped == 0 and every.delivered == 600


@pytest.mark.parametrize("source_hz, rate, expected", [(60, 30, 30), (60, 20, 20), (60, 50, 50),
                                                      (30, 60, 30), (60, 59, 59)])
def test_max_rate_gives_the_rate_asked_for(source_hz, rate, expected):
    clock = [100.0]
    hub = InMemoryHub(clock=lambda: clock[0])
    sub = hub.subscribe("s", max_queue=10000, max_rate=rate)
    for i in range(source_hz * 10):
        clock[0] = 100.0 + i / source_hz + 0.002 * ((i * 7) % 3 - 1)  # +-2 ms jitter
        hub.publish("s", i)
    assert abs(sub.delivered / 10 - expected) <= 0.05 * expected + 1


def test_max_rate_first_messages_are_throttled_too():
    clock = [1000.0]
    hub = InMemoryHub(clock=lambda: clock[0])
    sub = hub.subscribe("s", max_queue=100, max_rate=30)
    for i in range(4):  # 0, 16.7, 33.3, 50 ms
        clock[0] = 1000.0 + i / 60
        hub.publish("s", i)
    assert [sub.get_nowait() for _ in range(2)] == [0, 2]


def test_bad_limits_are_refused():
    hub = InMemoryHub()
    with pytest.raises(ValueError):
        hub.subscribe("s", max_queue=0)
    with pytest.raises(ValueError):
        hub.subscribe("s", max_rate=0)

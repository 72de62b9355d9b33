"""Scale-out on Redis, as a deployment runs it: a real ``redis-server`` on loopback, one
``articast track-worker`` and two ``articast gateway`` processes (the entrypoints the Docker
compose file runs), real WebSocket subscribers on both gateways.

Shown: hello travels through Redis (a gateway has no local session); a Redis restart
mid-stream: worker and gateways reconnect by themselves, subscribers on every gateway get
frames again, and nothing produced during the outage is replayed.
"""

import asyncio
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import websockets

from tests.service_helpers import TIMEOUT, write_recording

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not shutil.which("redis-server"),
                                reason="redis-server is not installed")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Redis:
    def __init__(self) -> None:
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(["redis-server", "--port", str(self.port), "--save", "",
                                      "--appendonly", "no", "--bind", "127.0.0.1"],
                                     stdout=subprocess.DEVNULL)
        deadline = time.monotonic() + TIMEOUT
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.2).close()
                return
            except OSError:
                assert time.monotonic() < deadline, "redis-server did not start"
                time.sleep(0.05)

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(TIMEOUT)
            self.proc = None


def articast(*args, env=None):
    e = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    e.update(env or {})
    return subprocess.Popen([sys.executable, "-m", "articast.service.cli", *args], cwd=ROOT,
                            env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def first_line(p) -> dict:
    line = p.stdout.readline()
    if not line:
        raise AssertionError(p.stderr.read())
    return json.loads(line)


def stop(p) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.fixture
def deployment(tmp_path):
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=90, fps=30)
    redis = Redis()
    redis.start()
    procs = []
    try:
        worker = articast("track-worker", "--hub", redis.url, "--json",
                          "--source", f"alice=replay-record:{rec}?loop=yes")
        procs.append(worker)
        first_line(worker)
        urls = []
        for _ in range(2):
            g = articast("gateway", "--hub", redis.url, "--port", "0", "--json")
            procs.append(g)
            urls.append(first_line(g)["url"])
        yield redis, urls, procs
    finally:
        for p in procs:
            stop(p)
        redis.stop()


async def subscriber(url, session="alice"):
    deadline = time.monotonic() + 3 * TIMEOUT
    while True:  # the gateway learns of the session within a second or two
        ws = await websockets.connect(url, max_size=2**24)
        await ws.send(json.dumps({"type": "subscribe", "session": session}))
        m = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))
        if m["type"] != "error":
            return ws, m
        await ws.close()
        assert m["code"] == "unknown_session" and time.monotonic() < deadline, m
        await asyncio.sleep(0.2)


def worker_and_gateway(hub_url, source, procs) -> str:
    """A track-worker of ``source`` and a gateway on ``hub_url`` (added to ``procs``): the
    gateway's URL."""
    procs.append(articast("track-worker", "--hub", hub_url, "--json", "--source", source))
    first_line(procs[-1])
    procs.append(articast("gateway", "--hub", hub_url, "--port", "0", "--json"))
    return first_line(procs[-1])["url"]


async def streaming(url):
    """A subscriber of alice on ``url`` that has had its hello and a first frame."""
    ws, first = await subscriber(url)
    if first["type"] != "hello":
        await next_of(ws, "hello")
    await next_of(ws, "frame")
    return ws


async def next_of(ws, kind):
    while True:
        m = json.loads(await asyncio.wait_for(ws.recv(), 3 * TIMEOUT))
        if m["type"] == kind:
            return m


def test_hello_and_frames_through_redis_and_recovery_after_a_redis_restart(deployment):
    redis, urls, procs = deployment

    async def go():
        subs = []
        for url in urls:
            for _ in range(2):
                ws, first = await subscriber(url)
                hello = first if first["type"] == "hello" else await next_of(ws, "hello")
                assert hello["session"] == "alice" and hello["geometry"]["n_points"] == 12
                assert len(hello["param_names"]) == 7
                subs.append(ws)
        for ws in subs:
            await next_of(ws, "frame")
        # the gateway's API shows the remote session
        http = urls[0].replace("ws://", "http://").rsplit("/ws", 1)[0]
        listed = httpx.get(http + "/api/sessions", timeout=TIMEOUT).json()
        assert [s["name"] for s in listed] == ["alice"] and listed[0]["state"] == "running"
        # the worker container's HEALTHCHECK (docker/compose.yaml) passes
        env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
        health = subprocess.run([sys.executable, "-m", "articast.service.healthcheck",
                                 "--worker"], env={**env, "ARTICAST_HUB": redis.url},
                                capture_output=True, text=True, timeout=60)
        assert health.returncode == 0, health.stderr

        t_down = time.time()
        redis.stop()
        await asyncio.sleep(2.0)
        t_up = time.time()
        redis.start()
        # every subscriber on every gateway receives again, by itself
        firsts = []
        for ws in subs:
            while True:
                m = await next_of(ws, "frame")
                if m["t_tracked"] > t_down:
                    firsts.append(m)
                    break
        # nothing tracked during the outage is replayed (0.5 s writer age limit + slack)
        for m in firsts:
            assert m["t_tracked"] > t_up - 1.0, (m["t_tracked"] - t_down, t_up - t_down)
        for ws in subs:
            await ws.close()

    asyncio.run(asyncio.wait_for(go(), 12 * TIMEOUT))
    for p in procs:
        assert p.poll() is None, p.stderr.read()


def test_serve_with_the_redis_hub(tmp_path):
    """``serve --hub redis://`` is worker and gateway in one process, through Redis."""
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=60, fps=30)
    redis = Redis()
    redis.start()
    p = articast("serve", "--hub", redis.url, "--port", "0", "--json",
                 "--source", f"bob=replay-record:{rec}?loop=yes")
    try:
        url = first_line(p)["url"]

        async def go():
            ws, first = await subscriber(url, "bob")
            hello = first if first["type"] == "hello" else await next_of(ws, "hello")
            assert hello["session"] == "bob"
            f = await next_of(ws, "frame")
            assert f["session"] == "bob" and len(f["values"]["articulatory"]) == 7
            await ws.close()

        asyncio.run(asyncio.wait_for(go(), 6 * TIMEOUT))
    finally:
        stop(p)
        redis.stop()


def test_roles_refuse_a_missing_or_wrong_hub():
    for args in (["gateway", "--port", "0"], ["track-worker", "--source", "a=synthetic:"],
                 ["gateway", "--hub", "http://x"]):
        p = articast(*args)
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2 and "--hub" in err and "Traceback" not in err, err


def test_a_killed_worker_is_reported_and_its_replacement_streams_again(tmp_path):
    """kill -9 of a track-worker: its session becomes ``unavailable`` on the gateway (no
    heartbeat); a new worker for the same session brings a new hello, then frames."""
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=60, fps=30)
    redis = Redis()
    redis.start()
    source = f"alice=replay-record:{rec}?loop=yes"
    procs: list = []
    try:
        url = worker_and_gateway(redis.url, source, procs)

        async def go():
            ws = await streaming(url)
            procs[0].kill()
            procs[0].wait(TIMEOUT)
            while True:
                m = await next_of(ws, "status")
                if m["state"] == "unavailable":
                    assert "worker" in m["detail"]
                    break
            procs.append(articast("track-worker", "--hub", redis.url, "--json",
                                  "--source", source))
            await next_of(ws, "hello")
            await next_of(ws, "frame")
            await ws.close()

        asyncio.run(asyncio.wait_for(go(), 12 * TIMEOUT))
    finally:
        for p in procs:
            stop(p)
        redis.stop()

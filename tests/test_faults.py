"""Faults: a hung worker is declared ``stalled``, subscribers are told, the worker restarted;
a worker that is still starting (first run: caches, compilation) is not stalled."""

import asyncio
import json
import os
import signal

import websockets

from articast.service.app import ServiceConfig
from articast.service.settings import ServerSettings, SessionPolicy
from articast.service.worker import SessionSpec
from tests.service_helpers import TIMEOUT, ServerThread, write_recording


def test_a_hung_worker_is_declared_stalled_and_restarted(tmp_path):
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=60, fps=30)
    config = ServiceConfig(
        server=ServerSettings(log_level="critical"),
        policy=SessionPolicy(worker="process", worker_stall_s=1.0, restart_initial_s=0.05,
                             restart_max_s=0.2),
        sessions=(SessionSpec("rec", f"replay-record:{rec}?loop=yes"),))

    async def go(srv):
        async with websockets.connect(srv.url, max_size=2**24) as ws:
            await ws.send(json.dumps({"type": "subscribe", "session": "rec",
                                      "geometry": False}))

            async def until(pred):
                while True:
                    m = json.loads(await asyncio.wait_for(ws.recv(), 3 * TIMEOUT))
                    if pred(m):
                        return m

            await until(lambda m: m["type"] == "frame")
            session = srv.service.manager.sessions["rec"]
            pid = session._worker.process.pid
            os.kill(pid, signal.SIGSTOP)  # hung: alive, silent
            try:
                m = await until(lambda m: m["type"] == "status" and m["state"] == "stalled")
                assert "no frame" in m["detail"]
                await until(lambda m: m["type"] == "hello")  # a new worker, a new hello
                await until(lambda m: m["type"] == "frame")
            finally:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            assert session._worker.process.pid != pid
            assert session.metrics.restarts >= 1 and session.state == "running"

    with ServerThread(config) as srv:
        asyncio.run(asyncio.wait_for(go(srv), 6 * TIMEOUT))


def test_a_worker_starting_slower_than_the_stall_bound_is_not_killed(tmp_path, caplog):
    """The first `articast demo` ever: the worker builds its caches and compiles for longer
    than --worker-stall-s after its source opened; the watchdog killed it (code -9) and the
    next start did the same. A starting worker is held to --worker-start-s instead, and
    what it does is said on the console and to subscribers."""
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=30, fps=30)
    config = ServiceConfig(
        server=ServerSettings(log_level="critical"),
        policy=SessionPolicy(worker="process", worker_stall_s=0.5, restart_initial_s=0.05),
        sessions=(SessionSpec("slow", f"replay-record:{rec}?loop=yes",
                              processor="tests.service_helpers:SlowStart",
                              options={"start_s": 2.0}),))

    async def go(srv):
        seen = []
        async with websockets.connect(srv.url, max_size=2**24) as ws:
            await ws.send(json.dumps({"type": "subscribe", "session": "slow",
                                      "geometry": False}))
            while not any(m["type"] == "frame" for m in seen):
                seen.append(json.loads(await asyncio.wait_for(ws.recv(), 3 * TIMEOUT)))
        states = [(m["state"], m["detail"]) for m in seen if m["type"] == "status"]
        assert ("starting", "building test caches (first run only)") in states, states
        assert not any(state == "stalled" for state, _ in states), states
        assert srv.service.manager.sessions["slow"].metrics.restarts == 0

    with caplog.at_level("WARNING", logger="articast.session"):
        with ServerThread(config) as srv:
            asyncio.run(asyncio.wait_for(go(srv), 6 * TIMEOUT))
    lines = [r.getMessage() for r in caplog.records]
    assert "session slow: building test caches (first run only)" in lines, lines
    assert not any("stalled" in line for line in lines), lines


def test_compiling_longer_than_the_start_bound_is_starting_not_a_stall(tmp_path, caplog):
    """Issue 39: the first `articast demo` on a fresh install compiled the kernels for longer
    than --worker-start-s (120 s at load 5-14), was declared stalled, reported crashed and
    compiled all over again. Work known to finish (the compilation) keeps the worker alive
    while it runs: three times the start bound, no stall, no restart, then frames."""
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=30, fps=30)
    config = ServiceConfig(
        server=ServerSettings(log_level="critical"),
        policy=SessionPolicy(worker="process", worker_stall_s=0.5, worker_start_s=1.0,
                             restart_initial_s=0.05, max_restarts=0),
        sessions=(SessionSpec("compiles", f"replay-record:{rec}?loop=yes",
                              processor="tests.service_helpers:BusyStart",
                              options={"start_s": 3.0}),))

    async def go(srv):
        session = srv.service.manager.sessions["compiles"]
        while session.metrics.frames == 0:
            assert session.state in ("starting", "running"), (session.state, session.detail)
            await asyncio.sleep(0.05)
        assert session.metrics.restarts == 0

    with caplog.at_level("WARNING", logger="articast.session"):
        with ServerThread(config) as srv:
            asyncio.run(asyncio.wait_for(go(srv), 6 * TIMEOUT))
    lines = [r.getMessage() for r in caplog.records]
    assert "session compiles: compiling test kernels (first run only)" in lines, lines
    assert not any("stalled" in line or "crashed" in line for line in lines), lines


def test_a_worker_that_never_finishes_starting_is_declared_stalled(tmp_path):
    """...within --worker-start-s, even while its looping source keeps reopening."""
    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=10, fps=30)
    config = ServiceConfig(
        server=ServerSettings(log_level="critical"),
        policy=SessionPolicy(worker="process", worker_stall_s=0.5, worker_start_s=1.0,
                             restart_initial_s=0.05, max_restarts=0),
        sessions=(SessionSpec("hung", f"replay-record:{rec}?loop=yes",
                              processor="tests.service_helpers:SlowStart",
                              options={"start_s": 600.0}),))

    async def go(srv):
        session = srv.service.manager.sessions["hung"]
        while session.state != "failed":
            await asyncio.sleep(0.05)
        assert "stalled: no start for" in session.detail, session.detail

    with ServerThread(config) as srv:
        asyncio.run(asyncio.wait_for(go(srv), 6 * TIMEOUT))

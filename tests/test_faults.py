"""Faults: a hung worker is declared ``stalled``, subscribers are told, the worker restarted."""

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
        sessions=(SessionSpec("rec", f"replay-record:{rec}?loop=0"),))

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

"""The Python client against a real server: typed frames, both encodings, reconnection
across a server restart on the same port, the recorder, and a light import."""

import asyncio
import json
import subprocess
import sys
import time

import pytest

from articast.client import Client, ClientError, subscribe_sync
from articast.service.app import ServiceConfig
from articast.service.settings import ServerSettings
from articast.service.worker import SessionSpec
from tests.service_helpers import TIMEOUT, ServerThread, write_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "talk.jsonl"
    write_recording(path, frames=60, fps=30)
    return path


def config(recording, loop="yes"):
    spec = SessionSpec("rec", f"replay-record:{recording}?loop={loop}")
    return ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,))


class PortServer(ServerThread):
    """A server on a given port (to restart one where the client expects it)."""

    def __init__(self, cfg, port):
        super().__init__(cfg)
        from articast.service.server import bound_socket

        self.sock.close()
        self.sock = bound_socket("127.0.0.1", port)
        self.port = port
        self.url = f"ws://127.0.0.1:{port}/ws"


def test_typed_frames_after_hello_in_both_encodings(recording):
    async def take(url, encoding, n=10):
        async with Client(url, "rec", ("articulatory", "pose"), encoding=encoding) as c:
            out = []
            async for f in c.frames():
                out.append(f)
                if len(out) == n:
                    return c.hello, out

    with ServerThread(config(recording)) as srv:
        hello, frames = asyncio.run(asyncio.wait_for(take(srv.url, "json"), 6 * TIMEOUT))
        _, binary = asyncio.run(asyncio.wait_for(take(srv.url, "binary"), 6 * TIMEOUT))
    assert hello is not None and hello.session == "rec" and len(hello.param_names) == 7
    assert all(f.values.articulatory is not None and len(f.values.pose.rotation) == 3
               for f in frames)
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs)
    # binary carries float32: the same parameters to float32 precision
    jb = {f.frame: f for f in frames}
    common = [f for f in binary if f.frame in jb]
    for f in common:
        for k, v in f.values.articulatory.items():
            assert v == pytest.approx(jb[f.frame].values.articulatory[k], rel=1e-6, abs=1e-6)


def test_unknown_session_is_a_client_error(recording):
    async def go(url):
        async with Client(url, "nobody") as c:
            async for _ in c.frames():
                pass

    with ServerThread(config(recording)) as srv:
        with pytest.raises(ClientError, match="unknown_session"):
            asyncio.run(asyncio.wait_for(go(srv.url), 6 * TIMEOUT))


def test_reconnects_after_the_server_restarts(recording):
    first = ServerThread(config(recording, loop="yes"))
    port = first.port
    got, hellos = [], []

    async def consume(client):
        async for f in client.frames():
            got.append((client.connects, f))
            if client.hello is not None and (not hellos or hellos[-1] is not client.hello):
                hellos.append(client.hello)
            if sum(1 for c, _ in got if c == 2) >= 5:
                return

    async def scenario():
        client = Client(first.url, "rec", backoff_initial_s=0.05, backoff_max_s=0.2)
        task = asyncio.create_task(consume(client))
        deadline = time.monotonic() + TIMEOUT
        while len(got) < 5 and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        assert len(got) >= 5, "no frames before the restart"
        await asyncio.to_thread(first.__exit__, None, None, None)  # server goes away
        before = len(got)
        await asyncio.sleep(0.3)
        second = PortServer(config(recording, loop="yes"), port)
        await asyncio.to_thread(second.__enter__)
        try:
            await asyncio.wait_for(task, 6 * TIMEOUT)
        finally:
            await client.close()
            await asyncio.to_thread(second.__exit__, None, None, None)
        return client, before

    with first:
        client, before = asyncio.run(scenario())
    assert client.connects == 2
    assert len(hellos) >= 2 and len(got) > before  # hello again, and frames again
    assert sum(1 for c, _ in got if c == 2) >= 5


def test_record_cli_writes_a_replayable_file(recording, tmp_path):
    out = tmp_path / "out.jsonl"
    with ServerThread(config(recording, loop="yes")) as srv:
        r = subprocess.run([sys.executable, "-m", "articast.client.record", srv.url, "rec",
                            "-o", str(out), "--frames", "12"], capture_output=True, text=True,
                           timeout=60)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert lines[0]["type"] == "header" and len(lines) == 13
    assert all(x["type"] == "frame" and len(x["alpha"]) == 7 for x in lines[1:])
    # the server can serve the client's recording again
    from articast.service.sources import make_source

    src = make_source(f"replay-record:{out}?pace=fast")
    src.open()
    assert src.read() is not None


def test_sync_iterator(recording):
    with ServerThread(config(recording)) as srv:
        with subscribe_sync(srv.url, "rec") as sub:
            frames = []
            for f in sub:
                frames.append(f)
                if len(frames) == 5:
                    break
            assert sub.hello is not None
    assert len(frames) == 5


def test_client_imports_without_opencv_fastapi_or_the_tracker():
    code = ("import sys\n"
            "for m in ('cv2', 'fastapi', 'uvicorn', 'core', 'numpy'):\n"
            "    sys.modules[m] = None\n"
            "import articast.client as c\n"
            "print(c.Client.__name__)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "Client"

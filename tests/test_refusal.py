"""Issue 20, item 1: a refusal is final, said once, with the fix.

A wrong or missing token (HTTP 401 before the handshake) or an unknown session makes the
Python client, ``articast-print`` and ``articast-record`` stop with one line naming the fix
and a non-zero status, instead of retrying silently for ever; what can recover (connection
refused, a server restart) is still retried. The server logs each refused handshake as a
refusal, never as ``ASGI callable returned without completing handshake``.
"""

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from articast.client import Client, ClientClosed, ClientError, ClientRefused
from articast.service.app import ServiceConfig
from articast.service.security import AccessPolicy
from articast.service.settings import ServerSettings
from articast.service.worker import SessionSpec
from tests.service_helpers import TIMEOUT, ServerThread, write_recording

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "a-token-of-at-least-16-bytes"


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "talk.jsonl"
    write_recording(path, frames=60, fps=30)
    return path


def config(recording, token=TOKEN):
    spec = SessionSpec("rec", f"replay-record:{recording}?loop=yes")
    return ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,),
                         access=AccessPolicy(token=token))


async def first_frame(url, session="rec", **kw):
    async with Client(url, session, backoff_initial_s=0.05, backoff_max_s=0.1, **kw) as c:
        async for f in c.frames():
            return f


def test_a_wrong_or_missing_token_is_final_and_says_the_fix(recording, monkeypatch):
    monkeypatch.delenv("ARTICAST_TOKEN", raising=False)
    with ServerThread(config(recording)) as srv:
        plain = f"ws://127.0.0.1:{srv.port}/ws"
        for kw in ({}, {"token": "wrong-token-wrong-token"}):
            t0 = time.monotonic()
            with pytest.raises(ClientRefused) as e:
                asyncio.run(asyncio.wait_for(first_frame(plain, **kw), 6 * TIMEOUT))
            assert time.monotonic() - t0 < TIMEOUT  # at once, not after retries
            msg = str(e.value)
            assert "401" in msg and "ARTICAST_TOKEN" in msg and "--token" in msg, msg
            assert "\n" not in msg
        # the right token, from the argument or from ARTICAST_TOKEN, streams
        f = asyncio.run(asyncio.wait_for(first_frame(plain, token=TOKEN), 6 * TIMEOUT))
        assert f is not None
        monkeypatch.setenv("ARTICAST_TOKEN", TOKEN)
        assert asyncio.run(asyncio.wait_for(first_frame(plain), 6 * TIMEOUT)) is not None
        # a refusal never shows the token offered in the URL
        with pytest.raises(ClientRefused) as e:
            asyncio.run(asyncio.wait_for(first_frame(plain + "?token=guess-guess-guess",
                                                     token=""), 6 * TIMEOUT))
        assert "guess-guess-guess" not in str(e.value)


def test_what_can_recover_is_still_retried():
    """Connection refused is retried (until max_retries), not final."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nobody listens there
    with pytest.raises(ClientClosed, match="gave up after 3 attempts"):
        asyncio.run(asyncio.wait_for(first_frame(f"ws://127.0.0.1:{port}/ws", max_retries=2),
                                     6 * TIMEOUT))


def _client_cli(module, *args, env_token=None):
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    env["PYTHONPATH"] = str(ROOT)
    if env_token is not None:
        env["ARTICAST_TOKEN"] = env_token
    return subprocess.run([sys.executable, "-W", "default", "-m", module, *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=20 * TIMEOUT)


@pytest.mark.parametrize("module", ["articast.client.print", "articast.client.record"])
def test_the_commands_stop_with_one_line(recording, tmp_path, module):
    out = ["-o", str(tmp_path / "o.jsonl")] if module.endswith("record") else []
    with ServerThread(config(recording)) as srv:
        plain = f"ws://127.0.0.1:{srv.port}/ws"
        t0 = time.monotonic()
        r = _client_cli(module, plain, "rec", *out)
        assert time.monotonic() - t0 < 10 * TIMEOUT
        lines = r.stderr.strip().splitlines()
        assert r.returncode != 0 and len(lines) == 1, r.stderr
        assert "ARTICAST_TOKEN" in lines[0] and "--token" in lines[0], lines
        # an unknown session: one line, and no "coroutine ... was never awaited"
        r = _client_cli(module, plain, "nobody", *out, env_token=TOKEN)
        lines = r.stderr.strip().splitlines()
        assert r.returncode != 0 and len(lines) == 1, r.stderr
        assert "unknown_session" in lines[0] and "never awaited" not in r.stderr
        # and with the token it works (the first frames, then it stops)
        r = _client_cli(module, plain, "rec", "--frames", "3", *out, "--token", TOKEN)
        assert r.returncode == 0, r.stderr
        assert "never awaited" not in r.stderr


def test_an_ended_session_is_final(recording):
    spec = SessionSpec("rec", f"replay-record:{recording}?loop=no&pace=fast")
    cfg = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,))
    with ServerThread(cfg) as srv:
        async def drain():
            async with Client(srv.url, "rec") as c:
                async for _ in c.frames():
                    pass
                return c.last_status

        deadline = time.monotonic() + 3 * TIMEOUT
        while srv.service.manager.sessions["rec"].state != "ended":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        status = asyncio.run(asyncio.wait_for(drain(), 3 * TIMEOUT))
        assert status is not None and status.state == "ended"


def test_the_server_logs_a_refused_handshake_once_as_such(recording, tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    env.update(PYTHONPATH=str(ROOT), ARTICAST_TOKEN=TOKEN)
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "replay-record",
                          str(recording), "--loop", "--port", "0", "--json",
                          "--log-level", "info"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        import json

        url = json.loads(p.stdout.readline())["url"]
        with pytest.raises(ClientError):
            asyncio.run(asyncio.wait_for(first_frame(url, token="not-the-right-token"),
                                         6 * TIMEOUT))
    finally:
        p.terminate()
        _, err = p.communicate(timeout=10 * TIMEOUT)
    assert "without completing handshake" not in err, err
    refusals = [x for x in err.splitlines() if "refused" in x]
    assert len(refusals) == 1 and "401" in refusals[0] and "wrong token" in refusals[0], err
    assert TOKEN not in err and "not-the-right-token" not in err

"""``articast serve`` / ``replay-record`` as a user runs them: a subprocess, SIGTERM, recordings."""

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import websockets

from tests.service_helpers import TIMEOUT, write_recording, write_video

ROOT = Path(__file__).resolve().parents[1]


def start(*args):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ARTICAST_LOG_LEVEL": "error"}
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", *args, "--port", "0", "--json"],
                         cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    line = p.stdout.readline()
    if not line:
        p.kill()
        raise AssertionError(p.stderr.read())
    return p, json.loads(line)["url"]


async def frames(url, session, n):
    out = []
    async with websockets.connect(url, close_timeout=1) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": session}))
        while len(out) < n:
            m = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))
            if m["type"] == "frame":
                out.append(m)
    return out


def test_serve_records_and_stops_cleanly_on_sigterm(tmp_path):
    rec = tmp_path / "in.jsonl"
    write_recording(rec, frames=40, fps=60)
    out = tmp_path / "out"
    p, url = start("serve", "--source", f"talk=replay-record:{rec}?loop=yes", "--record", str(out))
    try:
        got = asyncio.run(frames(url, "talk", 20))
        assert len(got) == 20
    finally:
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        code = p.wait(TIMEOUT * 2)
    # uvicorn shuts down gracefully, then re-raises the signal so supervisors see it
    assert code in (0, -signal.SIGTERM) and time.monotonic() - t0 < TIMEOUT
    assert "Traceback" not in p.stderr.read()
    files = list(out.glob("talk-*.jsonl"))
    assert len(files) == 1
    lines = files[0].read_text().splitlines()
    assert json.loads(lines[0])["type"] == "header"
    assert all(json.loads(x)["type"] == "frame" for x in lines[1:]) and len(lines) > 20

    # what was recorded serves again, with the same values
    p2, url2 = start("replay-record", str(files[0]), "--name", "again", "--loop")
    try:
        again = asyncio.run(frames(url2, "again", 5))
    finally:
        p2.send_signal(signal.SIGTERM)
        p2.wait(TIMEOUT * 2)
    # the replay numbers frames by their line in the recording (which, on a loaded machine,
    # may have skipped source frames: the capture keeps only the newest)
    by_line = [json.loads(x)["alpha"] for x in lines[1:]]
    for f in again:
        assert f["values"]["articulatory"] == pytest.approx(by_line[f["frame"] % len(by_line)])


def test_replay_of_a_corrupt_video_is_one_clear_error(tmp_path):
    bad = tmp_path / "talk.mp4"
    bad.write_bytes(b"not a video at all" * 100)
    r = subprocess.run([sys.executable, "-m", "articast.service.cli", "replay", str(bad)], cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "talk.mp4" in r.stderr
    assert "Traceback" not in r.stderr


def test_bad_source_option_is_one_clear_error():
    r = subprocess.run([sys.executable, "-m", "articast.service.cli", "serve", "--source", "nope"],
                       cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "NAME=URI" in r.stderr and "Traceback" not in r.stderr


def test_replay_without_an_appearance_model_says_so(tmp_path):
    video = tmp_path / "v.avi"
    from tests.service_helpers import write_video

    write_video(video, frames=3)
    r = subprocess.run([sys.executable, "-m", "articast.service.cli", "replay", str(video)], cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "appearance" in r.stderr and "Traceback" not in r.stderr


def test_sigterm_with_subscribers_connected(tmp_path):
    rec = tmp_path / "in.jsonl"
    write_recording(rec, frames=40, fps=60)
    p, url = start("serve", "--source", f"a=replay-record:{rec}?loop=yes",
                   "--source", f"b=replay-record:{rec}?loop=yes")  # a thread and a process

    async def go():
        clients = []
        for name in ("a", "b"):
            ws = await websockets.connect(url, close_timeout=1)
            await ws.send(json.dumps({"type": "subscribe", "session": name}))
            clients.append(ws)
        for ws in clients:
            while json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))["type"] != "frame":
                pass
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        for ws in clients:
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await asyncio.wait_for(ws.recv(), TIMEOUT)
        return time.monotonic() - t0

    try:
        took = asyncio.run(go())
        code = p.wait(TIMEOUT * 2)
    finally:
        if p.poll() is None:
            p.kill()
    assert took < TIMEOUT and code in (0, -signal.SIGTERM)
    err = p.stderr.read()
    assert "Traceback" not in err and "leaked" not in err, err


def test_no_url_is_printed_for_a_session_that_failed(tmp_path):
    """A session that fails at start (a clip of another size than the enrolment, a bad
    file) used to be announced with its URL all the same. Now: every session failed ->
    no URL, exit 2 and one line; some failed -> the URL of the others, the failed named."""
    rec, video = tmp_path / "in.jsonl", tmp_path / "in.avi"
    write_recording(rec, frames=40, fps=30)
    write_video(video)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ARTICAST_LOG_LEVEL": "error"}
    bad = "tests.service_helpers:RefusesVideo"
    run = subprocess.run([sys.executable, "-m", "articast.service.cli", "serve", "--source",
                          f"a=file:{video}", "--processor", bad, "--port", "0"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=20 * TIMEOUT)
    assert run.returncode == 2, run
    assert "ws://" not in run.stdout + run.stderr
    assert run.stderr.strip().splitlines()[-1] == ("articast serve: error: nothing to serve: a "
                                                   "failed (the reason is above)"), run.stderr
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "serve",
                          "--source", f"good=replay-record:{rec}?loop=yes",
                          "--source", f"bad=file:{video}",
                          "--processor", bad, "--port", "0", "--json"],
                         cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        line = json.loads(p.stdout.readline())
        assert line["sessions"] == ["good"] and list(line["failed"]) == ["bad"], line
        assert "session=good" in line["avatar"]
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(TIMEOUT)


def test_sigterm_to_the_whole_group_is_a_stop_not_a_crash(tmp_path):
    """systemd (and `kill -TERM -PGID`) signal every process of the service at once: the
    worker process died of SIGTERM and the server logged `session ... crashed: worker
    process exited with code -15` on its way out. A worker takes SIGTERM as a stop."""
    rec = tmp_path / "in.jsonl"
    write_recording(rec, frames=40, fps=30)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ARTICAST_LOG_LEVEL": "warning"}
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "serve", "--source",
                          f"a=replay-record:{rec}?loop=yes", "--worker", "process",
                          "--port", "0", "--json"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        url = json.loads(p.stdout.readline())["url"]
        asyncio.run(frames(url, "a", 3))
        os.killpg(p.pid, signal.SIGTERM)
        _, err = p.communicate(timeout=3 * TIMEOUT)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert "crashed" not in err and "code -15" not in err and "Traceback" not in err, err


@pytest.mark.parametrize("disposition", ["default", "ignored"])
def test_ctrl_c_ends_a_replay_with_one_line(tmp_path, disposition):
    """Issue 39: replay and replay-record printed nothing on Ctrl-C. From a terminal (SIGINT
    at its default) the server stops and says 'interrupted' (exit 130); where the shell had
    SIGINT ignored (a background job), the server still stops on it and says 'stopped'."""
    rec = tmp_path / "talk.jsonl"
    write_recording(rec, frames=60, fps=30)
    handler = signal.SIG_DFL if disposition == "default" else signal.SIG_IGN
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "replay-record",
                          str(rec), "--loop", "--port", "0", "--json"], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, handler))
    try:
        assert p.stdout.readline(), p.stderr.read()  # serving: the face streams
    finally:
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=TIMEOUT * 3)
    lines = [x for x in err.splitlines() if x.strip()]
    assert "Traceback" not in err
    word, code = ("interrupted", 130) if disposition == "default" else ("stopped", 0)
    assert p.returncode == code and lines[-1] == f"articast replay-record: {word}", err

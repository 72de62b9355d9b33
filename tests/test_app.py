"""The service end to end: a real uvicorn server on loopback and the real websockets client."""

import asyncio
import json
import time

import httpx
import numpy as np
import pytest
import websockets

from articast.client import protocol as P
from articast.service.app import ServiceConfig
from articast.service.capture import Capture
from articast.service.security import AccessPolicy
from articast.service.settings import CaptureSettings, HubSettings, ServerSettings, SessionPolicy
from articast.service.sources import make_source
from articast.service.worker import SessionSpec
from tests.service_helpers import (
    TIMEOUT,
    ImageStats,
    ServerThread,
    small_model,
    write_recording,
    write_video,
)

FPS = 60


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 6 * TIMEOUT))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "talk.jsonl"
    truth = write_recording(path, frames=120, fps=FPS)
    return path, truth


@pytest.fixture(scope="module")
def server(recording, tmp_path_factory):
    big = tmp_path_factory.mktemp("big") / "big.jsonl"
    write_recording(big, frames=60, fps=30, model=small_model(n=4000))
    record_dir = tmp_path_factory.mktemp("recorded")
    config = ServiceConfig(
        server=ServerSettings(record=str(record_dir), log_level="critical"),
        hub=HubSettings(max_queue=4, max_message_bytes=4096, ws_max_size=65536,
                        stall_timeout_s=60, max_messages_per_s=1000),
        capture=CaptureSettings(retry_initial_s=0.05, retry_max_s=0.2),
        policy=SessionPolicy(restart_initial_s=0.05, restart_max_s=0.2, max_restarts=3),
        sessions=(SessionSpec("rec", f"replay-record:{recording[0]}?loop=yes"),
                  SessionSpec("big", f"replay-record:{big}?loop=yes")),
        access=AccessPolicy(token="test-token",
                            media_roots=(str(tmp_path_factory.getbasetemp()),),
                            allowed_devices=("/dev/video97",)),
        http_processors=("auto", "truth", "tests.service_helpers:Crashy",
                         "tests.service_helpers:HardCrash",
                         "tests.service_helpers:ImageStats", "tests.service_helpers:Occludes"),
    )
    with ServerThread(config) as srv:
        srv.record_dir = record_dir
        yield srv


async def recv(ws, timeout=TIMEOUT):
    data = await asyncio.wait_for(ws.recv(), timeout)
    return json.loads(data) if isinstance(data, str) else data


async def subscribe(url, **msg):
    # close_timeout: a client that stopped reading cannot see the server's close reply behind
    # the frames it has not read, so the closing handshake would wait the default 10 s
    ws = await websockets.connect(url, open_timeout=TIMEOUT, max_size=2**24, close_timeout=1)
    await ws.send(json.dumps({"type": "subscribe", **msg}))
    return ws


async def until(ws, kind, skip=("status",), timeout=TIMEOUT):
    while True:
        m = await recv(ws, timeout)
        t = m["type"] if isinstance(m, dict) else "binary"
        if t == kind:
            return m
        assert t in skip, m


# ----------------------------------------------------------------------------- streaming
def test_hello_then_frames(server, recording):
    _, truth = recording

    async def go():
        async with await subscribe(server.url, session="rec",
                                   streams=["articulatory", "pose", "mesh"]) as ws:
            hello = P.Hello.model_validate(await until(ws, "hello"))
            assert hello.protocol == 1 and hello.param_names == list(small_model().param_names)
            g = hello.geometry
            assert g.n_points == 12 and len(g.mean) == 36 and len(g.basis) == 7 * 36
            assert len(g.triangles) % 3 == 0 and hello.camera["width"] == 64
            frames = [P.Frame.model_validate(await until(ws, "frame")) for _ in range(10)]
        seqs = [f.seq for f in frames]
        assert seqs == list(range(seqs[0], seqs[0] + 10))
        model = small_model()
        for f in frames:
            t = truth[f.frame % len(truth)]
            alpha = [f.values.articulatory[n] for n in hello.param_names]
            np.testing.assert_allclose(alpha, t.alpha)
            np.testing.assert_allclose(f.values.pose.translation, t.pose.translation)
            mesh = model.shape(np.array(alpha)).ravel()
            np.testing.assert_allclose(f.values.mesh, mesh, rtol=1e-4, atol=1e-3)
            assert f.t_capture <= f.t_tracked <= f.t_sent
            assert f.dropped == 0
    run(go())


def test_binary_encoding_and_rate(server):
    async def go():
        async with await subscribe(server.url, session="rec", encoding="binary", rate=20,
                                   streams=["articulatory", "pose"]) as ws:
            hello = P.Hello.model_validate(await until(ws, "hello"))
            assert hello.encoding == "binary"
            got = []
            while len(got) < 12:
                m = await recv(ws)
                if isinstance(m, bytes):
                    got.append(P.parse_server_message(m, {hello.sid: "rec"},
                                                      {hello.sid: hello.param_names}))
        assert all(f.session == "rec" and len(f.values.articulatory) == 7 for f in got)
        gaps = np.diff([f.frame for f in got])
        assert np.median(gaps) == 3  # 60 Hz source, 20 Hz asked: every third frame
    run(go())


def test_several_subscribers_get_the_same_frames(server):
    async def go():
        clients = [await subscribe(server.url, session="rec") for _ in range(5)]
        for ws in clients:
            await until(ws, "hello")
        firsts = [await until(ws, "frame") for ws in clients]
        start = max(f["seq"] for f in firsts) + 2
        seen = []
        for ws in clients:
            while True:
                f = await until(ws, "frame")
                if f["seq"] >= start:
                    break
            seen.append((f["seq"], f["values"]["articulatory"]))
            await ws.close()
        assert all(s == seen[0] for s in seen)
    run(go())


def test_a_stalled_subscriber_does_not_slow_the_others(server):
    async def go():
        # the stalled client asks for the heavy mesh stream (~200 kB a frame) and stops reading
        stalled = await websockets.connect(server.url, max_queue=1, max_size=2**24,
                                           close_timeout=1)
        await stalled.send(json.dumps({"type": "subscribe", "session": "big",
                                       "streams": ["mesh"]}))
        fast = await subscribe(server.url, session="big", streams=["articulatory"])
        # ~2 MB of geometry: frames queued meanwhile may drop (at load 13 it took > 10 s)
        await until(fast, "hello", timeout=6 * TIMEOUT)
        for _ in range(10):
            await until(fast, "frame")
        frames = [await until(fast, "frame")]
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            frames.append(await until(fast, "frame"))
        seqs = [f["seq"] for f in frames]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # nothing lost
        assert len({f["dropped"] for f in frames}) == 1  # no new drops (the count is cumulative)
        assert len(frames) >= 0.5 * 3.0 * 30  # it kept up with the 30 Hz source
        # the stalled one lost frames and is told so when it reads again
        dropped = 0
        t_end = time.monotonic() + TIMEOUT
        while not dropped and time.monotonic() < t_end:
            m = await recv(stalled)
            if m.get("type") == "frame":
                dropped = m["dropped"]
        assert dropped > 0
        await stalled.close()
        await fast.close()
    run(go())
    text = server.client().get("/metrics").text
    line = [x for x in text.splitlines()
            if x.startswith('articast_subscriber_dropped_total{session="big"}')][0]
    assert int(line.split()[-1]) > 0


def test_reconnect_gets_hello_again_and_newer_frames(server):
    async def go():
        async with await subscribe(server.url, session="rec") as ws:
            await until(ws, "hello")
            a = await until(ws, "frame")
        async with await subscribe(server.url, session="rec") as ws:
            await until(ws, "hello")
            b = await until(ws, "frame")
        assert b["seq"] > a["seq"]
    run(go())


# ----------------------------------------------------------------------------- bad input
def test_every_bad_ws_input_gets_an_error_and_the_connection_survives(server):
    async def go():
        async with websockets.connect(server.url, max_size=2**24) as ws:
            cases = [
                ("{nope", "bad_json"),
                ("[]", "bad_message"),
                ('{"type": "subscribe", "session": "nobody"}', "unknown_session"),
                ('{"type": "subscribe", "session": "rec", "streams": ["smell"]}',
                 "unknown_stream"),
                ('{"type": "subscribe", "session": "rec", "streams": ["fap"]}',
                 "unavailable_stream"),
                ('{"type": "unsubscribe", "session": "rec"}', "not_subscribed"),
                (json.dumps({"type": "subscribe", "session": "rec", "pad": "x" * 5000}),
                 "too_large"),
                (b"\x00\x01\x02binary garbage\xff", "binary_not_accepted"),
            ]
            for data, code in cases:
                await ws.send(data)
                m = P.Error.model_validate(await until(ws, "error"))
                assert m.code == code and m.reason and "Traceback" not in m.reason
            await ws.send(json.dumps({"type": "subscribe", "session": "rec"}))
            await until(ws, "hello")
            await until(ws, "frame")
    run(go())


def test_a_message_beyond_the_protocol_limit_closes_with_1009(server):
    async def go():
        async with websockets.connect(server.url, max_size=2**24) as ws:
            await ws.send("x" * 100_000)
            with pytest.raises(websockets.ConnectionClosed) as e:
                await recv(ws)
            assert e.value.rcvd.code == 1009
        async with websockets.connect(server.url) as ws:  # the server is fine
            await ws.send(json.dumps({"type": "subscribe", "session": "rec"}))
            await until(ws, "hello")
    run(go())


def test_http_errors_are_4xx_with_a_reason(server):
    c = server.client()
    cases = [
        c.post("/api/sessions", content=b"{not json", headers={"content-type":
                                                                "application/json"}),
        c.post("/api/sessions", json={"name": "x"}),
        c.post("/api/sessions", json={"name": "bad name!", "source": "file:a"}),
        c.post("/api/sessions", json={"name": "x", "source": "ftp:nothing"}),
        c.post("/api/sessions", json={"name": "x", "source": "file:/no/such.mp4"}),
        c.post("/api/sessions", json={"name": "x", "source": "replay-record:/etc/hostname",
                                      "processor": "os:system"}),
        c.post("/api/sessions", json={"name": "rec", "source": "synthetic:seed=1"}),
        c.post("/api/sessions", content=b"\xff" * 10_000,
               headers={"content-type": "application/json"}),
        c.post("/api/sessions", content=(b"x" * 1000 for _ in range(100)),  # chunked
               headers={"content-type": "application/json"}),
        c.delete("/api/sessions/nobody"),
        c.get("/api/nothing"),
    ]
    for r in cases:
        assert 400 <= r.status_code < 500, (r.status_code, r.text)
        assert "Traceback" not in r.text and r.json()["detail"]
    assert cases[6].status_code in (400, 409)
    assert "not allowed" in cases[5].json()["detail"]
    assert c.get("/healthz").json()["status"] == "ok"


def test_metrics_healthz_and_schema(server):
    c = server.client()
    text = c.get("/metrics").text
    for name in ("articast_fps", "articast_frames_total", "articast_send_latency_seconds_bucket",
                 "articast_residual_bucket", "articast_subscriber_dropped_total",
                 "articast_subscribers", "articast_source_dropped_total"):
        assert f'{name}{{session="rec"' in text
    health = c.get("/healthz").json()
    assert health["sessions"]["rec"] == "running"
    schema = c.get("/api/protocol").json()
    assert schema["protocol"] == 1 and "Hello" in json.dumps(schema)


# ----------------------------------------------------------------------------- sessions
def test_start_and_stop_a_session_at_run_time(server, recording):
    c = server.client()
    r = c.post("/api/sessions", json={"name": "late",
                                      "source": f"replay-record:{recording[0]}?loop=yes"})
    assert r.status_code == 201, r.text

    async def go():
        async with await subscribe(server.url, session="late") as ws:
            await until(ws, "hello")
            await until(ws, "frame")
            assert c.delete("/api/sessions/late").status_code == 200
            while True:
                m = await recv(ws)
                if m["type"] == "status" and m["state"] == "stopped":
                    break
    run(go())
    assert "late" not in [s["name"] for s in c.get("/api/sessions").json()]


def test_an_ended_source_tells_its_subscribers_and_loop_1_loops(server, tmp_path):
    """A file played once ends: its subscribers get `status: ended`, one subscribing after
    the end gets it too (not only hello.state), and the console says so; loop=1, serve
    --help's own example, plays past the end (it played once)."""
    import logging

    short = tmp_path / "short.jsonl"
    write_recording(short, frames=6, fps=30)
    c = server.client()
    for name, option in (("once", "loop=no&pace=fast"), ("looped", "loop=1&pace=fast")):
        r = c.post("/api/sessions", json={"name": name, "wait_for_subscriber": True,
                                          "source": f"replay-record:{short}?{option}"})
        assert r.status_code == 201, r.text
    messages = []
    handler = logging.Handler()
    handler.emit = lambda record: messages.append(record.getMessage())
    logging.getLogger("articast.session").addHandler(handler)

    async def go():
        async with await subscribe(server.url, session="once", queue=64) as ws:
            await until(ws, "hello")
            while True:
                m = await recv(ws)
                if m["type"] == "status" and m["state"] == "ended":
                    break
                assert m["type"] == "frame" or m["state"] in ("starting", "running"), m
        async with await subscribe(server.url, session="once") as late:
            await until(late, "hello", skip=())
            m = await recv(late)
            assert (m["type"], m["state"]) == ("status", "ended"), m
            assert "6 frames" in m["detail"]
        async with await subscribe(server.url, session="looped", queue=64) as ws:
            frames = [await until(ws, "frame", skip=("status", "hello")) for _ in range(15)]
            assert frames[-1]["frame"] >= 14  # 6 frames a play: it looped
    try:
        run(go())
    finally:
        logging.getLogger("articast.session").removeHandler(handler)
        for name in ("once", "looped"):
            c.delete(f"/api/sessions/{name}")
    assert "session once: ended: source ended after 6 frames" in messages, messages


def test_occluded_frames_reach_clients_flagged_with_the_last_good_state(server, recording):
    """What the docs say about `occluded` is what clients get: the frame is streamed, ok
    false, its reason starting `occluded`, the articulation and pose of the last good
    frame held (the tracker keeps fitting underneath)."""
    c = server.client()
    r = c.post("/api/sessions", json={"name": "hand", "processor": "tests.service_helpers:"
                                      "Occludes", "wait_for_subscriber": True,
                                      "source": f"replay-record:{recording[0]}?pace=fast"})
    assert r.status_code == 201, r.text

    async def go():
        async with await subscribe(server.url, session="hand", queue=64) as ws:
            return [await until(ws, "frame", skip=("status", "hello")) for _ in range(8)]
    try:
        frames = run(go())
    finally:
        c.delete("/api/sessions/hand")
    assert [f["seq"] for f in frames] == list(range(8))  # none left out
    flags = [(f["quality"]["ok"], f["quality"]["reason"].split(":")[0]) for f in frames]
    assert flags == [(True, "")] * 3 + [(False, "occluded")] * 3 + [(True, "")] * 2, flags
    for f in frames[3:6]:
        assert f["values"]["articulatory"] == frames[2]["values"]["articulatory"]
        assert f["values"]["pose"]["translation"] == frames[2]["values"]["pose"]["translation"]
    # and the words agree: neither the docs nor the tracker's own reason say "not streamed"
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for path in (root / "README.md", root / "docs" / "history" / "REAL_SPEAKERS_LOG.md",
                 root / "docs" / "SERVICE.md", root / "core" / "tracking" / "tracker.py"):
        assert "not streamed" not in path.read_text(), path


def test_a_crashing_session_is_restarted_and_the_server_survives(server, recording):
    c = server.client()
    r = c.post("/api/sessions", json={
        "name": "crashy", "source": f"replay-record:{recording[0]}?loop=yes",
        "processor": "tests.service_helpers:Crashy"})
    assert r.status_code == 201

    async def go():
        async with await subscribe(server.url, session="crashy") as ws:
            states = []
            while states.count("restarting") < 2:
                m = await recv(ws)
                if m["type"] == "status":
                    states.append(m["state"])
            assert "boom" in m["detail"]
    run(go())
    deadline = time.monotonic() + TIMEOUT
    while c.get("/api/sessions").json()[-1]["state"] != "failed":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    s = [s for s in c.get("/api/sessions").json() if s["name"] == "crashy"][0]
    assert s["restarts"] == 4 and "crashed" in s["detail"]
    assert c.get("/healthz").status_code == 200
    c.delete("/api/sessions/crashy")


def test_a_worker_process_that_dies_is_restarted(server, recording):
    c = server.client()
    assert c.post("/api/sessions", json={
        "name": "dies", "source": f"replay-record:{recording[0]}?loop=yes",
        "processor": "tests.service_helpers:HardCrash"}).status_code == 201

    async def go():
        async with await subscribe(server.url, session="dies") as ws:
            while True:  # (a worker's start may take longer than TIMEOUT on a loaded machine)
                m = await recv(ws, 6 * TIMEOUT)
                if m["type"] == "status" and m["state"] == "restarting":
                    return m["detail"]
    detail = run(go())
    assert "exited with code 3" in detail
    s = [s for s in c.get("/api/sessions").json() if s["name"] == "dies"][0]
    assert s["worker"] == "process"
    c.delete("/api/sessions/dies")


def test_corrupt_file_session_fails_once_with_a_clear_error(server, tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"garbage" * 1000)
    c = server.client()
    assert c.post("/api/sessions", json={"name": "corrupt", "source": f"file:{bad}",
                                         "processor": "truth"}).status_code == 201
    deadline = time.monotonic() + TIMEOUT
    while (s := [s for s in c.get("/api/sessions").json() if s["name"] == "corrupt"][0])[
            "state"] != "failed":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert "bad.mp4" in s["detail"] and s["restarts"] == 0
    c.delete("/api/sessions/corrupt")


def test_playback_is_not_read_before_its_first_frame_is_wanted(tmp_path):
    """Issue 39's first demo: the synthetic speaker rendered (~85 ms a frame) and dropped
    frames for the minute or two its tracker compiled, a core taken from the compilation.
    A playback source now waits for the consumer: its first frame is the clip's first, none
    dropped, however long the consumer took to ask (a camera is read from the start)."""
    video = tmp_path / "v.avi"
    write_video(video, frames=30, fps=25)
    cap = Capture(make_source(f"file:{video}")).start()  # pace=realtime
    try:
        assert cap.opened.wait(TIMEOUT) and cap.error is None
        time.sleep(0.5)  # a dozen frame periods: a capture reading ahead drops ~12 frames
        first = cap.get(TIMEOUT)
        assert first is not None and first.index == 0 and cap.dropped == 0, (
            first and first.index, cap.dropped)
        assert cap.get(TIMEOUT) is not None  # and it plays on
    finally:
        cap.stop()


def test_fast_file_replay_gives_the_offline_parameters(server, tmp_path):
    """A served file replay (pace=fast, worker process) equals processing the file offline."""
    video = tmp_path / "v.avi"
    write_video(video, frames=30, fps=25)
    uri = f"file:{video}?pace=fast"
    offline = []
    cap = Capture(make_source(uri)).start()
    proc = ImageStats(None)
    while not cap.done:
        f = cap.get(0.05)
        if f is not None:
            offline.append(proc.process(f))

    c = server.client()
    server.service.config  # noqa: B018 - the server is the module's
    r = c.post("/api/sessions", json={"name": "file", "source": uri, "wait_for_subscriber": True,
                                      "processor": "tests.service_helpers:ImageStats"})
    assert r.status_code == 201

    async def go():
        frames = []
        async with websockets.connect(server.url, max_queue=None) as ws:
            await ws.send(json.dumps({"type": "subscribe", "session": "file", "queue": 64}))
            while True:
                m = await recv(ws)
                if m["type"] == "frame":
                    frames.append(m)
                elif m["type"] == "status" and m["state"] in ("ended", "failed"):
                    assert m["state"] == "ended", m
                    return frames
    frames = run(go())
    assert [f["frame"] for f in frames] == list(range(30))
    assert all(f["dropped"] == 0 for f in frames)
    for f, o in zip(frames, offline, strict=True):
        assert [f["values"]["articulatory"][n] for n in small_model().param_names] == \
            [float(a) for a in o.alpha]
        assert f["t"] == pytest.approx(o.t)
    c.delete("/api/sessions/file")


def test_recording_round_trip(server, recording):
    recs = sorted(server.record_dir.glob("rec-*.jsonl"))
    assert recs
    lines = recs[0].read_text().splitlines()
    header = json.loads(lines[0])
    assert header["type"] == "header" and header["geometry"]["n_points"] == 12
    frames = [json.loads(x) for x in lines[1:]]
    assert [f["seq"] for f in frames] == list(range(len(frames)))
    _, truth = recording
    for f in frames[:20]:
        t = truth[f["frame"] % len(truth)]
        assert list(f["alpha"].values()) == pytest.approx(list(t.alpha))


def test_two_faces_never_share_a_gil(server):
    sessions = {s["name"]: s for s in server.client().get("/api/sessions").json()}
    kinds = [sessions[n]["worker"] for n in ("rec", "big")]
    assert sorted(kinds) == ["process", "thread"]  # one in the server, the other its own


def test_a_subscriber_stalled_past_the_timeout_is_disconnected(tmp_path):
    big = tmp_path / "big.jsonl"  # ~200 kB mesh frames: a socket fills within a second
    write_recording(big, frames=60, fps=30, model=small_model(n=4000))
    config = ServiceConfig(
        server=ServerSettings(log_level="critical"),
        hub=HubSettings(stall_timeout_s=0.5),
        sessions=(SessionSpec("big", f"replay-record:{big}?loop=yes"),),
        access=AccessPolicy(token="secret"),
    )

    async def go(srv):
        stalled = await websockets.connect(srv.url, max_queue=1, max_size=2**24,
                                           close_timeout=1)
        await stalled.send(json.dumps({"type": "subscribe", "session": "big",
                                       "streams": ["mesh"]}))
        # no 2 MB geometry in hello: its send alone could outlast a 0.5 s stall timeout
        healthy = await subscribe(srv.url, session="big", geometry=False)
        await until(healthy, "hello")
        deadline = time.monotonic() + TIMEOUT
        while len(srv.service.connections) > 1:  # the watchdog cuts the stalled one
            assert time.monotonic() < deadline
            await until(healthy, "frame")
        for _ in range(5):
            await until(healthy, "frame")  # and the healthy one goes on
        await healthy.close()
        stalled.transport.abort()

    with ServerThread(config) as srv:
        run(go(srv))
        c = httpx.Client(base_url=srv.http, timeout=TIMEOUT)
        bad = c.post("/api/sessions", json={"name": "x", "source": "file:/a"})
        assert bad.status_code == 401 and "Bearer" in bad.json()["detail"]
        wrong = c.delete("/api/sessions/big", headers={"Authorization": "Bearer secreT"})
        assert wrong.status_code == 401
        assert c.delete("/api/sessions/big").status_code == 401
        ok = c.delete("/api/sessions/big", headers={"Authorization": "Bearer secret"})
        assert ok.status_code == 200


def test_a_missing_camera_is_a_status_not_a_crash(server):
    c = server.client()
    assert c.post("/api/sessions", json={"name": "cam", "source": "v4l2:/dev/video97"}
                  ).status_code == 201

    async def go():
        async with await subscribe(server.url, session="cam") as ws:
            details = []
            while len(details) < 3:  # retried with backoff, reported each time
                m = await recv(ws)
                assert m["type"] == "status", m
                if m["state"] == "unavailable":
                    details.append(m["detail"])
        assert all("/dev/video97" in d for d in details)
    run(go())
    s = [s for s in c.get("/api/sessions").json() if s["name"] == "cam"][0]
    assert s["state"] == "unavailable" and "no such device" in s["detail"]
    assert c.delete("/api/sessions/cam").status_code == 200
    assert c.get("/healthz").json()["status"] == "ok"


def test_random_garbage_never_breaks_the_server(server):
    """200 seeded random messages (text, JSON-ish, binary); every one answered, server fine."""
    import random

    rng = random.Random(7)
    pieces = ['{"type":', '"subscribe"', '"session":', '"rec"', '"streams":', '[', ']', '{',
              '}', ',', '"rate":', '-1', '1e309', 'null', '"\\u0000"', '"mesh"', '9' * 40]

    def garbage():
        k = rng.random()
        if k < 0.3:
            return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))
        if k < 0.6:
            return "".join(rng.choice(pieces) for _ in range(rng.randrange(1, 12)))
        return "".join(chr(rng.randrange(32, 0x2FFF)) for _ in range(rng.randrange(0, 300)))

    async def go():
        async with websockets.connect(server.url, max_size=2**24, close_timeout=1) as ws:
            for _ in range(200):
                await ws.send(garbage())
                while True:  # each message gets an error, or (if valid) a hello: skip frames
                    m = await recv(ws)
                    if m["type"] in ("error", "hello"):
                        assert "Traceback" not in json.dumps(m)
                        break
            await ws.send(json.dumps({"type": "subscribe", "session": "rec"}))
            await until(ws, "hello", skip=("status", "frame"))
    run(go())
    assert httpx.get(server.http + "/healthz", timeout=TIMEOUT).json()["status"] == "ok"


def test_two_readers_are_asked_for_with_a_speaker_and_as_1_or_2(server):
    """``readers`` (core/faces/two_readers.py) tracks a speaker's face: asked for without a
    speaker it is a 400 saying so, anything but 1 or 2 is malformed (422); neither starts a
    session."""
    c = server.client()
    r = c.post("/api/sessions", json={"name": "two", "source": "synthetic:seed=1",
                                      "readers": 2})
    assert r.status_code == 400 and "needs a speaker" in r.json()["detail"], r.text
    for bad in (0, 3, "many"):
        r = c.post("/api/sessions", json={"name": "two", "source": "synthetic:seed=1",
                                          "readers": bad})
        assert r.status_code == 422, (bad, r.text)
    assert "two" not in [s["name"] for s in c.get("/api/sessions").json()]

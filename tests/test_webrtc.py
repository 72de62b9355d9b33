"""Browser ingest (issue 41, step 1): the join page in real headless Chromium sends a fake
camera (a .y4m clip of the synthetic speaker) over WebRTC; the server tracks it as a session
and streams it like any other; a malformed offer is a 400 in one line; without aiortc the
endpoint says why in one line (501)."""

import asyncio
import json
import sys
import time

import cv2
import numpy as np
import pytest

from articast.service.app import ServiceConfig
from articast.service.security import AccessPolicy
from articast.service.settings import ServerSettings
from articast.service.worker import SessionSpec
from tests.browser import CHROMIUM, Browser
from tests.service_helpers import TIMEOUT, ServerThread, collect

pytest.importorskip("aiortc", reason="WebRTC ingest needs aiortc (the test extra installs it)")

TOKEN = "join-token"
SEED = 1  # the synthetic speaker whose assets track a participant without a speaker folder
FAKE_MEDIA = ("--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream")


def write_y4m(path, frames, fps):
    """A YUV4MPEG2 file (what Chromium's fake camera reads): a header, then per frame
    ``FRAME`` and the I420 planes."""
    h, w = frames[0].shape[:2]
    with path.open("wb") as fh:
        fh.write(f"YUV4MPEG2 W{w} H{h} F{int(fps)}:1 Ip A1:1 C420jpeg\n".encode())
        for bgr in frames:
            fh.write(b"FRAME\n" + cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420).tobytes())
    return path


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """3 s of synthetic speaker SEED talking, at 30 fps, as .y4m; and its true apertures."""
    from articast.core.outputs.lips import lips_dict
    from articast.core.synthetic import open_stream
    from articast.service.sources import cache_dir

    stream = open_stream(seed=SEED, fps=30.0, cache_dir=cache_dir())
    frames, apertures = [], []
    for _, image, truth in stream.frames():
        frames.append(image)
        apertures.append(lips_dict(stream.model, truth.alpha)["aperture_mm"])
        if len(frames) == 90:
            break
    path = write_y4m(tmp_path_factory.mktemp("clip") / "speaker.y4m", frames, 30)
    return path, np.asarray(apertures)


def config(*sessions, token=TOKEN):
    return ServiceConfig(server=ServerSettings(), sessions=tuple(sessions),
                         access=AccessPolicy(token=token))


def join_url(srv, name, token=TOKEN):
    return f"{srv.http}/avatar/join.html?session={name}&token={token}"


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (.ci/run installs "
                    "Debian's chromium)")
def test_a_browser_camera_is_tracked_and_streamed_rejoins_and_leaving_ends_only_its_session(
        clip):
    path, true_aperture = clip
    flags = (*FAKE_MEDIA, f"--use-file-for-fake-video-capture={path}")
    other = SessionSpec("bystander", f"synthetic:seed={SEED}&fps=10&loop=yes",
                        processor="truth")
    with ServerThread(config(other)) as srv:
        with Browser(join_url(srv, "alice"), flags=flags, console=True) as b:
            # the tracker may compile its kernels first (a first run: 1-2 minutes)
            b.wait_for("window.articastJoin && window.articastJoin.ok >= 30", timeout=280)
            state = b.evaluate("JSON.stringify(window.articastJoin)")
            page = json.loads(state)
            assert page["connection"] == "connected", page
            # a subscriber of our own, over the WebSocket, sees the same session
            hello, frames = asyncio.run(collect(srv.url, "alice", ["articulatory"],
                                                until_end=False, n=60))
            assert hello["session"] == "alice"
            ok = [f for f in frames if f["quality"]["ok"] and f["lips"]]
            assert len(ok) >= 0.8 * len(frames), [f["quality"]["reason"] for f in frames]
            aperture = np.asarray([f["lips"]["aperture_mm"] for f in ok])
            # the lips move as the clip's do: the tracked range covers most of the true one
            assert np.ptp(aperture) > 0.5 * np.ptp(true_aperture), (aperture, true_aperture)
            info = srv.client().get("/api/sessions").json()
            alice = next(s for s in info if s["name"] == "alice")
            assert alice["source"]["kind"] == "webrtc"
            assert (alice["source"]["width"], alice["source"]["height"]) == (640, 480)
            assert not b.console_errors()
            # the media process dies mid-session: the page joins again by itself (no click)
            # and is tracked again; the bystander is not disturbed
            srv.service.media._proc.kill()
            b.wait_for("window.articastJoin.rejoined.length >= 1", timeout=6 * TIMEOUT)
            b.wait_for("window.articastJoin.ok >= window.articastJoin.rejoined[0].okBefore + 30"
                       " && window.articastJoin.connection === 'connected'", timeout=280)
            page = json.loads(b.evaluate("JSON.stringify(window.articastJoin)"))
            assert len(page["rejoined"]) == 1, page["rejoined"]  # one drop, one rejoin
            assert page["rejoined"][0]["delayMs"] == 2000, page["rejoined"]
            assert "ended" in page["rejoined"][0]["reason"] or "failed" in \
                page["rejoined"][0]["reason"], page["rejoined"]
            assert srv.service.manager.sessions["alice"].state == "running"
            assert srv.service.manager.sessions["bystander"].state == "running"
            bystander_frames = srv.service.manager.sessions["bystander"].metrics.frames
            b.evaluate("document.getElementById('leave').click()")
            deadline = time.monotonic() + 6 * TIMEOUT
            while srv.service.manager.sessions["alice"].state != "ended":
                assert time.monotonic() < deadline, srv.service.manager.sessions["alice"].state
                time.sleep(0.1)
            # joined again by hand, then removed by the operator: the page stays out
            b.evaluate("document.getElementById('join').click()")
            b.wait_for("window.articastJoin.status.startsWith('joined as alice')", timeout=280)
            assert srv.client().delete("/api/sessions/alice").status_code in (200, 204)
            b.wait_for("window.articastJoin.final.startsWith('session stopped')",
                       timeout=6 * TIMEOUT)
            # the page closes its side at once (left open, it fails ~30 s later, and a page
            # that took that for a drop joined again: the operator's removal undone)
            b.wait_for("window.articastJoin.connection === 'closed'", timeout=6 * TIMEOUT)
            time.sleep(5)  # longer than the first rejoin's delay
            page = json.loads(b.evaluate("JSON.stringify(window.articastJoin)"))
            assert len(page["rejoined"]) == 1 and "alice" not in srv.service.manager.sessions, \
                page
        assert srv.service.manager.sessions["bystander"].state == "running"
        deadline = time.monotonic() + TIMEOUT  # the bystander streams on
        while srv.service.manager.sessions["bystander"].metrics.frames <= bystander_frames:
            assert time.monotonic() < deadline
            time.sleep(0.1)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_the_page_says_when_the_camera_is_denied_or_the_token_refused(clip):
    path, _ = clip
    with ServerThread(config()) as srv:
        # no fake UI: headless Chromium denies the camera prompt
        with Browser(join_url(srv, "denied"), flags=("--use-fake-device-for-media-stream",
                                                     "--deny-permission-prompts")) as b:
            text = b.wait_for("window.articastJoin && window.articastJoin.final", timeout=20)
            assert text.startswith("the camera was denied"), text
        with Browser(join_url(srv, "refused", token="wrong"),
                     flags=(*FAKE_MEDIA, f"--use-file-for-fake-video-capture={path}")) as b:
            text = b.wait_for("window.articastJoin && window.articastJoin.final", timeout=20)
            assert text.startswith("the server refused this page's token"), text
        assert "denied" not in srv.service.manager.sessions
        assert "refused" not in srv.service.manager.sessions


@pytest.mark.parametrize("body, says", [
    (b"not json", "not JSON"),
    (b"[]", "JSON object"),
    (json.dumps({"type": "answer", "sdp": "v=0\r\n"}).encode(), 'type must be "offer"'),
    (json.dumps({"type": "offer", "sdp": 5}).encode(), "sdp must be"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\nthis is no offer\r\n"}).encode(),
     "the offer has no video track"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\nm=video x\r\n"}).encode(),
     "not a usable SDP offer"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\n"
                 "a=rtpmap:96 VP8/90000\r\n"}).encode(), "not a usable SDP offer: ICE"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\n", "camera": "x"}).encode(), "unknown field"),
])
def test_a_malformed_offer_is_a_400_in_one_line_and_starts_nothing(body, says):
    with ServerThread(config()) as srv:
        with srv.client() as c:
            r = c.post("/api/sessions/m/webrtc", content=body)
            assert r.status_code == 400, r.text
            detail = r.json()["detail"]
            assert says in detail and "\n" not in detail, detail
            assert c.get("/api/sessions").json() == []


def test_the_offer_needs_the_token():
    with ServerThread(config()) as srv:
        import httpx

        r = httpx.post(f"{srv.http}/api/sessions/m/webrtc", json={"type": "offer", "sdp": "v=0"})
        assert r.status_code == 401
    with ServerThread(config(token="")) as srv:
        r = httpx.post(f"{srv.http}/api/sessions/m/webrtc", json={"type": "offer", "sdp": "v=0"})
        assert r.status_code == 403 and "needs a token" in r.json()["detail"]


def test_without_aiortc_the_endpoint_says_why_in_one_line(monkeypatch):
    for name in [m for m in sys.modules if m == "aiortc" or m.startswith("aiortc.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "aiortc", None)  # import aiortc: ImportError
    with ServerThread(config()) as srv:
        with srv.client() as c:
            r = c.post("/api/sessions/m/webrtc", json={"type": "offer", "sdp": "v=0\r\n"})
            assert r.status_code == 501
            detail = r.json()["detail"]
            assert "pip install 'articast[webrtc]'" in detail and "\n" not in detail


def test_the_media_process_log_says_when_a_browser_stopped_answering_consent_checks():
    """aioice's INFO lines stay out of the server's log, except the one that says why a
    connection closed by itself (consent expired), raised to a WARNING."""
    import logging

    from articast.service.media import _ConsentExpiry

    keep = _ConsentExpiry()

    def record(level, msg):
        return logging.LogRecord("aioice.ice", level, __file__, 1, "%s " + msg,
                                 ("Connection(0)",), None)

    chatter = record(logging.INFO, "Check CandidatePair(...) State.WAITING -> State.SUCCEEDED")
    expired = record(logging.INFO, "Consent to send expired")
    problem = record(logging.WARNING, "Connection lost")
    assert not keep.filter(chatter)
    assert keep.filter(expired) and expired.levelname == "WARNING"
    assert keep.filter(problem)


def test_the_media_process_reads_a_ready_socket_s_datagrams_in_batches():
    """asyncio reads one datagram per socket per turn of its loop: a loop whose turns take
    a few ms (the media process's, with every participant's tasks) falls behind a socket that
    receives ~1000 datagrams a second until its buffer overflows, while the loop itself is
    never late (benchmarks/room_capacity.py: 2017 dropped in 30 s with 4 participants).
    With the media process's batched reads the same loop keeps up and loses none."""
    import socket
    import threading

    from articast.service.media import batch_datagram_reads

    def received_of(datagrams: int = 800) -> int:
        async def run() -> int:
            loop = asyncio.get_running_loop()
            got = [0]

            class Count(asyncio.DatagramProtocol):
                def datagram_received(self, data, addr):
                    got[0] += 1

            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)  # ~50 datagrams
            sock.bind(("127.0.0.1", 0))
            transport, _ = await loop.create_datagram_endpoint(Count, sock=sock)
            busy = True

            def turn():  # every turn of this loop takes ~3 ms (the participants' tasks)
                time.sleep(0.003)
                if busy:
                    loop.call_soon(turn)

            loop.call_soon(turn)

            def send():  # ~1000 datagrams a second, in bursts of 5
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
                    for i in range(datagrams):
                        out.sendto(b"x" * 1200, sock.getsockname())
                        if i % 5 == 4:
                            time.sleep(0.005)

            sender = threading.Thread(target=send)
            sender.start()
            while sender.is_alive():
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.2)
            busy = False
            transport.close()
            return got[0]

        return asyncio.run(run())

    from asyncio import selector_events

    cls = selector_events._SelectorDatagramTransport
    plain = cls._read_ready
    assert not getattr(plain, "batched", False), "batched reads leaked into this process"
    one_per_turn = received_of()
    original = batch_datagram_reads()
    try:
        batched = received_of()
    finally:
        cls._read_ready = original
    assert one_per_turn < 0.8 * 800, one_per_turn  # (the check that the test loads the loop)
    assert batched == 800, (batched, one_per_turn)

"""The meeting room past one machine (issue 41, item 5): two ``articast room`` servers on one
real ``redis-server`` serve one room. A participant who joins on server A over a real WebRTC
connection (aiortc as the page) is listed on B, and B's room socket receives their tracked
frames through Redis; their token publishes and reads as them only, on either server; when A
is killed (with its media process and workers), they leave B's list after the membership's
TTL. An enrolled member's delegate (their face) is served by the other server from Redis to the
room's participants only, and leaves Redis with them.

The members are tracked by a test processor that reads the image (``ImageStats``: the
channels' means) instead of the tracker, whose first start on a new checkout compiles kernels
for over a minute: what is tested is the room's path through Redis, not the tracker (the
two-browser test, tests/test_room.py, tracks for real)."""

import asyncio
import contextlib
import fractions
import json
import os
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
import websockets

from articast.service.remote import HEARTBEAT_S
from articast.service.room import participant_token
from tests.service_helpers import TIMEOUT, write_speaker
from tests.test_redis_scaleout import ROOT, Redis, pytestmark  # noqa: F401 - the skip

pytest.importorskip("aiortc", reason="the room needs aiortc (the test extra installs it)")

ROOM = "room-token-for-the-redis-test-0123"
TTL = 2.0
TONE = 440.0
"""ann's microphone: a sine of this many Hz."""


def room_server(redis_url, speakers, *more, skew=0.0):
    """``articast room`` on Redis in a process group of its own (a kill takes its media
    process and workers with it, as a machine going down would); ``skew``: its wall clock
    (and its children's) that many seconds off (the test-only ``ARTICAST_CLOCK_SKEW_S``,
    service/clock.py), as on a machine whose clock is wrong."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    env["ARTICAST_ROOM_TOKEN"] = ROOM
    if skew:
        env["ARTICAST_CLOCK_SKEW_S"] = repr(skew)
    return subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "room", "t", "--hub", redis_url,
         "--port", "0", "--json", "--member-ttl", str(TTL), "--speakers", str(speakers),
         "--processor", "tests.service_helpers:ImageStats", "--log-level", "warning",
         *more],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)


def base_url(p):
    line = p.stdout.readline()
    if not line:
        raise AssertionError(p.stderr.read())
    return json.loads(line)["url"].split("/room?")[0]


def stop(p):
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def tone_track(freq, pulse=None):
    """A microphone that says a sine of ``freq`` Hz: 20 ms frames of 48 kHz, in real time;
    ``pulse`` (on, of): the tone only in the first ``on`` frames of every ``of`` (the voice
    benchmark times its onsets)."""
    import av
    from aiortc.mediastreams import AudioStreamTrack

    class Tone(AudioStreamTrack):
        n = 0
        start = None

        async def recv(self):
            if self.start is None:
                self.start = time.monotonic()
            wait = self.start + self.n * 0.02 - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            t = (self.n * 960 + np.arange(960)) / 48000
            on = pulse is None or self.n % pulse[1] < pulse[0]
            pcm = (0.3 * 32767 * on * np.sin(2 * np.pi * freq * t)).astype(np.int16)
            frame = av.AudioFrame.from_ndarray(pcm.reshape(1, -1), format="s16", layout="mono")
            frame.sample_rate, frame.pts = 48000, self.n * 960
            frame.time_base = fractions.Fraction(1, 48000)
            self.n += 1
            return frame

    return Tone()


class Ear:
    """What a page's audio slot plays: its decoded frames (aiortc decodes them), each with
    when it came."""

    def __init__(self, track):
        self.frames = []
        self.task = asyncio.ensure_future(self._listen(track))

    async def _listen(self, track):
        from aiortc.mediastreams import MediaStreamError

        with contextlib.suppress(MediaStreamError, asyncio.CancelledError):
            while True:
                frame = await track.recv()
                pcm = frame.to_ndarray().reshape(-1, len(frame.layout.channels))[:, 0]
                self.frames.append((time.monotonic(), pcm.astype(np.float32) / 32768.0))

    def since(self, t):
        """The samples (channel 0, full scale 1) of the frames that came after ``t``."""
        parts = [pcm for at, pcm in self.frames if at > t]
        return np.concatenate(parts) if parts else np.zeros(0, np.float32)


def spectrum_peak(pcm, rate=48000):
    """The dominant frequency of ``pcm`` (Hz) and its RMS."""
    window = np.hanning(len(pcm))
    power = np.abs(np.fft.rfft(pcm * window)) ** 2
    power[0] = 0.0
    return np.argmax(power) * rate / len(pcm), float(np.sqrt(np.mean(pcm * pcm)))


class Page:
    """A participant's page, as far as the server can tell: aiortc sends a camera whose
    picture brightens and darkens (so the test processor's values move) and a microphone
    (silence, or a tone), with one receive-only audio slot."""

    def __init__(self, http, name, token="", tone=None, pulse=None, camera_first=False,
                 slots=1):
        self.http, self.name = http, name
        self.camera_first, self.n_slots = camera_first, slots
        """``camera_first``: a browser without a microphone offers its camera first (and no
        microphone), then its ``slots``."""
        self.pc = None
        self.token = token
        """An enrolled name's token comes from the host (the room token cannot take it)."""
        self.tone, self.pulse = tone, pulse
        self.slot = None
        """The receive-only audio transceiver (its ``mid`` is what the members list says)."""

    async def join(self):
        import av
        from aiortc import (
            RTCBundlePolicy,
            RTCConfiguration,
            RTCPeerConnection,
            RTCSessionDescription,
        )
        from aiortc.mediastreams import AudioStreamTrack, VideoStreamTrack

        class Camera(VideoStreamTrack):
            """10 frames a second (a real camera's 30 would cost the machine three times
            the encoding here and decoding there for nothing this test looks at)."""
            n = 0

            async def recv(self):
                await asyncio.sleep(0.1)
                Camera.n += 1
                img = np.full((240, 320, 3), 60 + 60 * (1 + np.sin(Camera.n / 3)), np.uint8)
                frame = av.VideoFrame.from_ndarray(img, format="bgr24")
                frame.pts, frame.time_base = Camera.n * 9000, fractions.Fraction(1, 90000)
                return frame

        async with httpx.AsyncClient(base_url=self.http, timeout=3 * TIMEOUT) as c:
            if not self.token:
                r = await c.post("/room/api/join", json={"name": self.name},
                                 headers={"X-Room-Token": ROOM})
                assert r.status_code == 200, r.text
                self.token = r.json()["token"]
                assert r.json()["max_fps"] == 15.0
            # as the page does: one transport for all, the microphone first (a browser's
            # stream lists its audio first), then the camera, then the slot. (The server's
            # aiortc, answering a camera first, would put the second audio m-line on a
            # transport the bundle then discards: that slot would never send.)
            self.pc = pc = RTCPeerConnection(RTCConfiguration(
                bundlePolicy=RTCBundlePolicy.MAX_BUNDLE))
            if not self.camera_first:
                pc.addTrack(tone_track(self.tone, self.pulse) if self.tone
                            else AudioStreamTrack())
            pc.addTrack(Camera())
            self.slots = [pc.addTransceiver("audio", direction="recvonly")
                          for _ in range(self.n_slots)]
            self.slot = self.slots[0]
            await pc.setLocalDescription(await pc.createOffer())
            r = await c.post("/room/api/offer", json={"type": "offer",
                                                      "sdp": pc.localDescription.sdp},
                             headers={"X-Participant-Token": self.token})
            assert r.status_code == 200, r.text
            await pc.setRemoteDescription(RTCSessionDescription(r.json()["sdp"], "answer"))

    def socket(self, http=None):
        ws = (http or self.http).replace("http://", "ws://")
        # every message is read as it comes (a short test: no bound), so that closing is
        # not held behind unread frames
        return websockets.connect(f"{ws}/room/ws?key={self.token}", max_size=2**24,
                                  max_queue=None, close_timeout=1)


async def until(ws, test, timeout):
    """The first message from ``ws`` for which ``test`` holds (AssertionError at timeout)."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        assert left > 0, "timed out"
        m = json.loads(await asyncio.wait_for(ws.recv(), left))
        if test(m):
            return m


def names(m):
    return {x["name"]: x for x in m["members"]} if m["type"] == "members" else None


async def delegate_keys(client, name):
    """The keys of ``name``'s delegate in the room's Redis (one per server sharing it)."""
    return [k async for k in client.scan_iter(f"articast:room:t:delegate:{name}:*")]


def stop_all(servers, redis, says):
    """Stop the room's servers, print their log lines for which ``says(line)`` holds (with
    the server's letter), then stop Redis (the benchmarks' teardown)."""
    for p in servers:
        stop(p)
    for name, p in zip("ABCDEFGH", servers):
        for line in p.stderr.read().splitlines():
            if says(line):
                print(f"log {name}:", line)
    redis.stop()


def test_a_member_on_one_server_is_seen_and_streamed_on_another_and_leaves_when_it_dies(
        tmp_path):
    """ann and bob are enrolled (speaker folders with a delegate, in the folder both servers
    share); ann joins on A, bob on B, whose bound on a shared delegate is below his."""
    t0 = time.monotonic()
    at, took = {}, {}
    redis = Redis()
    redis.start()
    write_speaker(tmp_path / "ann")
    write_speaker(tmp_path / "bob", seed=1)
    ann_token = participant_token(ROOM, "ann")  # as the host mints it (articast room-token)
    servers = [room_server(redis.url, tmp_path),
               room_server(redis.url, tmp_path, "--max-shared-delegate", "0.1")]
    try:
        a, b = (base_url(p) for p in servers)
        ann = Page(a, "ann", ann_token, tone=TONE)
        bob = Page(b, "bob", participant_token(ROOM, "bob"))

        async def go():
            import redis.asyncio as aioredis

            client = aioredis.from_url(redis.url)
            at["servers up"] = time.monotonic() - t0
            await asyncio.gather(ann.join(), bob.join())
            at["joined"] = time.monotonic() - t0
            ear = Ear(bob.slot.receiver.track)  # what bob's page plays
            async with bob.socket() as on_b, ann.socket() as on_a:
                # each server lists the other's member (from Redis), its own as itself
                m = await until(on_b, lambda m: "ann" in (names(m) or {}), 3 * TIMEOUT)
                assert names(m)["ann"]["remote"]
                assert names(m)["ann"]["delegate"] is True  # her face: the page loads it
                assert names(m)["bob"]["self"] and "remote" not in names(m)["bob"]
                await until(on_a, lambda m: "bob" in (names(m) or {}), 3 * TIMEOUT)
                # ann's frames, tracked on A, reach bob's page on B through Redis
                hello = await until(on_b, lambda m: m["type"] == "hello"
                                    and m["session"] == "ann", 3 * TIMEOUT)
                assert hello["param_names"]
                at["ann's hello on B"] = time.monotonic() - t0
                frames = []
                while len(frames) < 8:
                    frames.append(await until(on_b, lambda m: m["type"] == "frame"
                                              and m["session"] == "ann", 3 * TIMEOUT))
                first = [next(iter(f["values"]["articulatory"].values())) for f in frames]
                assert np.ptp(first) > 1.0, first  # her camera's picture, live
                # her voice, relayed by A's media process through Redis: B points bob's slot
                # at her, and his page plays her tone (its pitch, well above silence)
                m = await until(on_b, lambda m: names(m) is not None and "ann" in names(m)
                                and names(m)["ann"]["slot"] is not None, 3 * TIMEOUT)
                assert names(m)["ann"]["slot"] == bob.slot.mid
                t_slot = time.monotonic()
                deadline = t_slot + 3 * TIMEOUT
                while len(ear.since(t_slot)) < 48000 + 9600:  # 1 s after a 0.2 s start
                    assert time.monotonic() < deadline, \
                        f"bob's slot played {len(ear.since(t_slot))} samples of ann's voice"
                    await asyncio.sleep(0.1)
                at["ann's voice on B"] = time.monotonic() - t0
                heard = ear.since(t_slot)[-48000:]
                freq, rms = spectrum_peak(heard)
                assert abs(freq - TONE) <= 3.0 and rms > 0.05, (freq, rms)
                # and bob's page on B sees her speaking: the level A measured on her
                # microphone travels with her packets (silent bob's own reads 0)
                m = await until(on_b, lambda m: names(m) is not None and "ann" in names(m)
                                and names(m)["ann"]["level"] > 0.02, 3 * TIMEOUT)
                assert names(m)["bob"]["level"] < 0.01, names(m)
                assert hello["delegate_url"]  # (B's page asks B for it on this hello)
                # her delegate, shared by A through Redis: B serves it to a participant (bob)
                # as A serves it to her, byte for byte, never cached; nobody else gets it
                async with httpx.AsyncClient(timeout=TIMEOUT) as c:
                    t = time.monotonic()
                    on_b_delegate = await c.get(f"{b}/room/api/delegate/ann",
                                                headers={"X-Participant-Token": bob.token})
                    took["from B"] = time.monotonic() - t
                    assert on_b_delegate.status_code == 200, on_b_delegate.text
                    t = time.monotonic()
                    on_a_delegate = await c.get(f"{a}/room/api/delegate/ann",
                                                headers={"X-Participant-Token": ann.token})
                    took["from A"] = time.monotonic() - t
                    assert on_a_delegate.status_code == 200, on_a_delegate.text
                    assert on_b_delegate.content == on_a_delegate.content
                    assert json.loads(on_b_delegate.content)["texture"].startswith(
                        "data:image/png;base64,")
                    size = len(on_b_delegate.content)
                    for r in (on_b_delegate, on_a_delegate):
                        assert r.headers["cache-control"] == "no-store"
                        assert r.headers["content-type"] == "application/json"
                    forged = "bob." + ann.token.rpartition(".")[2]
                    for headers in ({}, {"X-Participant-Token": forged},
                                    {"X-Room-Token": ROOM}):
                        r = await c.get(f"{b}/room/api/delegate/ann", headers=headers)
                        assert r.status_code == 401, r.text
                        assert "texture" not in r.text
                    # one copy in Redis, A's, for a TTL renewed with her membership
                    keys = await delegate_keys(client, "ann")
                    assert len(keys) == 1 and 0 < await client.pttl(keys[0]) <= 1000 * TTL
                    assert await client.get(keys[0]) == on_a_delegate.content
                    # bob's delegate (~0.27 MB) is over B's bound (0.1 MB): B keeps it to
                    # itself, A's list says so (the page shows the generic head) and A has
                    # none to serve
                    await until(on_a, lambda m: names(m) is not None and "bob" in names(m)
                                and names(m)["bob"]["delegate"] is False, 3 * TIMEOUT)
                    assert await delegate_keys(client, "bob") == []
                    r = await c.get(f"{a}/room/api/delegate/bob",
                                    headers={"X-Participant-Token": ann.token})
                    assert r.status_code == 404, r.text
                    r = await c.get(f"{b}/room/api/delegate/bob",  # (his own server's)
                                    headers={"X-Participant-Token": ann.token})
                    assert r.status_code == 200, r.text
                # her token is hers on either server: on B it is no member's socket, and
                # neither it nor the room token takes her name there while she is on A
                async with ann.socket(b) as wrong:
                    m = json.loads(await asyncio.wait_for(wrong.recv(), TIMEOUT))
                    assert m["type"] == "error" and m["code"] == "not_joined"
                async with httpx.AsyncClient(base_url=b, timeout=TIMEOUT) as c:
                    r = await c.post("/room/api/join", json={"name": "ann"},
                                     headers={"X-Room-Token": ROOM})
                    assert r.status_code == 403, r.text  # (enrolled: never with it)
                    r = await c.post("/room/api/offer", json={"type": "offer",
                                                              "sdp": "v=0\r\n"},
                                     headers={"X-Participant-Token": ann.token})
                    assert r.status_code == 409 and "\n" not in r.json()["detail"], r.text
                    forged = "ann." + bob.token.rpartition(".")[2]
                    r = await c.post("/room/api/offer", json={"type": "offer",
                                                              "sdp": "v=0\r\n"},
                                     headers={"X-Participant-Token": forged})
                    assert r.status_code == 401
                    r = await c.post(f"{a}/room/api/offer", json={"type": "offer",
                                                                   "sdp": "v=0\r\n"},
                                     headers={"X-Participant-Token": bob.token})
                    assert r.status_code == 409, r.text  # bob, on B, is in the room on A
                # ann leaves (her page closes its socket on A): her delegate leaves Redis
                # with her entry, and B no longer has it
                await on_a.close()
                await until(on_b, lambda m: names(m) is not None and "ann" not in names(m),
                            3 * TIMEOUT)
                # and her voice stops on B (her page still sends it to A): after what the
                # jitter buffer held, bob's slot plays nothing, or silence
                await asyncio.sleep(1.0)
                t_left = time.monotonic()
                await asyncio.sleep(1.5)
                after = ear.since(t_left)
                assert not ear.task.done()  # (bob's slot still plays, nobody in it now)
                if len(after) >= 4800:
                    freq_after, rms_after = spectrum_peak(after)
                    assert rms_after < rms / 10, (freq_after, rms_after, rms)
                assert await delegate_keys(client, "ann") == []
                async with httpx.AsyncClient(timeout=TIMEOUT) as c:
                    r = await c.get(f"{b}/room/api/delegate/ann",
                                    headers={"X-Participant-Token": bob.token})
                    assert r.status_code == 404 and "texture" not in r.text, r.text
                await ann.pc.close()
                at["ann left"] = time.monotonic() - t0
                # she joins A again (her page would, with a new connection): bob's slot, freed
                # when she left, carries her again
                again = Page(a, "ann", ann_token, tone=TONE)
                await again.join()
                await until(on_b, lambda m: "ann" in (names(m) or {}), 3 * TIMEOUT)
                t_again = time.monotonic()
                deadline = t_again + 3 * TIMEOUT
                while len(ear.since(t_again)) < 48000 // 2:
                    assert time.monotonic() < deadline, \
                        f"bob's slot played {len(ear.since(t_again))} samples once ann was back"
                    await asyncio.sleep(0.1)
                freq_again, _ = spectrum_peak(ear.since(t_again)[-48000 // 2:])
                assert abs(freq_again - TONE) <= 4.0, freq_again
                await until(on_b, lambda m: m["type"] == "frame" and m["session"] == "ann",
                            3 * TIMEOUT)
                # wrong tokens count room-wide: an address that used its free ones on A
                # is slowed down on B at once; B still admits the right token from it, and
                # another address is not held
                def guesser(host):
                    return httpx.AsyncClient(timeout=3 * TIMEOUT, transport=httpx.
                                             AsyncHTTPTransport(local_address=host))

                wrong = {"X-Participant-Token": "bob." + "0" * 40}
                async with guesser("127.0.0.9") as g:
                    codes = [(await g.get(f"{a}/room/api/me", headers=wrong)).status_code
                             for _ in range(5)]
                    assert codes == [401] * 5, codes
                    r = await g.get(f"{b}/room/api/me", headers=wrong)
                    assert r.status_code == 429 and "answered after 1 s" in r.text, r.text
                    r = await g.get(f"{b}/room/api/me",
                                    headers={"X-Participant-Token": bob.token})
                    assert r.status_code == 200 and r.json()["name"] == "bob", r.text
                async with guesser("127.0.0.10") as g:
                    assert (await g.get(f"{b}/room/api/me", headers=wrong)).status_code == 401
                # server A dies (its media process and workers with it): ann leaves B's
                # room once her entry's TTL has run out
                at["A killed"] = time.monotonic() - t0
                os.killpg(servers[0].pid, signal.SIGKILL)
                t_kill = time.monotonic()
                await until(on_b, lambda m: names(m) is not None and "ann" not in names(m),
                            TTL + 3.0)
                gone = time.monotonic() - t_kill
                # (a killed server says no goodbye: her entry lapsed. No lower bound: on a
                # loaded machine A's last rewrite may have come late, her entry lapsing soon)
                assert servers[0].wait(TIMEOUT) == -signal.SIGKILL
                # and so does A's copy of her delegate (its TTL is her entry's), and B no
                # longer serves it
                deadline = time.monotonic() + 3 * TIMEOUT
                while await delegate_keys(client, "ann"):
                    assert time.monotonic() < deadline, "ann's delegate stayed in Redis"
                    await asyncio.sleep(0.1)
                async with httpx.AsyncClient(timeout=TIMEOUT) as c:
                    r = await c.get(f"{b}/room/api/delegate/ann",
                                    headers={"X-Participant-Token": bob.token})
                    assert r.status_code == 404, r.text
                # bob stays, and ann can join again on B
                await ann_again(on_b)
            ear.task.cancel()
            for p in (again, bob):
                await p.pc.close()
            await client.aclose()
            return gone, size, freq, rms, after

        async def ann_again(on_b):
            again = Page(b, "ann", ann_token)
            await again.join()
            await until(on_b, lambda m: names(m) is not None and "ann" in names(m)
                        and names(m)["ann"].get("remote") is None, 3 * TIMEOUT)
            await again.pc.close()

        gone, size, freq, rms, after = asyncio.run(asyncio.wait_for(go(), 12 * TIMEOUT))
        print(f"ann's {TONE:g} Hz tone heard on B at {freq:.1f} Hz, RMS {rms:.3f} "
              f"(after she left: {len(after)} samples, RMS "
              f"{spectrum_peak(after)[1] if len(after) else 0:.4f}); "
              f"ann left B's list {gone:.2f} s after A was killed (TTL {TTL:g} s); "
              f"her delegate ({size / 1e6:.2f} MB) served by B in {took['from B'] * 1e3:.0f} ms, "
              f"by A in {took['from A'] * 1e3:.0f} ms; "
              + ", ".join(f"{k} at {v:.1f} s" for k, v in at.items())
              + f"; the test took {time.monotonic() - t0:.1f} s")
        assert servers[1].poll() is None, servers[1].stderr.read()
        stop(servers[1])
        refused = [line for line in servers[1].stderr.read().splitlines()
                   if "bob's delegate is not shared" in line]
        assert len(refused) == 1 and "MB, over the 0.1 MB shared" in refused[0], refused
    finally:
        for p in servers:
            stop(p)
        redis.stop()


def test_the_membership_hash_gives_a_name_and_a_seat_once_and_forgets_a_silent_server():
    """service/room_presence.py against the real Redis: two servers' claims, the room's
    limit across them, a refresh, and an entry lapsing when its server goes quiet."""
    from articast.service.room_presence import Presence, Refused

    redis = Redis()
    redis.start()

    async def go():
        import redis.asyncio as aioredis

        client = aioredis.from_url(redis.url)
        a, b = (Presence(client, "test:room:t:members", s, 0.6) for s in ("A", "B"))
        assert await a.claim("ann", 1.0, False, 2) == 0
        with pytest.raises(Refused) as e:
            await b.claim("ann", 2.0, False, 2)
        assert e.value.status == 409
        assert await b.claim("bob", 2.0, True, 2) == 1
        with pytest.raises(Refused) as e:
            await b.claim("cy", 3.0, False, 2)
        assert e.value.status == 429 and "full (2" in e.value.detail
        live = await a.live()
        assert {n: (x["server"], x["slot"]) for n, x in live.items()} == {
            "ann": ("A", 0), "bob": ("B", 1)}
        for _ in range(3):  # A keeps ann; B goes quiet
            await asyncio.sleep(0.3)
            assert await a.refresh({"ann": {"joined": 1.0, "slot": 0}}) == []
        assert set(await a.live()) == {"ann"}
        assert await b.claim("cy", 3.0, False, 2) == 1  # bob's seat is free again
        await b.leave("ann")  # only its own server takes a member out
        await a.leave("ann")
        assert set(await b.live()) == {"cy"}
        # a name taken by another server while its holder was away: the holder is told
        assert await b.refresh({"cy": {"joined": 3.0, "slot": 1}}) == []
        assert await a.refresh({"cy": {"joined": 9.0, "slot": 0}}) == ["cy"]
        await client.aclose()

    try:
        asyncio.run(asyncio.wait_for(go(), 3 * TIMEOUT))
    finally:
        redis.stop()


@pytest.mark.parametrize("args, says", [
    (["--max-fps", "0"], "--max-fps: 1 to 60"),
    (["--member-ttl", "0.5"], "--member-ttl: 1 to 3600"),
    (["--max-shared-delegate", "0"], "--max-shared-delegate: 0.01 to 64 MB"),
    (["--hub", "http://x"], "expected redis://"),
    (["--remote-trackers"], "--remote-trackers needs --hub"),
    (["--tracker-wait", "0"], "--tracker-wait: 1 to 3600"),
])
def test_bad_room_options_are_one_line(args, says, capsys, tmp_path, monkeypatch):
    from articast.service.cli import main

    monkeypatch.setenv("ARTICAST_ROOM_TOKEN", ROOM)
    assert main(["room", "--port", "0", "--speakers", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err, err


@pytest.mark.parametrize("args, says", [
    ([], "--hub redis://HOST:PORT/DB is required"),
    (["--hub", "redis://127.0.0.1:1/0", "--lease", "0"], "--lease: 1 to 600"),
    (["--hub", "redis://127.0.0.1:1/0", "--max-members", "0"], "--max-members: 1 to 64"),
])
def test_bad_room_tracker_options_are_one_line(args, says, capsys, monkeypatch):
    from articast.service.cli import main

    monkeypatch.delenv("ARTICAST_HUB", raising=False)
    assert main(["room-tracker", "t", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err, err


def test_without_its_redis_an_offer_is_a_503_in_one_line_and_starts_nothing():
    """A room server whose Redis cannot be reached (never started here) answers an offer
    with one line and starts no session and no media process."""
    from articast.service.app import ServiceConfig
    from articast.service.room import RoomConfig
    from articast.service.security import AccessPolicy
    from tests.service_helpers import ServerThread
    from tests.test_redis_scaleout import free_port
    from tests.test_room import offer_sdp

    config = ServiceConfig(access=AccessPolicy(token="operator-token-for-the-tests-0123"),
                           hub_url=f"redis://127.0.0.1:{free_port()}/0",
                           room=RoomConfig(name="t", token=ROOM))
    sdp = offer_sdp()
    with ServerThread(config) as srv, httpx.Client(base_url=srv.http, timeout=TIMEOUT) as c:
        r = c.post("/room/api/join", json={"name": "ann"}, headers={"X-Room-Token": ROOM})
        assert r.status_code == 200, r.text
        r = c.post("/room/api/offer", json={"type": "offer", "sdp": sdp},
                   headers={"X-Participant-Token": r.json()["token"]})
        assert r.status_code == 503, r.text
        assert "Redis cannot be reached" in r.json()["detail"] and "\n" not in r.text
        assert not srv.service.manager.sessions and srv.service.media is None
        assert not srv.service.room.members


def test_a_page_that_offers_its_camera_first_hears_every_other_member(tmp_path):
    """A browser without a microphone offers its camera first, then its receive-only audio
    slots. Answered with aiortc's default (balanced) bundling, the second slot's m-line was
    put on the first slot's transport, which the BUNDLE then discarded: that slot never sent,
    and such a page heard one member only. Each slot must carry a voice: ann's 440 Hz and
    carl's 660 Hz. (One server; the room's script needs its Redis.)"""
    redis = Redis()
    redis.start()
    server = room_server(redis.url, tmp_path)
    try:
        url = base_url(server)
        ann, carl = Page(url, "ann", tone=440.0), Page(url, "carl", tone=660.0)
        bob = Page(url, "bob", camera_first=True, slots=2)

        async def go():
            await asyncio.gather(ann.join(), carl.join(), bob.join())
            ears = [Ear(s.receiver.track) for s in bob.slots]
            t = time.monotonic()
            heard = {}
            while len(heard) < 2 and time.monotonic() < t + 4 * TIMEOUT:
                await asyncio.sleep(0.25)
                for i, ear in enumerate(ears):
                    pcm = ear.since(t)
                    if len(pcm) >= 48000:
                        freq, rms = spectrum_peak(pcm[-24000:])
                        if rms > 0.05:
                            heard[i] = round(freq)
            for page in (ann, carl, bob):
                await page.pc.close()
            return heard, [len(e.since(t)) for e in ears]

        heard, samples = asyncio.run(asyncio.wait_for(go(), 8 * TIMEOUT))
        assert len(heard) == 2, f"bob's slots heard {heard} (samples per slot {samples})"
        assert sorted(heard.values()) == [440, 660], heard
    finally:
        stop(server)
        redis.stop()


# ----------------------------------------------------------------------------- remote trackers
def room_tracker(redis_url, speakers, lease=2.0, processor="ImageStats", skew=0.0):
    """``articast room-tracker t`` in a process group of its own (a kill takes its workers);
    ``skew``: as :func:`room_server`'s."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    if skew:
        env["ARTICAST_CLOCK_SKEW_S"] = repr(skew)
    return subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "room-tracker", "t", "--hub", redis_url,
         "--speakers", str(speakers), "--lease", str(lease), "--json",
         "--processor", f"tests.service_helpers:{processor}", "--log-level", "warning"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)


def descendants(pid):
    """The processes under ``pid`` (children, theirs, ...), as ``{pid: command line}``,
    multiprocessing's resource tracker left out."""
    parent = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                stat = open(f"/proc/{entry}/stat").read()
                parent[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    out, todo = {}, [pid]
    while todo:
        p = todo.pop()
        for child, par in parent.items():
            if par == p and child not in out:
                with contextlib.suppress(OSError):
                    out[child] = open(f"/proc/{child}/cmdline").read().replace("\0", " ")
                todo.append(child)
    return {p: c for p, c in out.items() if "resource_tracker" not in c}


def sessions_entry(client_redis_url, name):
    """The sessions hash's entry of ``name`` (who announced their session), or None."""
    import redis as sync_redis

    c = sync_redis.Redis.from_url(client_redis_url)
    try:
        raw = c.hget("articast:sessions", name)
        return json.loads(raw) if raw else None
    finally:
        c.close()


def test_a_room_tracker_on_redis_tracks_a_member_and_another_takes_over_when_it_dies(tmp_path):
    """A room server with --remote-trackers tracks nobody: ann's frames go to Redis, a room
    tracker (another process, as on another machine) tracks them and her page receives them;
    the server started no worker for her. A second tracker waits; the first is killed (with
    its workers): the second takes her within its lease and her frames come again, from it.
    With no tracker left, she is told in one line (her socket closes with the reason)."""
    lease, wait = 2.0, 6.0
    redis = Redis()
    redis.start()
    server = room_server(redis.url, tmp_path, "--remote-trackers", "--tracker-wait", str(wait))
    trackers = [room_tracker(redis.url, tmp_path, lease)]
    at = {}
    try:
        url = base_url(server)
        first = json.loads(trackers[0].stdout.readline() or "{}")
        assert first.get("pid") == trackers[0].pid, trackers[0].stderr.read()
        write_speaker(tmp_path / "ann")  # enrolled: her delegate, served by the server
        ann = Page(url, "ann", participant_token(ROOM, "ann"))

        def tracked_by(p):
            e = sessions_entry(redis.url, "ann")
            return e is not None and f":{p.pid}:" in e.get("run", "")

        async def frames(ws, n):
            got = []
            while len(got) < n:
                got.append(await until(ws, lambda m: m["type"] == "frame"
                                       and m["session"] == "ann", 3 * TIMEOUT))
            return [next(iter(f["values"]["articulatory"].values())) for f in got]

        async def go():
            await ann.join()
            async with ann.socket() as ws:
                t = time.monotonic()
                hello = await until(ws, lambda m: m["type"] == "hello"
                                    and m["session"] == "ann", 6 * TIMEOUT)
                at["hello"] = time.monotonic() - t
                assert hello["delegate_url"]  # (the page asks the server's room route)
                async with httpx.AsyncClient(timeout=TIMEOUT) as c:
                    r = await c.get(f"{url}/room/api/delegate/ann",
                                    headers={"X-Participant-Token": ann.token})
                    assert r.status_code == 200 and "texture" in r.text, r.text[:300]
                values = await frames(ws, 8)
                assert np.ptp(values) > 1.0, values  # her camera's picture, live, via JPEG
                # tracked by the tracker process: it announced her session (its pid in the
                # run), and the server has no worker: under it only its fork server and the
                # media process (forked from it; a local worker would be a third)
                assert tracked_by(trackers[0]), sessions_entry(redis.url, "ann")
                under = descendants(server.pid)
                assert len(under) == 2, under
                workers = descendants(trackers[0].pid)
                assert len(workers) >= 2, workers  # its fork server and her worker
                # a second tracker waits: she stays with the first while it lives
                trackers.append(room_tracker(redis.url, tmp_path, lease))
                trackers[1].stdout.readline()
                await asyncio.sleep(2 * lease)
                assert tracked_by(trackers[0]), sessions_entry(redis.url, "ann")
                await frames(ws, 3)
                # the first tracker dies with its workers: the second takes her over
                os.killpg(trackers[0].pid, signal.SIGKILL)
                t_kill = time.monotonic()
                await until(ws, lambda m: m["type"] == "hello" and m["session"] == "ann",
                            lease + 6 * TIMEOUT)
                values = await frames(ws, 8)
                at["takeover"] = time.monotonic() - t_kill
                # the sessions hash is rewritten each heartbeat (remote.HEARTBEAT_S): her frames
                # may come before the new tracker's first rewrite of it (on a machine twice as
                # fast, 8 frames took less than a beat and the entry still named the dead one)
                beat = time.monotonic() + 3 * HEARTBEAT_S
                while not tracked_by(trackers[1]) and time.monotonic() < beat:
                    await asyncio.sleep(0.05)
                assert tracked_by(trackers[1]), sessions_entry(redis.url, "ann")
                assert np.ptp(values) > 1.0, values
                assert len(descendants(server.pid)) == 2
                # no tracker left: she is told so, in one line, after --tracker-wait
                os.killpg(trackers[1].pid, signal.SIGKILL)
                t_kill = time.monotonic()
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:
                        await asyncio.wait_for(ws.recv(), wait + lease + 3 * TIMEOUT)
                at["told"] = time.monotonic() - t_kill
            await ann.pc.close()
            return closed.value

        closed = asyncio.run(asyncio.wait_for(go(), 20 * TIMEOUT))
        reason = closed.rcvd.reason if closed.rcvd else ""
        print(f"ann's hello after {at['hello']:.1f} s; taken over {at['takeover']:.1f} s after "
              f"the first tracker was killed (lease {lease:g} s); told {at['told']:.1f} s after "
              f"the last one was (wait {wait:g} s): {reason!r}")
        assert closed.rcvd is not None and closed.rcvd.code == 4001, closed
        assert "no room tracker took your video for 6 s" in reason, reason
        assert at["told"] >= wait - 1.0, at  # (not before the wait)
        assert server.poll() is None, server.stderr.read()
    finally:
        for p in (server, *trackers):
            stop(p)
        for who, p in (("server", server), ("tracker 1", trackers[0])):
            for text in p.stderr.read().splitlines():
                if "tracked by" in text or "let go" in text or "left" in text or "lapsed" in text or "held" in text \
                        or "tracking" in text:
                    print(f"{who}: {text}")
        redis.stop()


def test_a_member_whose_session_fails_on_the_room_tracker_is_told_why_and_can_join_again(
        tmp_path):
    """The tracker's session of ann fails (its processor refuses her video): her server tells
    her the reason in one line (her socket's close reason) and she leaves; the tracker does
    not start her again, and she can join again (failing again, told again)."""
    redis = Redis()
    redis.start()
    server = room_server(redis.url, tmp_path, "--remote-trackers")
    tracker = room_tracker(redis.url, tmp_path, processor="RefusesAll")
    try:
        url = base_url(server)
        tracker.stdout.readline()

        async def told():
            ann = Page(url, "ann")
            await ann.join()
            try:
                async with ann.socket() as ws:
                    with pytest.raises(websockets.ConnectionClosed) as closed:
                        while True:
                            await asyncio.wait_for(ws.recv(), 6 * TIMEOUT)
                return closed.value.rcvd
            finally:
                await ann.pc.close()

        for _ in range(2):
            rcvd = asyncio.run(asyncio.wait_for(told(), 12 * TIMEOUT))
            assert rcvd is not None and rcvd.code == 4001, rcvd
            assert "their tracker failed" in rcvd.reason and "refuses" in rcvd.reason, rcvd
        assert server.poll() is None and tracker.poll() is None
    finally:
        for p in (server, tracker):
            stop(p)
        redis.stop()


# ----------------------------------------------------------------------------- one clock
SKEW = 3.0
"""Server A's wall clock is this many seconds ahead (ARTICAST_CLOCK_SKEW_S: test-only)."""


def test_a_frame_captured_on_a_server_whose_clock_is_wrong_is_timed_right_on_another():
    """ann joins on A, whose wall clock is SKEW s ahead (as on a machine without NTP); bob on
    B (right). ann's frames reach ann's socket on A and bob's on B through Redis; each says
    when it was captured (``t_capture``) and when that server sent it (``t_sent``), and a page
    maps the first onto its own clock through the second (clients/web/room.js). For the same
    frame, ``t_sent - t_capture`` on B is what it is on A (the two servers send it within a
    few ms of each other): the capture time crossed in Redis's clock (service/clock.py).
    Without that, B's figure is off by A's skew (main's code: by -SKEW s)."""
    import tempfile

    redis = Redis()
    redis.start()
    with tempfile.TemporaryDirectory() as speakers:
        servers = [room_server(redis.url, speakers, skew=SKEW), room_server(redis.url, speakers)]
        try:
            a, b = (base_url(p) for p in servers)
            ann, bob = Page(a, "ann"), Page(b, "bob")
            lat = {"A": {}, "B": {}}

            async def read(ws, side, n):
                while len(lat[side]) < n:
                    f = await until(ws, lambda m: m["type"] == "frame" and m["session"] == "ann",
                                    3 * TIMEOUT)
                    lat[side][f["seq"]] = f["t_sent"] - f["t_capture"]

            async def go():
                await asyncio.gather(ann.join(), bob.join())
                async with ann.socket() as on_a, bob.socket() as on_b:
                    await asyncio.gather(read(on_a, "A", 40), read(on_b, "B", 40))
                await asyncio.gather(ann.pc.close(), bob.pc.close())

            asyncio.run(asyncio.wait_for(go(), 12 * TIMEOUT))
            # each server's /healthz says how far its clock is from Redis's
            health = [httpx.get(f"{u}/healthz", timeout=TIMEOUT).json()["clock"] for u in (a, b)]
            assert abs(health[0]["ahead_of_redis_ms"] - 1000 * SKEW) < 5.0, health
            assert abs(health[1]["ahead_of_redis_ms"]) < 5.0, health
            both = sorted(set(lat["A"]) & set(lat["B"]))
            assert len(both) >= 20, (len(lat["A"]), len(lat["B"]), len(both))
            d = np.array([lat["B"][k] - lat["A"][k] for k in both]) * 1000
            on_a = np.array([lat["A"][k] for k in both]) * 1000
            print(f"A {SKEW:+g} s: t_sent - t_capture of ann's {len(both)} frames on A: median "
                  f"{np.median(on_a):.1f} ms; on B minus on A: median {np.median(d):+.2f} ms, "
                  f"p5..p95 {np.percentile(d, 5):+.2f}..{np.percentile(d, 95):+.2f} ms")
            assert 0 < np.median(on_a) < 2000, on_a  # (one clock on A: exact)
            assert abs(np.median(d)) < 15.0, d
        finally:
            stop_all(servers, redis, lambda line: "clock" in line)


TRACKER_SKEW = -7.0
"""The room tracker's wall clock is this many seconds behind: more than a session entry may
age (remote.STALE_S) before its session is taken for unavailable."""


def test_a_room_tracker_whose_clock_is_wrong_times_a_member_s_frames_right():
    """A room server with --remote-trackers, and a room tracker whose wall clock is 7 s
    behind: ann's frames cross twice (to the tracker in her frame stream, back through the
    hub). On her page, the tracking took what it takes (``t_tracked - t_capture`` between 0
    and 1 s) and her frame left the server after it was captured (``t_sent - t_capture``), as
    with one clock; and her session is not taken for unavailable (its entries' time stamps
    are not 7 s old). Without Redis's clock (main's code) ``t_tracked - t_capture`` is off by
    the tracker's skew."""
    import tempfile

    redis = Redis()
    redis.start()
    with tempfile.TemporaryDirectory() as speakers:
        server = room_server(redis.url, speakers, "--remote-trackers")
        tracker = room_tracker(redis.url, speakers, skew=TRACKER_SKEW)
        try:
            url = base_url(server)
            tracker.stdout.readline()
            ann = Page(url, "ann")
            got, states = [], []

            async def go():
                await ann.join()
                async with ann.socket() as ws:
                    while len(got) < 30:
                        m = await until(ws, lambda m: m.get("session") == "ann"
                                        and m["type"] in ("frame", "status"), 6 * TIMEOUT)
                        if m["type"] == "status":
                            states.append(m["state"])
                        else:
                            got.append(m)
                await ann.pc.close()

            asyncio.run(asyncio.wait_for(go(), 12 * TIMEOUT))
            tracked = np.array([f["t_tracked"] - f["t_capture"] for f in got]) * 1000
            sent = np.array([f["t_sent"] - f["t_capture"] for f in got]) * 1000
            print(f"tracker {TRACKER_SKEW:+g} s: t_tracked - t_capture median "
                  f"{np.median(tracked):.1f} ms ({np.min(tracked):.1f}..{np.max(tracked):.1f}), "
                  f"t_sent - t_capture median {np.median(sent):.1f} ms; statuses {states}")
            assert 0 < np.median(tracked) < 1000, tracked
            assert np.median(tracked) < np.median(sent) < 2000, (tracked, sent)
            assert "unavailable" not in states, states
        finally:
            stop_all([server, tracker], redis, lambda line: "clock" in line)


def test_a_membership_s_frame_stream_key_is_the_same_on_the_server_and_the_tracker():
    """The server names a member's frame stream from its own join time; the tracker from the
    membership hash, whose numbers Redis's Lua (cjson) rewrites with 14 significant digits:
    the same key either way, and another key for the same name joining again (a tracker of
    the new membership never reads the former one's ``end``)."""
    from articast.service.room_frames import frames_key

    joined = 1764481234.567890123
    rewritten = float(f"{joined:.14g}")  # (as cjson writes it back)
    assert rewritten != joined
    assert frames_key("p:", "r", "ann", joined) == frames_key("p:", "r", "ann", rewritten)
    assert frames_key("p:", "r", "ann", joined) != frames_key("p:", "r", "ann", joined + 0.01)

"""The meeting room (issue 41): two participants in real headless Chromium, each with a fake
camera and microphone fed from a clip of the synthetic speaker, see each other's delegate move
with the other's clip; a participant who closes their page leaves everyone's scene and can
join again. Access (room and participant tokens) and bad offers are checked over HTTP with a
real WebRTC client (aiortc)."""

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
import wave

import numpy as np
import pytest

from articast.service.app import ServiceConfig
from articast.service.security import AccessPolicy
from tests.browser import CHROMIUM, Browser
from tests.service_helpers import TIMEOUT, ServerThread
from tests.test_webrtc import write_y4m

pytest.importorskip("aiortc", reason="the room needs aiortc (the test extra installs it)")

from articast.service.room import RoomConfig, participant_token  # noqa: E402

SEED = 1
ROOM = "room-token-for-the-tests-0123"
OPERATOR = "operator-token-for-the-tests-0123"
FPS = 30
SLOW = 5
"""The clips' speech plays at 1/SLOW of its speed (rendered at SLOW * FPS, played at FPS).
The test maps a streamed frame to a clip frame by its media time, and Chromium's fake camera
does not keep time: under load its frames are 1-2 frames (p95 3-4) from where their media
time puts them, drifting 6-10 frames in 20 s (benchmarks/fake_camera.py). Errors of 2 frames
(s.d.) alone cap r for a perfect tracker at ~0.6 at full speed, ~0.92 at a third of it (where
runs gave 0.884-0.966) and ~0.97 at a fifth. The drift (1-2 % here) is searched for: see
:data:`RATES`."""
ENROLLED_FILES = ("model.npz", "appearance.npz", "camera.json", "speaker.json",
                  "points_v1.npz", "points_v2.npz", "delegate.npz", "room-key")
"""A speaker folder the room's enrolment writes (no contact sheet, no clip; room-key: the
secret its participant's token is bound to)."""
ENROLLED_SEED = 4
"""The synthetic speaker bob shows when he comes back and enrols through the page (a desk
webcam's view; test_enroll.py enrols the same speaker from a file)."""
FAKE = ("--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream",
        "--autoplay-policy=no-user-gesture-required")


def config(speakers="", max_participants=8):
    return ServiceConfig(access=AccessPolicy(token=OPERATOR),
                         room=RoomConfig(name="t", token=ROOM, speakers=speakers,
                                         max_participants=max_participants))


def write_wav(path, envelope, fps, rate=48000):
    """A voice for the fake microphone: a 180 Hz buzz whose loudness follows ``envelope`` (one
    value per video frame), so the sound and the lips move together."""
    n = int(len(envelope) / fps * rate)
    t = np.arange(n) / rate
    env = np.interp(t, np.arange(len(envelope)) / fps, envelope)
    buzz = np.sign(np.sin(2 * np.pi * 180 * t)) * 0.3 + np.sin(2 * np.pi * 360 * t) * 0.2
    pcm = (np.clip(buzz * env, -1, 1) * 32000).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate)
        w.writeframes(pcm.tobytes())
    return path


def make_clip(folder, seed, start, n=90, slow=1, rig="head"):
    """n frames of synthetic speaker ``seed`` (from frame ``start``: two participants say
    different things) as .y4m and a .wav, the speech ``slow`` times slower than life; the
    speaker's assets as files for `articast track`. ``rig`` desk: a webcam's view, to enrol
    from (the room tracks the others with the synthetic speaker's head-rig assets)."""
    from articast.core.outputs.lips import lips_dict
    from articast.core.synthetic import open_stream
    from articast.service.sources import cache_dir

    stream = open_stream(seed=seed, fps=float(FPS * slow), rig=rig, cache_dir=cache_dir())
    frames, apertures = [], []
    for _, image, truth in stream.frames(start):
        frames.append(image)
        apertures.append(lips_dict(stream.model, truth.alpha)["aperture_mm"])
        if len(frames) == n:
            break
    folder.mkdir(parents=True, exist_ok=True)
    y4m = write_y4m(folder / "clip.y4m", frames, FPS)
    a = np.asarray(apertures)
    wav = write_wav(folder / "voice.wav", (a - a.min()) / max(np.ptp(a), 1e-6), FPS)
    stream.model.save(folder / "model.npz")
    stream.appearance.save(folder / "appearance.npz")
    stream.camera.save(folder / "camera.json")
    pose = stream.initial_pose
    init = ",".join(f"{v:.9g}" for v in (*pose.rotation, *pose.translation))
    return {"y4m": y4m, "wav": wav, "truth": a, "folder": folder, "init": init,
            "rig": getattr(stream, "rig", "head")}


def track_causal(clip, speaker=None):
    """Start `articast track --causal` on the clip with the speaker's assets (or an enrolled
    speaker folder); the returned function waits for it and gives the per-frame lip
    apertures (nan where not ok)."""
    out = clip["folder"] / ("track-enrolled.jsonl" if speaker else "track.jsonl")
    f = clip["folder"]
    assets = ["--speaker", str(speaker)] if speaker else [
        "--model", str(f / "model.npz"), "--appearance", str(f / "appearance.npz"),
        "--camera", str(f / "camera.json"), "--init-pose", clip["init"], "--rig", clip["rig"]]
    proc = subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "track", str(clip["y4m"]), *assets,
         "--causal", "--quiet", "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    # the reference runs beside the room under test, below its priority (it needs only to
    # finish: at equal priority it starved the media process on a loaded 2-core machine)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, proc.pid, 10)

    def result():
        _, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err.decode(errors="replace")
        rows = [json.loads(line) for line in out.read_text().splitlines()]
        return np.asarray([r["lips"]["aperture_mm"] if r["quality"]["ok"] and r.get("lips")
                           else np.nan for r in rows])
    return result


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    base = tmp_path_factory.mktemp("room")
    out = {}
    waiting = {}
    out["ann"] = make_clip(base / "ann", SEED, 0, n=90 * SLOW, slow=SLOW)
    waiting["ann"] = track_causal(out["ann"])  # (side by side with the next clip's render)
    # bob's webcam, from which he enrols: another synthetic speaker, seen from a desk
    t0 = time.monotonic()
    out["bob-desk"] = make_clip(base / "bob-desk", ENROLLED_SEED, 900, n=90 * SLOW, slow=SLOW,
                                rig="desk")
    print(f"bob's desk clip rendered in {time.monotonic() - t0:.1f} s")
    for name, result in waiting.items():
        out[name]["offline"] = result()
    return out


def room_url(srv, name, enrol=False):
    return f"{srv.http}/room?room={ROOM}&name={name}&fps=15" + ("&enrol=1" if enrol else "")


def participant(srv, name, clip, enrol=False):
    flags = (*FAKE, f"--use-file-for-fake-video-capture={clip['y4m']}",
             f"--use-file-for-fake-audio-capture={clip['wav']}", "--window-size=800,600")
    return Browser(room_url(srv, name, enrol), flags=flags, console=True)


RATES = 1.0 + 0.01 * np.arange(-5, 6)
"""The fake camera's clock against the media time: Chromium's file-backed fake camera steps
through the clip one frame per capture tick, and a starved capture thread ticks late (at load
5-7 ann's clip read r 0.885 at the nominal rate where bob's, on the same pages, read 0.975):
the clip's frame is taken as ``t * fps * rate`` with the best rate within 5 %."""


def best_correlation(received, offline, fps=FPS, rates=RATES):
    """The correlation of the apertures a page received for a member (media time t, aperture)
    with the clip's offline track, at the best circular shift (the camera loops the clip and
    started before the connection, so which clip frame came first is not known) and the best
    of :data:`RATES`; ``((r, shift, rate), n)``."""
    rows = [(t, a) for t, a, *_ in received if a is not None]
    t = np.asarray([r[0] for r in rows])
    a = np.asarray([r[1] for r in rows])
    n = len(offline)
    best = (-1.0, 0, 1.0)
    for rate in rates:
        frame = np.round(t * fps * rate).astype(int)
        for shift in range(n):
            ref = offline[(frame + shift) % n]
            ok = ~np.isnan(ref)
            if ok.sum() < 20 or np.std(a[ok]) == 0 or np.std(ref[ok]) == 0:
                continue
            r = float(np.corrcoef(a[ok], ref[ok])[0, 1])
            best = max(best, (r, shift, float(rate)))
    return best, len(rows)


def members(b):
    return set(json.loads(b.evaluate("JSON.stringify(Object.keys(window.articastRoom.members))")))


def room_of(srv):
    return srv.server.config.loaded_app.app.state.room


STEADY = ("(() => {{ const m = window.articastRoom.members[{0}];"
          " if (!m || m.received.filter(r => r[1] !== null).length < {1} || !m.applied.length"
          " || !(m.audioDelayMs > 0) || !window.articastRoom.maxFramerate) return null;"
          " return JSON.stringify({{received: m.received, hook: {{audioDelayMs: m.audioDelayMs,"
          " method: m.delayMethod, jitterMs: m.jitterMs, jitterTarget: m.jitterTarget,"
          " arrival: m.arrival, drawn: m.drawn, applied: m.applied.length,"
          " received: m.received.length}}, maxFramerate: window.articastRoom.maxFramerate,"
          " rejoined: window.articastRoom.rejoined.length}}); }})()")
"""A member's stream on a page once it has ``n`` frames with an aperture, frames applied and
its voice's delay measured, read at one moment (under load a connection may drop and the page
join again by itself: then the member's counts start again)."""


def wait_until(predicate, timeout):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "still false"
        time.sleep(0.1)


def steady(page, name, n, timeout):
    return json.loads(page.wait_for(STEADY.format(json.dumps(name), n), timeout=timeout))


ENOUGH = ("(() => {{ const m = window.articastRoom.members[{0}];"
          " return m && m.received.filter(r => r[1] !== null).length >= {1}; }})()")


@pytest.mark.timeout(1500)  # never killed mid-way (its browsers would outlive it)
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_two_participants_see_each_other_move_and_leaving_and_rejoining_work(clips, tmp_path):
    """bob enrols through the guided page first (his browser records 24 s of his webcam, the
    server enrols him: the real enrolment, alone on the machine), then ann joins with the
    generic head: each page shows the other's delegate moving with the other's clip (r >=
    0.9 against ``articast track --causal``; ann sees bob's own textured delegate) and plays
    the other's voice. bob's delete on the page removes his folder and takes him out of
    ann's scene, ending only his session; he comes back (a new page) and ann sees him move
    again."""
    ann, desk = clips["ann"], clips["bob-desk"]
    assert np.nanstd(ann["offline"]) > 0.5
    speakers = tmp_path / "speakers"
    speakers.mkdir()
    from urllib.parse import parse_qs

    with ServerThread(config(speakers=str(speakers))) as srv, contextlib.ExitStack() as stack:
        sessions = srv.service.manager.sessions
        t0 = time.monotonic()
        b = stack.enter_context(participant(srv, "bob", desk, enrol=True))
        b.wait_for("window.articastRoom.enrol.state === 'running'", timeout=120)
        t_recorded = time.monotonic()
        b.wait_for("!['starting', 'countdown', 'recording', 'uploading', 'running']"
                   ".includes(window.articastRoom.enrol.state)", timeout=600)
        t_enrolled = time.monotonic()
        enrolment = json.loads(b.evaluate("JSON.stringify(window.articastRoom.enrol)"))
        print(f"bob's enrolment: recorded and sent in {t_recorded - t0:.1f} s, "
              f"enrolled in {t_enrolled - t_recorded:.1f} s: {enrolment}")
        assert enrolment["state"] == "done", enrolment
        assert enrolment["type"].startswith("video/webm") and \
            enrolment["bytes"] > 1_000_000, enrolment
        folder = speakers / "bob"
        assert sorted(os.listdir(folder)) == sorted(ENROLLED_FILES), os.listdir(folder)
        assert not (speakers / ".enrolling").exists() or \
            not os.listdir(speakers / ".enrolling")  # the clip is not kept
        assert os.stat(folder).st_mode & 0o777 == 0o700
        # (its result: waited for below; from a copy of his folder: he deletes his enrolment
        # before the reference, which runs below the room's priority, may have read it)
        reference = tmp_path / "bob-reference"
        shutil.copytree(folder, reference)
        desk["offline"] = track_causal(desk, speaker=reference)
        # his page joins with his own token (an enrolled name's), tracked as himself
        b.wait_for("window.articastRoom.joined", timeout=120)
        a = stack.enter_context(participant(srv, "ann", ann))
        # each page: both delegates, the other's frames flowing (the tracker may compile
        # its kernels on a first run: minutes)
        # (what each page received and did with the other's stream is read at one moment:
        # the apertures are scored below, once the offline track of bob's clip has ended;
        # meanwhile he leaves and comes back)
        seen = {"bob": steady(a, "bob", 45, 420)}
        print(f"ann's page had bob's 45 frames {time.monotonic() - t_enrolled:.1f} s after "
              "his enrolment")
        seen["ann"] = steady(b, "ann", 45, 300)
        a.wait_for("window.articastRoom.members.bob.drawn === 'delegate'", timeout=60)
        wait_until(lambda: members(a) == members(b) == {"ann", "bob"}, 6 * TIMEOUT)
        # each page sends no more frames than the room's cap (max_fps, 15): the media
        # process decodes every frame it receives
        for name, other in (("ann", "bob"), ("bob", "ann")):  # (name's page saw other)
            assert seen[other]["maxFramerate"] == 15
            wait_until(lambda n=name: n in room_of(srv).members and
                       room_of(srv).members[n].feed is not None, 6 * TIMEOUT)
            m = room_of(srv).members[name]
            rate = m.feed.received / (time.time() - m.joined)
            print(f"{name}'s video: {m.feed.received} frames received, {rate:.1f} a second")
            assert rate <= 15 * 1.15, rate
        assert os.path.samefile(sessions["bob"].spec.speaker, folder)
        # his page's address is his own link now, a token bound to his folder's secret: the
        # token anyone could take for "bob" before no longer admits
        secret = (folder / "room-key").read_text().strip()
        assert os.stat(folder / "room-key").st_mode & 0o777 == 0o600
        query = parse_qs(b.evaluate("location.search").lstrip("?"))
        assert query == {"key": [participant_token(ROOM, "bob", secret)]}, query
        with http(srv) as c:
            h = {"X-Participant-Token": participant_token(ROOM, "bob")}
            assert c.get("/room/api/me", headers=h).status_code == 401
            assert c.delete("/room/api/enrol/bob", headers=h).status_code == 401
        got = {name: seen[name]["received"] for name in seen}
        for other, mine, drawn in (("bob", "ann", "delegate"), ("ann", "bob", "generic")):
            h = seen[other]["hook"]
            print(f"{other}'s voice on {mine}'s page: {h}; that page had rejoined "
                  f"{seen[other]['rejoined']} times")
            assert h["drawn"] == drawn and h["applied"] > 0, h
            # the other's voice plays on this page: its delay was measured from the jitter
            # buffer's played samples (how long it is depends on the load: the page holds
            # the voice as long as the animation is late)
            assert h["audioDelayMs"] is not None and h["audioDelayMs"] > 0, h
        assert not a.console_errors(), a.console_errors()
        # he deletes his enrolment on the page: the folder goes, he leaves ann's scene (his
        # face is no longer shown) and his session ends; ann's goes on
        b.evaluate("document.getElementById('forget').click()")
        a.wait_for("!('bob' in window.articastRoom.members) && "
                   "window.articastRoom.left.includes('bob')", timeout=6 * TIMEOUT)
        assert not folder.exists()
        assert not b.console_errors(), b.console_errors()
        b.close()
        deadline = time.monotonic() + 6 * TIMEOUT
        while sessions["bob"].state != "ended":
            assert time.monotonic() < deadline, sessions["bob"].state
            time.sleep(0.1)
        wait_until(lambda: sessions.get("ann") is not None and
                   sessions["ann"].state == "running", 6 * TIMEOUT)  # (or rejoined: again)
        # bob joins again (a new page, on another camera: the generic head's clip): ann
        # sees him move again
        with participant(srv, "bob", ann) as b2:
            a.wait_for(ENOUGH.format(json.dumps("bob"), 10), timeout=120)
            wait_until(lambda: members(b2) == {"ann", "bob"}, 6 * TIMEOUT)
            # the media process dies mid-meeting: both connections drop, both pages say so
            # and join again by themselves; ann sees bob move again
            before = {p: len(p.evaluate("window.articastRoom.rejoined")) for p in (a, b2)}
            srv.service.media._proc.kill()
            for page in (a, b2):
                page.wait_for(f"window.articastRoom.rejoined.length > {before[page]}",
                              timeout=6 * TIMEOUT)
            t_drop = time.monotonic()
            a.wait_for(ENOUGH.format(json.dumps("bob"), 10), timeout=180)
            b2.wait_for(ENOUGH.format(json.dumps("ann"), 10), timeout=60)
            print(f"after the media process was killed, ann saw bob again in "
                  f"{time.monotonic() - t_drop:.1f} s; rejoins: "
                  f"{a.evaluate('window.articastRoom.rejoined')}")
            assert "dropped" in a.evaluate("window.articastRoom.rejoined")[-1]["reason"]
            wait_until(lambda: members(a) == members(b2) == {"ann", "bob"}, 6 * TIMEOUT)
        t_wait = time.monotonic()
        desk["offline"] = desk["offline"]()
        print(f"the offline track of bob's clip ended {time.monotonic() - t_wait:.1f} s after "
              "he came back")
        for other, mine in (("bob", "ann"), ("ann", "bob")):
            theirs, own = (desk, ann) if other == "bob" else (ann, desk)
            (r, shift, rate), n = best_correlation(got[other], theirs["offline"])
            nominal = best_correlation(got[other], theirs["offline"], rates=(1.0,))[0][0]
            print(f"{other} on {mine}'s page: r {r:.3f} over {n} frames with an aperture "
                  f"(of {len(got[other])}), the camera's clock at {rate:.2f} (at 1.00: r "
                  f"{nominal:.3f})")
            assert r >= 0.9, (other, r, shift, rate, n)
            # the other's clip, not any moving mouth: this page's own clip fits worse
            (r_wrong, _, _), _ = best_correlation(got[other], own["offline"])
            assert r_wrong < r, (other, r, r_wrong)
        a.close()
        deadline = time.monotonic() + 6 * TIMEOUT
        while room_of(srv).members:
            assert time.monotonic() < deadline, list(room_of(srv).members)
            time.sleep(0.2)


# ----------------------------------------------------------------------------- access
def offer_sdp():
    """A real WebRTC offer (aiortc's client: a camera of blank frames and a microphone),
    as a page's; the connection itself is not made."""
    from aiortc import RTCPeerConnection
    from aiortc.mediastreams import AudioStreamTrack, VideoStreamTrack

    async def make():
        pc = RTCPeerConnection()
        pc.addTrack(VideoStreamTrack())
        pc.addTrack(AudioStreamTrack())
        pc.addTransceiver("audio", direction="recvonly")
        await pc.setLocalDescription(await pc.createOffer())
        sdp = pc.localDescription.sdp
        await pc.close()
        return sdp

    return asyncio.run(make())


def http(srv):
    import httpx

    return httpx.Client(base_url=srv.http, timeout=TIMEOUT)


def join(c, name, room=ROOM):
    return c.post("/room/api/join", json={"name": name}, headers={"X-Room-Token": room})


def offer(c, token, sdp):
    return c.post("/room/api/offer", json={"type": "offer", "sdp": sdp},
                  headers={"X-Participant-Token": token})


def test_joining_needs_the_room_token_and_a_token_publishes_only_as_its_participant():
    sdp = offer_sdp()
    with ServerThread(config()) as srv, http(srv) as c:
        assert join(c, "ann", room="").status_code == 401
        assert join(c, "ann", room=ROOM + "x").status_code == 401
        r = join(c, "ann")
        assert r.status_code == 200, r.text
        ann = r.json()["token"]
        assert ann == participant_token(ROOM, "ann") and r.json()["slots"] == 7
        bob = join(c, "bob").json()["token"]
        # bob's token publishes as bob, whatever the page says: the name is the token's
        r = c.post("/room/api/offer", json={"type": "offer", "sdp": sdp, "session": "ann"},
                   headers={"X-Participant-Token": bob})
        assert r.status_code == 400 and "unknown field" in r.json()["detail"]
        r = offer(c, bob, sdp)
        assert r.status_code == 200, r.text
        assert r.json()["name"] == "bob" and len(r.json()["slots"]) == 1
        sessions = srv.service.manager.sessions
        assert "bob" in sessions and "ann" not in sessions
        # a token for ann made up by bob (his own MAC, ann's name) is refused
        forged = "ann." + bob.rpartition(".")[2]
        assert offer(c, forged, sdp).status_code == 401
        assert offer(c, "", sdp).status_code == 401
        assert "ann" not in sessions
        # nobody publishes into a session that has its participant: bob cannot again
        assert offer(c, bob, sdp).status_code == 409
        # the room's tokens open nothing of the operator's: no session API, no /ws (each a
        # wrong token to the server: past its free ones, 429 after a wait, still refused)
        refused = (401, 429)
        for token in (ROOM, bob):
            h = {"Authorization": f"Bearer {token}"}
            assert c.get("/api/sessions", headers=h).status_code in refused
            assert c.delete("/api/sessions/bob", headers=h).status_code in refused
            assert c.post("/api/sessions/ann/webrtc", headers=h,
                          json={"type": "offer", "sdp": sdp}).status_code in refused
        assert sessions["bob"].state not in ("stopped",)
        # the room socket takes participant tokens only
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect

        for key in ("", ROOM, forged):
            with pytest.raises(InvalidStatus) as e:
                connect(f"ws://127.0.0.1:{srv.port}/room/ws?key={key}", open_timeout=TIMEOUT)
            assert e.value.response.status_code == 401
        # ann's delegate (she has none: not a member) is not served to a wrong token
        assert c.get("/room/api/delegate/bob",
                     headers={"X-Participant-Token": forged}).status_code == 401


def test_wrong_tokens_from_one_address_are_slowed_down():
    with ServerThread(config()) as srv, http(srv) as c:
        codes = [join(c, "ann", room="wrong-room-token-000") for _ in range(7)]
        assert [r.status_code for r in codes[:5]] == [401] * 5
        # past the free ones each wrong token is answered late (1 s, then 2 s), with 429
        assert [r.status_code for r in codes[5:]] == [429, 429]
        assert "answered after 2 s" in codes[-1].json()["detail"]
        r = join(c, "ann")  # the right token is never held (clients behind one NAT)
        assert r.status_code == 200 and r.json()["name"] == "ann"


def test_an_enrolled_name_needs_the_hosts_token(tmp_path):
    (tmp_path / "cleo").mkdir()
    (tmp_path / "cleo" / "speaker.json").write_text("{}")
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        r = join(c, "cleo")
        assert r.status_code == 403 and "articast room-token" in r.json()["detail"]
        assert join(c, "dan").status_code == 200
    # the host's command mints the token the server accepts
    out = subprocess.run([sys.executable, "-m", "articast.service.cli", "room-token", "cleo"],
                         capture_output=True, text=True, env={"ARTICAST_ROOM_TOKEN": ROOM,
                                                              "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == participant_token(ROOM, "cleo")
    out = subprocess.run([sys.executable, "-m", "articast.service.cli", "room-token", "cleo"],
                         capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 2 and "no room token" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("body, says", [
    (b"not json", "not JSON"),
    (json.dumps({"type": "answer", "sdp": "v=0\r\n"}).encode(), 'type must be "offer"'),
    (json.dumps({"type": "offer", "sdp": 5}).encode(), "sdp must be"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\nm=video x\r\n"}).encode(),
     "not a usable SDP offer"),
    (json.dumps({"type": "offer", "sdp": "v=0\r\nthis is no offer\r\n"}).encode(),
     "the offer has no video track"),
])
def test_a_malformed_offer_is_one_line_and_the_name_stays_free(body, says):
    with ServerThread(config()) as srv, http(srv) as c:
        token = join(c, "ann").json()["token"]
        r = c.post("/room/api/offer", content=body, headers={"X-Participant-Token": token})
        assert r.status_code == 400, r.text
        detail = r.json()["detail"]
        assert says in detail and "\n" not in detail, detail
        assert not room_of(srv).members and not srv.service.manager.sessions
        assert join(c, "ann").status_code == 200  # the name is free: joining again works


def test_a_killed_media_process_ends_its_participants_and_joining_again_works():
    """The participants' connections live in the media process (service/media.py): when it
    dies, its participants leave (their sessions end, the room forgets them) and the server
    stays up; the next offer starts a new media process."""
    sdp = offer_sdp()
    with ServerThread(config()) as srv, http(srv) as c:
        bob = join(c, "bob").json()["token"]
        r = offer(c, bob, sdp)
        assert r.status_code == 200, r.text
        media = srv.service.media
        first = media._proc
        assert first.is_alive() and "bob" in room_of(srv).members
        first.kill()
        deadline = time.monotonic() + 6 * TIMEOUT
        while "bob" in room_of(srv).members:
            assert time.monotonic() < deadline, "bob stayed in the room"
            time.sleep(0.1)
        sessions = srv.service.manager.sessions
        while sessions["bob"].state not in ("ended", "failed", "stopped"):
            assert time.monotonic() < deadline, sessions["bob"].state
            time.sleep(0.1)
        r = offer(c, bob, sdp)  # bob joins again: a new media process answers
        assert r.status_code == 200, r.text
        assert media._proc is not first and media._proc.is_alive()
        assert room_of(srv).members["bob"].feed.ended == ""

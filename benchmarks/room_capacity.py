"""How many participants this machine's room holds at 25 fps (issue 41), with light clients.

    python benchmarks/room_capacity.py [--participants 1,2,4,6,8] [--seconds 30] [--json]

benchmarks/room.py runs each participant as a real headless Chromium (a fake camera, software
WebGL, VP8 encoding): with 4 of them the browsers took the machine and the server was never
measured. Here each participant is a Python aiortc client that joins the way the room page
does (``/room/api/join`` with the room token, its offer to ``/room/api/offer`` with the
participant token: its microphone, its camera, then ``slots`` receive-only audio slots; the
room socket ``/room/ws?key=``), but costs almost nothing:

- its camera sends a pre-encoded VP8 clip (640x480, 30 fps, a keyframe each second) of the
  synthetic speaker the tests use, packet by packet, never re-encoded (each participant starts
  at another keyframe of the loop), and its microphone pre-encoded Opus (a 180 Hz buzz that
  follows the lips), made once and cached (``--cache``);
- the audio the room sends to its slots is counted, never decoded;
- it reads the room socket as a page does: every member's ``frame`` messages, each with
  ``t_capture`` (when the server received the video frame).

The server runs in this process (a fresh one per N, its trackers real: the synthetic
speaker's assets), the N clients in one child process (so their CPU is not the server's).
After the warm-up (every client receives frames of every member, or ``--timeout`` passed:
then ``before_measuring`` says who was short), for ``--seconds``:

- ``delivered_fps``: per member, the frames of theirs a client received a second (the median
  over the other clients; with one participant, their own page);
- ``latency_ms``: capture (the server receiving the video frame) to **receipt on the client's
  socket** (not a rendered screen: a page adds its drawing and its wait for the voice),
  p50/p95 over every pair, and its part up to the tracker's result (``tracked_ms``);
- ``rtp``: video and audio RTP packets the server's receivers counted and lost, per
  participant (read every 5 s: approximate), and connections that dropped (a closed room
  socket, a failed peer; ``workers_ended``: members whose worker was gone by the end);
- ``media_udp_drops`` / ``clients_udp_drops``: datagrams the kernel dropped on the media
  process's / the clients' UDP sockets (``/proc/net/udp``, the sockets open at both ends),
  and ``media_loop_late_ms`` / ``clients_loop_late_ms``: how late each loop ran a 0.1 s timer
  at worst; ``received_fps`` / ``replaced_fps``: video frames the media process decoded, and
  those replaced before a worker took them; ``slot_packets_per_s``: the voices each client
  received;
- CPU in cores (``/proc``): this process (the server's loop and its sockets), the media
  process (WebRTC, VP8 decoding, the audio relay), each worker (the tracker), the clients;
- ``cpu_x_v1``: per participant, CPU per tracked frame (their worker, plus 1/N of the server
  and of the media process) over the FaceMesh v1 loop's (benchmarks/room.py
  ``v1_loop_cpu_ms``, one thread, the same clip's frames);
- ``capacity``: the largest N at which every member is delivered at >= ``--target`` fps
  (25, or the clip's rate if lower).

The load (``load_1min``, start and end) includes this benchmark's own processes. Results and
what they mean: docs/ROOM.md, "Capacity with light clients".

``--trackers local,remote`` measures each N twice in one run, both on one ``redis-server``
started here (``--hub``): ``local``, the server's own workers track (their results through
Redis, as with any hub); ``remote``, the server runs with ``--remote-trackers`` and one
``articast room-tracker`` process tracks every member from their frames in Redis
(service/room_frames.py): the difference is the frames' hop through Redis (JPEG encoding in
the media process, the stream, decoding in the tracker's worker). Then ``tracker`` gives the
tracker process's CPU (it and its workers), ``server_cores_per_participant`` the server's
(its loop and the media process, plus its workers when they track here), ``redis`` the bytes
a second into Redis and the JPEG frames' size and rate (docs/ROOM.md, "Trackers on other
machines").
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

ROOM_TOKEN = "room-token-for-the-capacity-bench-0"
OPERATOR = "operator-token-for-the-capacity-bench"
FPS = 30
SLOW = 5
"""The speech at a fifth of its speed (as the room's tests and benchmarks/room.py)."""
GOP = 30


def missing() -> str:
    """Why this benchmark cannot run here ("" when it can)."""
    for mod, extra in (("aiortc", "webrtc"), ("av", "webrtc"), ("websockets", "test"),
                       ("httpx", "test")):
        try:
            __import__(mod)
        except ImportError as exc:
            return (f"benchmarks/room_capacity.py needs {mod} ({exc}): "
                    f"pip install 'articast[{extra}]'")
    return ""


# ----------------------------------------------------------------------------- the clip
def make_media(cache: Path, frames: int = 450, bitrate: int = 1_200_000) -> Path:
    """The participants' camera and microphone, encoded once: ``speaker.webm`` (VP8 640x480
    at FPS, a keyframe every GOP frames; Opus 48 kHz mono, 20 ms packets) and the frames as
    ``frames.npy`` (for the v1 loop's reference)."""
    out = cache / "speaker.webm"
    if out.exists() and (cache / "frames.npy").exists():
        return out
    import av
    import numpy as np

    from articast.core.outputs.lips import lips_dict
    from articast.core.synthetic import open_stream
    from articast.service.sources import cache_dir

    cache.mkdir(parents=True, exist_ok=True)
    stream = open_stream(seed=1, fps=float(FPS * SLOW), cache_dir=cache_dir())
    images, apertures = [], []
    for _, image, truth in stream.frames(0):
        images.append(image)
        apertures.append(lips_dict(stream.model, truth.alpha)["aperture_mm"])
        if len(images) == frames:
            break
    a = np.asarray(apertures)
    envelope = (a - a.min()) / max(float(np.ptp(a)), 1e-6)
    rate = 48000
    t = np.arange(int(len(images) / FPS * rate)) / rate
    env = np.interp(t, np.arange(len(envelope)) / FPS, envelope)
    buzz = np.sign(np.sin(2 * np.pi * 180 * t)) * 0.3 + np.sin(2 * np.pi * 360 * t) * 0.2
    pcm = (np.clip(buzz * env, -1, 1) * 32000).astype(np.int16)

    tmp = out.with_suffix(".tmp.webm")
    with av.open(str(tmp), "w", format="webm") as box:
        vs = box.add_stream("libvpx", rate=FPS)
        h, w = images[0].shape[:2]
        vs.width, vs.height, vs.pix_fmt, vs.bit_rate = w, h, "yuv420p", bitrate
        vs.codec_context.gop_size = GOP
        vs.codec_context.options = {"deadline": "good", "g": str(GOP), "keyint_min": str(GOP)}
        aus = box.add_stream("libopus", rate=rate)
        aus.layout = "mono"
        for i, img in enumerate(images):
            frame = av.VideoFrame.from_ndarray(img, format="bgr24")
            frame.pts, frame.time_base = i, Fraction(1, FPS)
            for p in vs.encode(frame):
                box.mux(p)
        for p in vs.encode():
            box.mux(p)
        for k in range(len(pcm) // 960):
            af = av.AudioFrame.from_ndarray(pcm[k * 960:(k + 1) * 960].reshape(1, -1),
                                            format="s16", layout="mono")
            af.sample_rate, af.pts, af.time_base = rate, k * 960, Fraction(1, rate)
            for p in aus.encode(af):
                box.mux(p)
        for p in aus.encode():
            box.mux(p)
    tmp.rename(out)
    np.save(cache / "frames.npy", np.stack(images))
    return out


def read_packets(path: Path) -> tuple[list[tuple[bytes, bool]], list[bytes]]:
    """The clip's VP8 packets (data, keyframe) and Opus packets, in order."""
    import av

    video: list[tuple[bytes, bool]] = []
    audio: list[bytes] = []
    with av.open(str(path)) as box:
        for p in box.demux():
            if not p.size:
                continue
            if p.stream.type == "video":
                video.append((bytes(p), bool(p.is_keyframe)))
            elif p.stream.type == "audio":
                audio.append(bytes(p))
    return video, audio


# ----------------------------------------------------------------------------- the clients
def _looped_track(kind: str, packets: list[bytes], period: float, step: int, clock: int,
                  start: int) -> Any:
    """A track that sends ``packets`` (encoded) in a loop, one each ``period`` s, from index
    ``start``, with RTP-clock timestamps ``step`` apart (never re-encoded: aiortc's sender
    packs an ``av.Packet`` as it is)."""
    import av
    from aiortc.mediastreams import MediaStreamTrack

    class Looped(MediaStreamTrack):
        def __init__(self) -> None:
            super().__init__()
            self.kind = kind
            self.n = 0
            self.t0: float | None = None

        async def recv(self) -> Any:
            if self.t0 is None:
                self.t0 = time.monotonic()
            wait = self.t0 + self.n * period - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            p = av.Packet(packets[(start + self.n) % len(packets)])
            p.pts, p.time_base = self.n * step, Fraction(1, clock)
            self.n += 1
            return p

    return Looped()


def udp_sockets(pc: Any) -> list[Any]:
    """The UDP sockets a peer connection's ICE gathered (aiortc 1.16, aioice: none found
    in another version)."""
    out, seen = [], set()
    for t in pc.getTransceivers():
        try:
            connection = t.receiver.transport.transport.iceGatherer._connection
            protocols = list(connection._protocols)
        except AttributeError:
            continue
        for p in protocols:
            transport = getattr(p, "transport", None)
            sock = transport.get_extra_info("socket") if transport is not None else None
            if sock is not None and sock.fileno() not in seen:
                seen.add(sock.fileno())
                out.append(sock)
    return out


def grow_receive_buffers(pc: Any, size: int) -> list[int]:
    """Each of the peer's UDP sockets asks for ``size`` bytes of receive buffer (Linux grants
    twice that, up to twice ``net.core.rmem_max``): the sizes granted."""
    import socket

    granted = []
    for sock in udp_sockets(pc):
        try:
            if sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) < size:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
            granted.append(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        except OSError as exc:  # (a socket closing meanwhile): the default then
            print(f"SO_RCVBUF: {exc!r}", file=sys.stderr)
    return granted


class _Counter:
    """In place of a receiver's queue to its decoder: packets counted, not decoded (the end,
    None, still reaches the decoder thread so that it stops)."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.packets = inner, 0

    def put(self, item: Any) -> None:
        if item is None:
            self.inner.put(None)
        else:
            self.packets += 1

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


class Client:
    """One participant, as the room page is to the server."""

    def __init__(self, http: str, name: str, media: tuple[Any, Any], index: int,
                 buffers: int = 0) -> None:
        self.http, self.name, self.media, self.index = http, name, media, index
        self.buffers = buffers
        self.pc: Any = None
        self.token = ""
        self.ws: Any = None
        self.frames: list[tuple[str, float, float, float]] = []
        """(member, received, t_capture, t_tracked) while measuring."""
        self.seen: dict[str, int] = {}
        self.measuring = False
        self.dropped: list[str] = []
        self.counters: list[_Counter] = []
        self.reader: asyncio.Task[None] | None = None

    async def join(self) -> None:
        import httpx
        import websockets
        from aiortc import (
            RTCBundlePolicy,
            RTCConfiguration,
            RTCPeerConnection,
            RTCRtpSender,
            RTCSessionDescription,
        )

        video, audio = self.media
        keys = [i for i, (_, key) in enumerate(video) if key]
        start = keys[(2 * self.index) % len(keys)]
        async with httpx.AsyncClient(base_url=self.http, timeout=120) as c:
            r = await c.post("/room/api/join", json={"name": self.name},
                             headers={"X-Room-Token": ROOM_TOKEN})
            r.raise_for_status()
            j = r.json()
            self.token, slots = j["token"], j["slots"]
            self.pc = pc = RTCPeerConnection(RTCConfiguration(
                bundlePolicy=RTCBundlePolicy.MAX_BUNDLE))
            # as the page: its stream's tracks (the microphone first), then the slots
            astart = int(start / FPS / 0.02)
            pc.addTransceiver(_looped_track("audio", audio, 0.02, 960, 48000,
                                            astart % len(audio)), direction="sendonly")
            t = pc.addTransceiver(_looped_track("video", [v for v, _ in video], 1 / FPS,
                                                90000 // FPS, 90000, start),
                                  direction="sendonly")
            t.setCodecPreferences([c for c in RTCRtpSender.getCapabilities("video").codecs
                                   if c.mimeType.lower() in ("video/vp8", "video/rtx")])
            for _ in range(slots):
                pc.addTransceiver("audio", direction="recvonly")

            @pc.on("connectionstatechange")
            def _state() -> None:
                if pc.connectionState in ("failed", "closed") and self.reader is not None:
                    self.dropped.append(f"peer {pc.connectionState}")

            await pc.setLocalDescription(await pc.createOffer())
            r = await c.post("/room/api/offer", json={"type": "offer",
                                                      "sdp": pc.localDescription.sdp},
                             headers={"X-Participant-Token": self.token})
            r.raise_for_status()
            await pc.setRemoteDescription(RTCSessionDescription(r.json()["sdp"], "answer"))
        if self.buffers:  # (this process is busy too: its sockets hold more)
            grow_receive_buffers(pc, self.buffers)
        for receiver in pc.getReceivers():  # the slots' audio: counted, never decoded
            attr = "_RTCRtpReceiver__decoder_queue"
            counter = _Counter(getattr(receiver, attr))
            setattr(receiver, attr, counter)
            self.counters.append(counter)
        ws = self.http.replace("http://", "ws://")
        self.ws = await websockets.connect(f"{ws}/room/ws?key={self.token}", max_size=2**24,
                                           max_queue=None, close_timeout=1)
        self.reader = asyncio.ensure_future(self._read())

    async def _read(self) -> None:
        try:
            async for text in self.ws:
                now = time.time()
                m = json.loads(text)
                if m.get("type") != "frame":
                    continue
                s = m["session"]
                self.seen[s] = self.seen.get(s, 0) + 1
                if self.measuring:
                    self.frames.append((s, now, m["t_capture"], m.get("t_tracked") or 0.0))
        except Exception as exc:  # noqa: BLE001 - said in the results
            self.dropped.append(f"socket: {exc!r}"[:200])
            return
        code = getattr(self.ws, "close_code", None)
        if code not in (None, 1000):
            self.dropped.append(f"socket closed {code}: {getattr(self.ws, 'close_reason', '')}")

    async def leave(self) -> None:
        with contextlib.suppress(Exception):
            if self.reader is not None:
                r, self.reader = self.reader, None
                await self.ws.close()
                r.cancel()
        with contextlib.suppress(Exception):
            await self.pc.close()


async def run_clients(http: str, names: list[str], clip: Path, seconds: float,
                      warmup: float, timeout: float, buffers: int = 0) -> dict[str, Any]:
    media = read_packets(clip)
    clients = [Client(http, n, media, i, buffers) for i, n in enumerate(names)]
    late = [0.0]

    async def lateness() -> None:  # how late this loop runs a 0.1 s timer (its worst)
        while True:
            t = time.monotonic()
            await asyncio.sleep(0.1)
            late[0] = max(late[0], time.monotonic() - t - 0.1)

    watch = asyncio.ensure_future(lateness())
    say = lambda **kw: print(json.dumps(kw), flush=True)  # noqa: E731
    try:
        for c in clients:  # one after the other, as people join
            await c.join()
        deadline = time.monotonic() + timeout
        short = ""
        while not all(c.seen.get(o, 0) >= 10 for c in clients for o in names):
            if time.monotonic() > deadline:  # measured all the same: how it goes is the figure
                short = {c.name: {o: c.seen.get(o, 0) for o in names
                                  if c.seen.get(o, 0) < 10} for c in clients}
                short = (f"not every client had received 10 frames of every member within "
                         f"{timeout:g} s (short: { {k: v for k, v in short.items() if v} }, "
                         f"dropped: { {c.name: c.dropped for c in clients if c.dropped} })")
                say(warning=short)
                break
            await asyncio.sleep(0.5)
        await asyncio.sleep(warmup)
        for c in clients:
            c.measuring, c.dropped = True, []
        packets0 = [sum(k.packets for k in c.counters) for c in clients]
        cpu0, t0 = time.process_time(), time.monotonic()
        late[0] = 0.0
        say(phase="start", t=time.time())
        await asyncio.sleep(seconds)
        for c in clients:
            c.measuring = False
        wall, own = time.monotonic() - t0, time.process_time() - cpu0
        say(phase="end", t=time.time())
        return {"wall": wall, "cpu_s": own, "late_ms": round(1000 * late[0], 1), "short": short,
                "frames": {c.name: c.frames for c in clients},
                "dropped": {c.name: c.dropped for c in clients},
                "slot_packets_per_s": {c.name: (sum(k.packets for k in c.counters) - p0) / wall
                                       for c, p0 in zip(clients, packets0, strict=True)}}
    finally:
        watch.cancel()
        for c in clients:
            await c.leave()


def clients_main(args: argparse.Namespace) -> None:
    out = asyncio.run(run_clients(args.http, args.names.split(","), Path(args.clip),
                                  args.seconds, args.warmup, args.timeout,
                                  args.client_buffers))
    print(json.dumps({"phase": "result", **out}), flush=True)


# ----------------------------------------------------------------------------- the server side
def worker_pid(session: Any) -> int | None:
    process = getattr(getattr(session, "_worker", None), "process", None)
    return getattr(process, "pid", None)


def proc_cpu_s(pid: int | None) -> float:
    if pid is None:
        return float("nan")
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:  # (it ended: a member who dropped)
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def udp_drops(pid: int) -> dict[str, int]:
    """Datagrams the kernel dropped (receive buffer full) on each UDP socket process ``pid``
    holds, by inode (``/proc/net/udp``'s ``drops``)."""
    inodes = set()
    with contextlib.suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
    out = {}
    for table in ("udp", "udp6"):
        with contextlib.suppress(OSError):
            for row in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
                cols = row.split()
                if cols[9] in inodes:
                    out[cols[9]] = int(cols[-1])
    return out


def drops_between(a: dict[str, int], b: dict[str, int]) -> int:
    """Drops on the sockets open at both times (a closed socket's count is gone)."""
    return sum(b[k] - a[k] for k in a.keys() & b.keys())


def pct(xs: list[float], q: float) -> float | None:
    import numpy as np

    return round(float(np.percentile(xs, q)), 1) if xs else None


def descendants(pid: int) -> list[int]:
    """``pid`` and every process under it."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                parent[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    out, todo = [pid], [pid]
    while todo:
        p = todo.pop()
        for child, par in parent.items():
            if par == p and child not in out:
                out.append(child)
                todo.append(child)
    return out


def tree_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds of ``pid`` and each process under it, by pid (a process that ended
    meanwhile is missing: compare the pids present at both ends)."""
    return {p: c for p in descendants(pid) if (c := proc_cpu_s(p)) == c}


def redis_counts(url: str, names: list[str]) -> dict[str, Any]:
    """Bytes into Redis so far, and per member the frames added to their stream and the
    sizes of the newest ones (JPEG)."""
    import redis

    c = redis.Redis.from_url(url)
    try:
        out: dict[str, Any] = {"in_bytes": int(c.info("stats")["total_net_input_bytes"]),
                               "added": {}, "jpeg_bytes": []}
        for m in names:
            for key in c.scan_iter(f"articast:room:cap:frames:{m}:*"):  # (one per membership)
                with contextlib.suppress(redis.ResponseError):
                    out["added"][m] = out["added"].get(m, 0) + int(
                        c.xinfo_stream(key)["entries-added"])
                for _, fields in c.xrevrange(key, count=2):
                    if b"img" in fields:
                        out["jpeg_bytes"].append(len(fields[b"img"]))
        return out
    finally:
        c.close()


def room_tracker(url: str, processor: str) -> subprocess.Popen[str]:
    """``articast room-tracker cap`` on ``url`` (a process group of its own), started."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "room-tracker", "cap", "--hub", url,
         "--processor", processor, "--max-members", "32", "--json"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True, start_new_session=True)
    assert proc.stdout is not None
    if not proc.stdout.readline():
        raise RuntimeError(f"the room tracker did not start ({proc.wait()})")
    return proc


def measure(n: int, clip: Path, args: argparse.Namespace, v1_ms: float,
            trackers: str = "local", redis_url: str = "") -> dict[str, Any]:
    import signal

    from articast.service.app import ServiceConfig
    from articast.service.room import RoomConfig
    from articast.service.security import AccessPolicy
    from tests.service_helpers import ServerThread

    names = [f"p{i}" for i in range(n)]
    remote = trackers == "remote"
    config = ServiceConfig(access=AccessPolicy(token=OPERATOR), hub_url=redis_url, room=RoomConfig(
        name="cap", token=ROOM_TOKEN, max_participants=max(8, n), max_fps=float(FPS),
        warm_media=True, processor=args.processor, remote_trackers=remote))
    load0 = os.getloadavg()
    tracker = room_tracker(redis_url, args.processor) if remote else None
    with ServerThread(config) as srv:
        proc = subprocess.Popen(
            [sys.executable, __file__, "--clients", "--http", srv.http, "--names",
             ",".join(names), "--clip", str(clip), "--seconds", str(args.seconds),
             "--warmup", str(args.warmup), "--timeout", str(args.timeout),
             "--client-buffers", str(args.client_buffers)],
            stdout=subprocess.PIPE, text=True)
        try:
            room = srv.service.room
            sessions = srv.service.manager.sessions
            before: dict[str, Any] = {}
            pids: dict[str, int | None] = {}

            def tracked(m: str) -> int:  # (remote: the frames that reached the server)
                s = sessions.get(m) or (srv.service.lookup(m) if remote else None)
                return s.metrics.frames if s is not None else 0

            def counts() -> dict[str, Any]:  # (a member who dropped counts 0 from then on)
                feeds = {m: getattr(room.members.get(m), "feed", None) for m in names}
                return {"workers": {m: proc_cpu_s(p) for m, p in pids.items()},
                        "tracker": tree_cpu_s(tracker.pid) if tracker is not None else {},
                        "redis": redis_counts(redis_url, names) if redis_url else {},
                        "tracked": {m: tracked(m) for m in names},
                        "received": {m: f.received if f else 0 for m, f in feeds.items()},
                        "replaced": {m: f.dropped if f else 0 for m, f in feeds.items()},
                        "rtp": {m: dict(f.rtp) if f else {} for m, f in feeds.items()}}
            result: dict[str, Any] = {}
            for line in proc.stdout:  # type: ignore[union-attr]
                msg = json.loads(line)
                if "warning" in msg:
                    print(f"N={n}: {msg['warning']}", file=sys.stderr, flush=True)
                    continue
                if "error" in msg:
                    return {"participants": n, "error": msg["error"], "seen": msg.get("seen"),
                            "load_1min": [round(load0[0], 2), round(os.getloadavg()[0], 2)]}
                if msg.get("phase") == "start":
                    pids = {m: (tracker.pid if tracker is not None else
                                worker_pid(sessions.get(m))) for m in names}
                    media_pid = srv.service.media._proc.pid
                    print(f"N={n}: measuring: server {os.getpid()}, media process {media_pid}"
                          f", workers {pids}, clients {proc.pid}", file=sys.stderr, flush=True)
                    srv.service.media.late_ms = 0.0
                    before = {"own": time.process_time(), "media": proc_cpu_s(media_pid),
                              "udp_drops": udp_drops(media_pid),
                              "client_udp_drops": udp_drops(proc.pid),
                              **counts(), "t": time.monotonic()}
                elif msg.get("phase") == "end":
                    wall = time.monotonic() - before["t"]
                    after = {"own": time.process_time(), "media": proc_cpu_s(media_pid),
                             "udp_drops": udp_drops(media_pid),
                             "client_udp_drops": udp_drops(proc.pid),
                             "late_ms": srv.service.media.late_ms, **counts()}
                    alive = all(p is not None and Path(f"/proc/{p}").exists()
                                for p in (media_pid, *pids.values()))
                elif msg.get("phase") == "result":
                    result = msg
            proc.wait(60)
        finally:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(10)
            if tracker is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(tracker.pid, signal.SIGTERM)
                try:
                    tracker.wait(20)
                except subprocess.TimeoutExpired:
                    os.killpg(tracker.pid, signal.SIGKILL)
                    tracker.wait()
    load1 = os.getloadavg()
    if not result:
        return {"participants": n, "error": f"the clients' process ended ({proc.returncode}) "
                "without results", "load_1min": [round(load0[0], 2), round(load1[0], 2)]}
    wall = result["wall"]
    delivered: dict[str, float] = {}
    lat: list[float] = []
    tracked_part: list[float] = []
    for m in names:
        rates = [sum(1 for f in result["frames"][c] if f[0] == m) / wall
                 for c in names if c != m or n == 1]
        delivered[m] = round(sorted(rates)[len(rates) // 2], 1)
    for c in names:
        for m, received, t_capture, t_tracked in result["frames"][c]:
            if m != c or n == 1:
                lat.append(1000 * (received - t_capture))
                if t_tracked:
                    tracked_part.append(1000 * (t_tracked - t_capture))
    media = after["media"] - before["media"]
    own = after["own"] - before["own"]
    workers = {m: after["workers"][m] - before["workers"][m] for m in names}
    tracker_s = sum(after["tracker"][p] - c for p, c in before["tracker"].items()
                    if p in after["tracker"])
    if remote:  # one process tracks them all: its CPU (its workers') shared out
        workers = {m: tracker_s / n for m in names}
    ended = sorted(m for m, v in workers.items() if v != v)  # their worker is gone: NaN
    workers = {m: (0.0 if m in ended else v) for m, v in workers.items()}
    tracked = {m: after["tracked"][m] - before["tracked"][m] for m in names}
    per = {m: 1000 * (workers[m] + (own + media) / n) / max(tracked[m], 1) for m in names
           if m not in ended}

    def rtp_delta(m: str) -> dict[str, list[int]]:
        out = {}
        for kind, (got, lost) in after["rtp"][m].items():
            g0, l0 = before["rtp"][m].get(kind, (0, 0))
            out[kind] = [got - g0, lost - l0]
        return out

    extra: dict[str, Any] = {"trackers": trackers}
    if remote:
        extra["tracker_cores"] = round(tracker_s / wall, 3)
        pid = tracker.pid if tracker is not None else -1  # (its own loop: the hub, leases)
        if pid in before["tracker"] and pid in after["tracker"]:
            extra["tracker_main_cores"] = round(
                (after["tracker"][pid] - before["tracker"][pid]) / wall, 3)
    here = own + media + (0.0 if remote else sum(workers.values()))
    extra["server_cores_per_participant"] = round(here / wall / n, 3)
    if redis_url:
        r0, r1 = before["redis"], after["redis"]
        added = {m: round((r1["added"][m] - r0["added"].get(m, 0)) / wall, 1)
                 for m in names if m in r1["added"]}
        jpeg = r1["jpeg_bytes"] + r0["jpeg_bytes"]
        extra["redis"] = {"in_kB_per_s": round((r1["in_bytes"] - r0["in_bytes"]) / wall / 1e3, 1),
                          "frames_published_fps": added,
                          "jpeg_kB": round(sum(jpeg) / len(jpeg) / 1e3, 1) if jpeg else None}
    return {
        "participants": n, "seconds": round(wall, 1), "cores": os.cpu_count(), **extra,
        "load_1min": [round(load0[0], 2), round(load1[0], 2)],
        "all_alive": alive,
        "before_measuring": result.get("short") or "every client received every member",
        "workers_ended": ended,
        "delivered_fps": delivered,
        "tracked_fps": {m: round(tracked[m] / wall, 1) for m in names},
        "received_fps": {m: round((after["received"][m] - before["received"][m]) / wall, 1)
                         for m in names},
        "replaced_fps": {m: round((after["replaced"][m] - before["replaced"][m]) / wall, 1)
                         for m in names},
        "latency_ms": {"p50": pct(lat, 50), "p95": pct(lat, 95), "n": len(lat),
                       "to": "the client's socket (not a rendered screen)"},
        "tracked_ms": {"p50": pct(tracked_part, 50), "p95": pct(tracked_part, 95)},
        "rtp": {m: rtp_delta(m) for m in names},
        "dropped": {m: v for m, v in result["dropped"].items() if v},
        "media_udp_drops": drops_between(before["udp_drops"], after["udp_drops"]),
        "media_loop_late_ms": after["late_ms"],
        "clients_udp_drops": drops_between(before["client_udp_drops"],
                                           after["client_udp_drops"]),
        "clients_loop_late_ms": result["late_ms"],
        "cpu_cores": {"server": round(own / wall, 3), "media_process": round(media / wall, 3),
                      "workers": {m: round(v / wall, 3) for m, v in workers.items()},
                      "workers_total": round(sum(workers.values()) / wall, 3),
                      "clients": round(result["cpu_s"] / wall, 3)},
        "cpu_ms_per_frame": {m: round(v, 1) for m, v in per.items()},
        "cpu_x_v1": {m: round(v / v1_ms, 2) for m, v in per.items()},
        "slot_packets_per_s": {m: round(v, 1) for m, v in result["slot_packets_per_s"].items()},
    }


def v1_reference(cache: Path) -> float:
    """The FaceMesh v1 loop's CPU ms per frame on the clip's frames (cached)."""
    ref = cache / "v1_loop_cpu_ms.json"
    if ref.exists():
        return float(json.loads(ref.read_text())["ms"])
    import numpy as np
    from room import v1_loop_cpu_ms

    frames = list(np.load(cache / "frames.npy")[:150])
    ms = v1_loop_cpu_ms(frames)
    ref.write_text(json.dumps({"ms": ms, "frames": len(frames), "load": os.getloadavg()[0]}))
    return ms


def line(r: dict[str, Any], target: float) -> str:
    n = r["participants"]
    if "error" in r:
        return f"N={n}: not measured: {r['error']} (load {r['load_1min'][0]}->{r['load_1min'][1]})"
    fps = list(r["delivered_fps"].values())
    lost = sum(v[1] for m in r["rtp"].values() for v in m.values())
    got = sum(v[0] for m in r["rtp"].values() for v in m.values())
    c = r["cpu_cores"]
    x = r["cpu_x_v1"].values()
    xv1 = f"; x v1 {min(x):.2f}-{max(x):.2f}" if x else ""
    if r["workers_ended"]:
        xv1 += f" (workers ended: {','.join(r['workers_ended'])})"
    how = ""
    if "trackers" in r and "redis" in r:
        how = (f"[{r['trackers']} trackers; server {r['server_cores_per_participant']:.2f} "
               f"cores/participant" + (f", tracker process {r['tracker_cores']:.2f} cores "
                                       f"(its own loop {r.get('tracker_main_cores', -1):.2f})"
                                       if "tracker_cores" in r else "")
               + f"; into Redis {r['redis']['in_kB_per_s']:.0f} kB/s"
               + (f", JPEG {r['redis']['jpeg_kB']} kB at "
                  f"{sum(r['redis']['frames_published_fps'].values()):.1f} fps"
                  if r["redis"]["jpeg_kB"] else "") + "] ")
    return (f"N={n}: {how}delivered {min(fps):.1f}-{max(fps):.1f} fps (tracked "
            f"{min(r['tracked_fps'].values()):.1f}-{max(r['tracked_fps'].values()):.1f}, target "
            f"{target:g}: {'ok' if min(fps) >= target else 'SHORT'}), capture->client socket "
            f"p50 {r['latency_ms']['p50']} p95 {r['latency_ms']['p95']} ms, RTP lost {lost}/"
            f"{got} (media's UDP buffers dropped {r['media_udp_drops']}, its loop late by up to "
            f"{r['media_loop_late_ms']:.0f} ms; clients' {r['clients_udp_drops']}, "
            f"{r['clients_loop_late_ms']:.0f} ms), dropped {len(r['dropped'])}, cores: server "
            f"{c['server']:.2f} media "
            f"{c['media_process']:.2f} workers {c['workers_total']:.2f} clients "
            f"{c['clients']:.2f}{xv1}; load {r['load_1min'][0]}->{r['load_1min'][1]}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", default="1,2,4,6,8", help="N to measure, comma-separated")
    ap.add_argument("--seconds", type=float, default=30.0, help="measured, per N")
    ap.add_argument("--warmup", type=float, default=10.0,
                    help="after every client receives every member's frames")
    ap.add_argument("--timeout", type=float, default=240.0,
                    help="for every client to receive every member's frames")
    ap.add_argument("--target", type=float, default=25.0)
    ap.add_argument("--processor", default="auto",
                    help="what tracks each member (auto: the tracker; "
                    "tests.service_helpers:ImageStats reads the image only, to measure the "
                    "media and the server without the trackers)")
    ap.add_argument("--trackers", default="local",
                    help="local (the server's workers; no Redis), or local,remote: each N "
                    "with both, on one redis-server started here (remote: the server with "
                    "--remote-trackers and one 'articast room-tracker')")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/articast-room-capacity"),
                    help="where the encoded clip (and the v1 reference) are kept")
    ap.add_argument("--client-buffers", type=int, default=2 * 1024 * 1024,
                    help="each client's UDP receive buffer (bytes; 0: the kernel's default)")
    ap.add_argument("--json", action="store_true", help="one JSON object, nothing else")
    ap.add_argument("--out", type=Path, help="also write the JSON object there")
    ap.add_argument("--clients", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--http", help=argparse.SUPPRESS)
    ap.add_argument("--names", help=argparse.SUPPRESS)
    ap.add_argument("--clip", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    problem = missing()
    if problem:
        raise SystemExit(problem)
    if args.clients:
        clients_main(args)
        return
    clip = make_media(args.cache)
    v1 = v1_reference(args.cache)
    target = min(args.target, FPS)
    results, started = [], time.time()
    modes = [m.strip() for m in args.trackers.split(",")]
    if not set(modes) <= {"local", "remote"}:
        raise SystemExit("--trackers: local, remote or local,remote")
    redis = None
    if modes != ["local"]:
        from tests.test_redis_scaleout import Redis

        redis = Redis()
        redis.start()
    try:
        for n in (int(x) for x in args.participants.split(",")):
            for mode in modes:
                r = measure(n, clip, args, v1, mode, redis.url if redis else "")
                results.append(r)
                if not args.json:
                    print(line(r, target), flush=True)
                time.sleep(3.0)  # the last N's workers and media process gone
    finally:
        if redis is not None:
            redis.stop()
    ok = [r["participants"] for r in results
          if "error" not in r and min(r["delivered_fps"].values()) >= target]
    out = {"started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(started)),
           "target_fps": target, "clip_fps": FPS, "v1_loop_cpu_ms_per_frame": round(v1, 1),
           "capacity": max(ok, default=0), "results": results}
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))
    if args.json:
        print(json.dumps(out))
    else:
        print(f"capacity at {target:g} fps: {out['capacity']} participant(s) (largest N "
              "measured at which every member was delivered at the target)")


if __name__ == "__main__":
    main()

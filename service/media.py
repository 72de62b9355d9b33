"""The media process: every participant's WebRTC connection runs in a process of its own.

aiortc does its work on an asyncio loop: ICE (and its consent checks, which a browser expects
answered within a second or so), DTLS, SRTP, the jitter buffers, and feeding the decoders.
On the server's own loop, which also serves the room's sockets, the session API and the
trackers' frames, under load that loop answered late: UDP queues filled (~370 kB), datagrams
were dropped, consent checks went unanswered and aioice closed the connection after ~50 s
(docs/ROOM.md). Here the connections, their decoding and the room's audio relay run on the
loop of one child process (forked from the workers' fork server, as a session's worker is),
so none of the server's work delays them, and none of theirs the server.

The server keeps a :class:`MediaProcess` (started on the first offer) and talks to it over one
duplex pipe:

server -> media   ``("offer", id, name, sdp, room)``  answer a participant's offer (``room``:
                                                      the room whose audio slots it takes,
                                                      "" for the join page)
                  ``("inlet", id)`` + a file handle   the writing end of a new worker's frame
                                                      pipe: the participant's frames go there
                  ``("close", id, reason)``           the participant leaves (closes the peer)
                  ``("frames", id, room, joined)``    (``--remote-trackers``) the participant's
                                                      frames go to Redis, for a tracker on
                                                      any machine (service/room_frames.py),
                                                      not to a local worker's pipe
                  ``("remote", room, [name, ...])``   (Redis) the room's members on its other
                                                      servers, each half second: their voices
                                                      are heard here, ours relayed to them
                  ``("quit",)``
media -> server   ``("answer", id, sdp, problem, mids)``
                  ``("ended", id, reason)``           the participant left (or their video)
                  ``("stats", {id: (received, replaced, width, height, resized,
                                    {kind: (RTP packets, lost)})}, late_ms)``  each second
                                                      (late_ms: how late this process's
                                                      loop ran a 0.1 s timer, at most, over
                                                      that second)
                  ``("room", room, {name: {"slots": {member: mid}, "level": rms}})``

Frames never pass through the server: the media process writes each participant's newest
frame straight into the pipe its session's worker reads (:class:`articast.service.webrtc.Feed`
there, a :class:`RemoteFeed` here with the same interface). The pipe's writing end is handed
over with ``SCM_RIGHTS`` (:func:`multiprocessing.reduction.send_handle`).

Voices across servers (``--hub redis://``): this process has a Redis connection of its own
(:class:`RedisVoices`), so that 50 packets a second per voice go from the receiving peer's
loop to Redis and from Redis to the slots without passing the server's busy loop or the
pipe. While the room has members on other servers, each member's Opus packets here are
published as they are forwarded (``PREFIX room:ROOM:audio:NAME``: a 16-byte header, the RTP
timestamp, the wall-clock time of sending and the microphone's level, then the packet), and
the channel of each member on another server is read into a tap (:class:`RemoteVoice`) that
the slots point at as at a local microphone. Redis away: the remote voices stop (two lines
in the log, one more when it is back), nothing else does.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import struct
import sys
import threading
import time
from multiprocessing import reduction
from multiprocessing.connection import Connection
from typing import Any

from articast.service.clock import CLOCK

log = logging.getLogger("articast.media")

ANSWER_TIMEOUT_S = 60.0
"""How long an offer waits for the media process's answer (it starts on the first offer)."""


# ----------------------------------------------------------------------------- the server's side
class RemoteFeed:
    """A participant's frames as the server sees them: the interface of
    :class:`articast.service.webrtc.Feed` (``new_inlet``, ``close``, ``ended`` and the
    counts), the frames themselves going from the media process to the worker."""

    def __init__(self, media: MediaProcess, pid: int, name: str, gen: int) -> None:
        self._media, self.pid, self.name, self.gen = media, pid, name, gen
        self.ended = ""
        self.received = self.dropped = self.resized = 0
        self.size: tuple[int, int] = (0, 0)
        self.rtp: dict[str, tuple[int, int]] = {}

    def new_inlet(self) -> Any:
        reader, writer = multiprocessing.Pipe(duplex=False)
        if self.ended or not self._media.send(("inlet", self.pid), handle=writer.fileno()):
            writer.send(("end", self.ended or "the media process is gone"))
        writer.close()  # the media process holds its own copy: EOF when it lets go
        return reader

    def close(self, reason: str) -> None:
        if self.ended:
            return
        self.ended = reason
        self._media.send(("close", self.pid, reason))

    def to_redis(self, room: str, joined: float) -> bool:
        """The participant's frames go to Redis (``--remote-trackers``), not to a worker: to
        their membership's stream (``joined``: :func:`articast.service.room_frames.frames_key`)."""
        return not self.ended and self._media.send(("frames", self.pid, room, joined))


class MediaProcess:
    """The server's handle on the media process (see the module's docstring)."""

    def __init__(self, redis_url: str = "", prefix: str = "articast:") -> None:
        self.redis_url, self.prefix = redis_url, prefix
        """The room's Redis (""): the media process relays voices to other servers there."""
        self._lock = threading.Lock()
        """Held while writing to the media process."""
        self._starting = threading.Lock()
        """Held while (re)starting it: a thread's work, never the event loop's (the first
        start waits for the workers' fork server to import what workers need: 5 s under
        load, which held the server's loop and every room socket)."""
        self._conn: Any = None
        self._proc: Any = None
        self._next = 1
        self._gen = 0
        """Which media process (a new one starts if the last one died)."""
        self._answers: dict[int, tuple[asyncio.AbstractEventLoop, asyncio.Future[Any],
                                       int]] = {}
        self.feeds: dict[int, RemoteFeed] = {}
        self.late_ms = 0.0
        """The most the media process's loop ran late (ms) since this was last set to 0
        (benchmarks/room_capacity.py reads it: a slow loop loses RTP packets, docs/ROOM.md,
        "Capacity")."""
        self.rooms: dict[str, dict[str, dict[str, Any]]] = {}
        """Room -> member -> ``{"slots": {other member: mid}, "level": rms}`` (the media
        process routes the audio; this is what it said last)."""

    def _start(self) -> None:
        from articast.service.worker import ProcessWorker

        ctx = ProcessWorker._ctx
        conn, child = ctx.Pipe(duplex=True)
        level = logging.getLogger("articast").getEffectiveLevel()
        proc = ctx.Process(target=_process_main,
                           args=(child, level, self.redis_url, self.prefix),
                           name="articast media", daemon=True)
        proc.start()
        child.close()
        with self._lock:
            self._conn, self._proc = conn, proc
            self._gen += 1
        threading.Thread(target=self._read, args=(conn, self._gen), name="media reader",
                         daemon=True).start()
        log.info("media process %d started", proc.pid)

    def start(self) -> None:
        """Start the media process now unless it runs (a thread's work: it waits for the
        workers' fork server)."""
        with self._starting:
            if self._proc is None or not self._proc.is_alive():
                self._start()

    def _ensure(self) -> tuple[int, int]:
        """Start the media process unless it runs; a new peer id and the process's gen."""
        self.start()
        with self._lock:
            pid, self._next = self._next, self._next + 1
            return pid, self._gen

    def send(self, msg: tuple[Any, ...], handle: int | None = None) -> bool:
        with self._lock:
            if self._conn is None:
                return False
            try:
                self._conn.send(msg)
                if handle is not None:
                    reduction.send_handle(self._conn, handle, self._proc.pid)
            except (OSError, ValueError):
                return False
            return True

    async def answer(self, sdp: str, name: str, room: str = "") -> tuple[str, list[str],
                                                                         RemoteFeed]:
        """The answer to ``name``'s offer, the audio slots' mids and their feed; ValueError
        (one line) when the offer cannot be answered."""
        pid, gen = await asyncio.to_thread(self._ensure)
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Any] = loop.create_future()
        self._answers[pid] = (loop, fut, gen)
        feed = self.feeds[pid] = RemoteFeed(self, pid, name, gen)
        problem = "" if self.send(("offer", pid, name, sdp, room)) else \
            "the server's media process is not running"
        answer, mids = "", []
        if not problem:
            try:
                answer, problem, mids = await asyncio.wait_for(fut, ANSWER_TIMEOUT_S)
            except TimeoutError:
                problem = f"the server's media process did not answer in {ANSWER_TIMEOUT_S:g} s"
        self._answers.pop(pid, None)
        if problem:
            feed.close(problem)
            self.feeds.pop(pid, None)
            raise ValueError(problem)
        return answer, mids, feed

    def _read(self, conn: Any, gen: int) -> None:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            if kind == "answer":
                entry = self._answers.pop(msg[1], None)
                if entry is not None:
                    loop, fut, _ = entry
                    loop.call_soon_threadsafe(_settle, fut, msg[2:])
            elif kind == "ended":
                feed = self.feeds.pop(msg[1], None)
                if feed is not None and not feed.ended:
                    feed.ended = msg[2]
            elif kind == "stats":
                if len(msg) > 2:
                    self.late_ms = max(self.late_ms, float(msg[2]))
                for pid, (received, dropped, width, height, resized, rtp) in msg[1].items():
                    feed = self.feeds.get(pid)
                    if feed is not None:
                        feed.received, feed.dropped = received, dropped
                        feed.size, feed.resized, feed.rtp = (width, height), resized, rtp
            elif kind == "room":
                self.rooms[msg[1]] = msg[2]
        log.warning("the media process ended: its participants leave")
        for pid, feed in list(self.feeds.items()):
            if feed.gen == gen:
                feed.ended = feed.ended or "the server's media process ended"
                self.feeds.pop(pid, None)
        for loop, fut, g in list(self._answers.values()):
            if g == gen:
                loop.call_soon_threadsafe(_settle, fut,
                                          ("", "the server's media process ended", []))

    def close(self, timeout: float = 3.0) -> None:
        self.send(("quit",))
        proc = self._proc
        if proc is not None:
            proc.join(timeout)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None


def _settle(fut: asyncio.Future[Any], value: Any) -> None:
    if not fut.done():
        fut.set_result(value)


# ----------------------------------------------------------------------------- the process
class _ConsentExpiry(logging.Filter):
    """aioice's own lines at WARNING and above, and the one INFO line that says why a
    connection closed by itself ("Consent to send expired": the browser left six consent
    checks in a row unanswered), raised to a WARNING: a participant dropped under load is
    then explained in the server's log (docs/ROOM.md, "Leaving and faults")."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            return True
        if "Consent to send expired" in record.getMessage():
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            return True
        return False


def _process_main(conn: Any, level: int, redis_url: str = "", prefix: str = "") -> None:
    logging.basicConfig(level=level, format="%(levelname)s %(name)s (media): %(message)s")
    logging.getLogger("aioice").setLevel(max(level, logging.WARNING))
    ice = logging.getLogger("aioice.ice")  # (its consent line is INFO: let that one through)
    ice.setLevel(min(level, logging.INFO))
    ice.addFilter(_ConsentExpiry())
    logging.getLogger("aiortc").setLevel(max(level, logging.WARNING))
    batch_datagram_reads()
    try:
        asyncio.run(_Media(conn, redis_url, prefix).main())
    except KeyboardInterrupt:  # the server's Ctrl-C reaches its children too
        pass


DATAGRAM_BATCH = 64
"""Datagrams a socket's readiness reads at most (libuv reads 32)."""


def batch_datagram_reads(batch: int = DATAGRAM_BATCH) -> Any:
    """asyncio's datagram transports read up to ``batch`` datagrams when their socket is
    ready, not one: the media process's (the call is its own; the server's loop is uvicorn's).

    asyncio reads one datagram per socket per turn of the loop, and a turn of the media
    process's loop runs every ready task of every participant (their RTP, the audio slots,
    the decoders' frames): with 4 participants on this machine, a turn every few ms took
    fewer datagrams a second from each socket than its camera and microphone sent, and its
    buffer (aioice's 512 kB) overflowed while the loop was never more than 90 ms late (2017
    datagrams dropped in 30 s; the VP8 decoder then fails until the next keyframe;
    benchmarks/room_capacity.py, docs/ROOM.md "Capacity"). Returns the method replaced (a test
    puts it back)."""
    from asyncio import selector_events

    cls: Any = getattr(selector_events, "_SelectorDatagramTransport", None)
    original = getattr(cls, "_read_ready", None)
    if original is None or not sys.version_info[:2] <= (3, 13):
        # asyncio's internals moved (a Python this was not read for): reads stay one a turn
        log.warning("the media process reads datagrams one at a time (asyncio's datagram "
                    "transport is not the one batch_datagram_reads knows)")
        return original
    if getattr(original, "batched", False):
        return original

    def _read_ready(self: Any) -> None:  # asyncio's own, looped (Python 3.11-3.13)
        for _ in range(batch):
            if self._conn_lost:
                return
            try:
                data, addr = self._sock.recvfrom(self.max_size)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._protocol.error_received(exc)
                return
            except (SystemExit, KeyboardInterrupt):
                raise
            except BaseException as exc:  # noqa: BLE001 - as asyncio's
                self._fatal_error(exc, "Fatal read error on datagram transport")
                return
            self._protocol.datagram_received(data, addr)

    _read_ready.batched = True  # type: ignore[attr-defined]
    cls._read_ready = _read_ready
    return original


class _Peer:
    def __init__(self, name: str, feed: Any, room: str) -> None:
        self.name, self.feed, self.room = name, feed, room


class _Media:
    """The media process's loop: peers by id, rooms by name."""

    def __init__(self, conn: Any, redis_url: str = "", prefix: str = "articast:") -> None:
        self.conn = conn
        self.redis_url, self.prefix = redis_url, prefix
        self._voices: RedisVoices | None = None
        self.lock = threading.Lock()
        self.peers: dict[int, _Peer] = {}
        self.rooms: dict[str, Any] = {}
        self.closed_early: dict[int, str] = {}
        self.publishers: dict[int, Any] = {}
        """Peer id -> its :class:`articast.service.room_frames.FramePublisher` (frames to
        Redis, ``--remote-trackers``)."""
        self.late = 0.0
        """The most this loop ran late since the last stats (s)."""
        self.loop: asyncio.AbstractEventLoop | None = None
        self.done: asyncio.Event | None = None

    def send(self, msg: tuple[Any, ...]) -> None:
        with self.lock:
            try:
                self.conn.send(msg)
            except (OSError, ValueError):
                pass

    async def main(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.done = asyncio.Event()
        threading.Thread(target=self._read, name="commands", daemon=True).start()
        reporter = asyncio.ensure_future(self._report())
        await self.done.wait()
        reporter.cancel()
        for peer in list(self.peers.values()):
            peer.feed.close("the server is stopping")
        if self._voices is not None:
            self._voices.close()
        await asyncio.sleep(0.2)  # the peers' close tasks

    def _read(self) -> None:
        assert self.loop is not None
        while True:
            try:
                msg = self.conn.recv()
                if msg[0] == "inlet":
                    msg = (*msg, reduction.recv_handle(self.conn))
            except (EOFError, OSError):  # the server is gone
                msg = ("quit",)
            self.loop.call_soon_threadsafe(self._handle, msg)
            if msg[0] == "quit":
                return

    def _handle(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "offer":
            asyncio.ensure_future(self._offer(*msg[1:]))
        elif kind == "inlet":
            pid, fd = msg[1], msg[2]
            writer = Connection(fd, readable=False)
            peer = self.peers.get(pid)
            if peer is not None:
                peer.feed.attach(writer)
            else:
                writer.send(("end", "the participant left"))
                writer.close()
        elif kind == "frames":
            self._publish_frames(msg[1], msg[2], msg[3])
        elif kind == "close":
            peer = self.peers.get(msg[1])
            if peer is not None:
                peer.feed.close(msg[2])
            else:  # still being answered (the server gave up waiting): closed once answered
                self.closed_early[msg[1]] = msg[2]
        elif kind == "remote":
            self.room(msg[1]).set_remote(msg[2])
        elif kind == "quit":
            assert self.done is not None
            self.done.set()

    def _publish_frames(self, pid: int, room: str, joined: float) -> None:
        """The peer's frames go to their stream in Redis from now on (the feed's forwarder
        writes there as it would to a worker's pipe), for a tracker on any machine."""
        from articast.service.room_frames import FramePublisher, frames_key

        peer = self.peers.get(pid)
        if peer is None or not self.redis_url:
            return
        publisher = FramePublisher(self.redis_url,
                                   frames_key(self.prefix, room, peer.name, joined))
        self.publishers[pid] = publisher
        peer.feed.attach(publisher)

    def log_frames(self, period: float) -> None:
        """One line on the frames put in Redis (``--log-level info``), then counted anew."""
        parts = []
        for pid, publisher in list(self.publishers.items()):
            peer = self.peers.get(pid)
            if peer is None:
                self.publishers.pop(pid, None)
                continue
            frames, size, encode_s = publisher.counts()
            if frames:
                parts.append(f"{peer.name}: {frames / period:.1f} frames/s, "
                             f"{size / frames / 1e3:.1f} kB a frame, JPEG "
                             f"{1e3 * encode_s / frames:.1f} ms a frame")
        if parts:
            log.info("frames to Redis over %g s: %s", period, "; ".join(parts))

    def voices(self) -> RedisVoices | None:
        """This process's Redis connection for the voices (made when first needed; None
        without Redis)."""
        if self._voices is None and self.redis_url:
            self._voices = RedisVoices(self.redis_url, self.prefix)
        return self._voices

    def room(self, name: str) -> MediaRoom:
        if name not in self.rooms:
            self.rooms[name] = MediaRoom(name, lambda state: self.send(("room", name, state)),
                                         self.voices)
        return self.rooms[name]

    async def _offer(self, pid: int, name: str, sdp: str, room: str) -> None:
        from articast.service import webrtc

        feed = webrtc.Feed(name)
        hooks = self.room(room).hooks(name) if room else None
        try:
            answer = await webrtc.answer(sdp, feed, hooks)
        except ValueError as exc:
            feed.close("the offer was refused")
            if hooks is not None:
                hooks.leave()
            self.closed_early.pop(pid, None)
            self.send(("answer", pid, "", str(exc), []))
            return
        except Exception as exc:  # noqa: BLE001 - one line to the server, the process lives
            feed.close("the offer was refused")
            if hooks is not None:
                hooks.leave()
            self.closed_early.pop(pid, None)
            self.send(("answer", pid, "", f"the offer could not be answered: {exc!r}"[:300],
                       []))
            return
        self.peers[pid] = _Peer(name, feed, room)

        def ended(reason: str) -> None:  # any thread
            def gone() -> None:
                self.peers.pop(pid, None)
                if hooks is not None:
                    hooks.leave()
                self.send(("ended", pid, reason))

            assert self.loop is not None
            self.loop.call_soon_threadsafe(gone)

        feed.on_end = ended
        early = self.closed_early.pop(pid, None)
        if early is not None:
            feed.close(early)  # (calls ended)
        if feed.ended and feed.on_end is not None:  # it ended while answering
            feed.on_end = None
            ended(feed.ended)
        self.send(("answer", pid, answer, "", hooks.mids if hooks is not None else []))

    async def _lateness(self) -> None:
        """How late this loop runs a 0.1 s timer (its worst, each second, in the stats)."""
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(0.1)
            self.late = max(self.late, time.monotonic() - t0 - 0.1)

    async def _report(self) -> None:
        from articast.service.webrtc import count_rtp

        tick = 0
        self.late = 0.0
        lateness = asyncio.ensure_future(self._lateness())
        while True:
            try:
                await asyncio.sleep(1.0)
            except asyncio.CancelledError:
                lateness.cancel()
                raise
            tick += 1
            if tick % 5 == 0:
                for p in list(self.peers.values()):
                    await count_rtp(p.feed)
            self.send(("stats", {pid: (p.feed.received, p.feed.dropped, *p.feed.size,
                                       p.feed.resized, p.feed.rtp)
                                 for pid, p in self.peers.items()}, round(1000 * self.late, 1)))
            self.late = 0.0
            for room in self.rooms.values():
                room.publish()
                if tick % 10 == 0:
                    room.log_voices(10.0)
            if tick % 10 == 0 and self.publishers:
                self.log_frames(10.0)


# ----------------------------------------------------------------------------- voices via Redis
HEADER = struct.Struct("!Idf")
"""A relayed packet's header: its RTP timestamp, when its server published it (in Redis's
clock, seconds: :mod:`articast.service.clock`; the hop's delay is measured on the receiving
server, in Redis's clock too), and the microphone's level
there (RMS of the last decoded frame: a remote member's page shows them speaking too)."""


class _Bytes:
    """The voices' messages are bytes as they are."""

    def encode(self, message: bytes) -> bytes:
        return message

    def decode(self, data: bytes) -> bytes:
        return bytes(data)


class RedisVoices:
    """The media process's own Redis connection, for the voices only: a
    :class:`articast.service.redis_hub.RedisHub` of bytes (its writer never holds the
    caller; a packet not sent within ``max_age_s`` is dropped, never replayed after an
    outage; its reader reconnects with back-off and joins its channels again)."""

    MAX_AGE_S = 0.2
    """A packet still waiting for Redis after this long is dropped (it would come too late to
    be played)."""

    def __init__(self, url: str, prefix: str) -> None:
        from articast.service.redis_hub import RedisHub

        CLOCK.start(url, quiet=True)
        self.hub: Any = RedisHub(url, _Bytes(), prefix=prefix, max_pending=256,
                                 max_age_s=self.MAX_AGE_S)

    @staticmethod
    def topic(room: str, name: str) -> str:
        return f"room:{room}:audio:{name}"

    def publish(self, room: str, name: str, payload: bytes, timestamp: int,
                level: float = 0.0) -> int:
        """One packet of ``name``'s voice to the room's other servers: its size in bytes."""
        data = HEADER.pack(timestamp, CLOCK.redis_now(), level) + payload
        self.hub.publish(self.topic(room, name), data)
        return len(data)

    def subscribe(self, room: str, name: str) -> Any:
        return self.hub.subscribe(self.topic(room, name), max_queue=Tap.QUEUE)

    def close(self) -> None:
        self.hub.close()


class RemoteVoice:
    """The voice of a member on another of the room's servers, read from Redis into a
    :class:`Tap` the slots point at as at a local microphone."""

    def __init__(self, voices: RedisVoices, room: str, name: str) -> None:
        self.name = name
        self.tap = Tap()
        self.packets = self.bytes = 0
        self.level = 0.0
        """The microphone's level as its server measured it (the last packet's)."""
        self.delays: list[float] = []
        """The hop's delays (s: publication on the member's server to reading here) since
        they were last logged."""
        self._sub = voices.subscribe(room, name)
        self._task = asyncio.ensure_future(self._read())

    async def _read(self) -> None:
        from articast.service.hub import HubClosed

        try:
            while True:
                data = await self._sub.get()
                if len(data) <= HEADER.size:
                    continue
                timestamp, sent, self.level = HEADER.unpack_from(data)
                self.packets += 1
                self.bytes += len(data)
                if len(self.delays) < 10_000:
                    self.delays.append(CLOCK.redis_now() - sent)
                self.tap._fan((data[HEADER.size:], timestamp))
        except (HubClosed, asyncio.CancelledError):
            pass

    def close(self) -> None:
        self._sub.close()
        self._task.cancel()
        self.tap.end()


# ----------------------------------------------------------------------------- a room's audio
class Tap:
    """A member's voice as Opus packets ``(payload, RTP timestamp)``, fanned out to the slots
    pointed at it (each a reader with a queue of its own); ``None`` ends it."""

    QUEUE = 25
    """Packets a slow subscriber may hold (0.5 s of 20 ms frames); older ones are dropped."""

    def __init__(self) -> None:
        self.subscribers: set[asyncio.Queue[Any]] = set()

    def _fan(self, item: Any) -> None:
        for q in list(self.subscribers):
            if q.full():
                q.get_nowait()
            q.put_nowait(item)

    def subscribe(self) -> _TapReader:
        q: asyncio.Queue[Any] = asyncio.Queue(self.QUEUE)
        self.subscribers.add(q)
        return _TapReader(self, q)

    def end(self) -> None:
        self._fan(None)


class PacketTap(Tap):
    """A member's microphone as the Opus packets their browser sent, for the other members'
    slots: forwarded as received, never decoded and encoded again.

    aiortc has no public way to read a remote track's encoded frames, so the receiver's queue
    to its decoder thread (``_RTCRtpReceiver__decoder_queue``, aiortc 1.16) is wrapped: each
    reassembled frame still goes to the decoder (the member's level is measured on it) and, as
    ``(payload, RTP timestamp)``, to every subscriber's queue, and to ``relay`` (the room's
    other servers, through Redis). aiortc's sender sends an ``av.Packet`` it is given as it is
    (``RTCRtpSender._next_encoded_frame``: ``pack``)."""

    def __init__(self, receiver: Any) -> None:
        super().__init__()
        attr = "_RTCRtpReceiver__decoder_queue"
        inner: Any = getattr(receiver, attr, None)
        if inner is None or not hasattr(inner, "put"):
            raise RuntimeError("this aiortc's receivers have no decoder queue to tap: "
                               "the room cannot forward microphones")
        tap = self
        self.relay: Any = None
        """Called with ``(payload, RTP timestamp)`` for each packet (None: not relayed)."""

        class Tee:
            def put(self, item: Any) -> None:  # on the media loop (the receiver's RTP task)
                inner.put(item)
                if item is None:
                    tap._fan(None)
                    return
                packet = (item[1].data, item[1].timestamp)
                tap._fan(packet)
                if tap.relay is not None:
                    tap.relay(*packet)

            def __getattr__(self, name: str) -> Any:
                return getattr(inner, name)

        setattr(receiver, attr, Tee())


class _TapReader:
    def __init__(self, tap: Tap, q: asyncio.Queue[Any]) -> None:
        self._tap, self._q = tap, q

    async def recv(self) -> tuple[bytes, int]:
        from aiortc.mediastreams import MediaStreamError

        item = await self._q.get()
        if item is None:
            raise MediaStreamError
        return item

    def stop(self) -> None:
        """No more packets; a slot waiting on this reader is woken (it then reads the tap it
        points at now: without this, a slot whose member left waited here for good and
        never carried anyone again)."""
        self._tap.subscribers.discard(self._q)
        while self._q.full():
            self._q.get_nowait()
        self._q.put_nowait(None)


class SlotTrack:
    """What the server sends on one audio slot of one page: the Opus packets of the member
    the slot is pointed at (a :class:`PacketTap` reader), re-timed so the slot's time line
    never jumps when it changes hands; while it points at nobody it waits (nothing is sent)."""

    FRAME = 960
    """20 ms at Opus's 48 kHz RTP clock: a packet's duration when its timestamps jump."""

    def __init__(self) -> None:
        from aiortc.mediastreams import MediaStreamTrack

        slot = self

        class _Track(MediaStreamTrack):
            kind = "audio"

            async def recv(self) -> Any:
                return await slot.next_packet()

        self.track = _Track()
        self.source: Any = None
        self.member = ""
        self._changed = asyncio.Event()
        self._pts = 0
        self._last: int | None = None

    def point(self, member: str, source: Any) -> None:
        """Send ``member``'s microphone (``source``, a tap reader) from now on; None: nobody."""
        old, self.source, self.member = self.source, source, member
        if old is not None:
            old.stop()
        self._last = None
        self._changed.set()

    async def next_packet(self) -> Any:
        from fractions import Fraction

        from aiortc.mediastreams import MediaStreamError
        from av import Packet

        while True:
            source = self.source
            if source is None:
                self._changed.clear()
                await self._changed.wait()
                continue
            try:
                data, timestamp = await source.recv()
            except MediaStreamError:
                if self.source is source:
                    self.source, self.member = None, ""
                continue
            if self.source is not source:
                continue
            step = (timestamp - self._last) % 2**32 if self._last is not None else self.FRAME
            self._last = timestamp
            self._pts += step if 0 < step <= 6 * self.FRAME else self.FRAME
            packet = Packet(data)
            packet.pts = self._pts
            packet.time_base = Fraction(1, 48000)
            return packet


class _Member:
    def __init__(self, name: str) -> None:
        self.name = name
        self.audio: PacketTap | None = None
        self.slots: list[SlotTrack] = []
        self.mids: list[str] = []


class MediaRoom:
    """One room's audio in the media process: each member's microphone is decoded once (its
    level measured) and its packets forwarded, as they came, to a slot of every other
    member (:class:`PacketTap`). With Redis (``voices``: a callable giving the process's
    :class:`RedisVoices`, or None), the members on the room's other servers are heard too
    (:class:`RemoteVoice`), and this server's members' packets are relayed to them while
    there are any."""

    def __init__(self, name: str, publish: Any, voices: Any = None) -> None:
        self.name = name
        self._publish = publish
        self._voices = voices
        self.remote: dict[str, RemoteVoice] = {}
        """The voices of the members on the room's other servers, by name."""
        self.others: set[str] = set()
        """The members on the room's other servers (as the server said last): while there
        are any, this server's voices are relayed to them."""
        self.relayed: dict[str, list[int]] = {}
        """Member -> [packets, bytes] relayed through Redis since last logged."""
        self.members: dict[str, _Member] = {}
        self.levels: dict[str, float] = {}
        self._drains: dict[str, asyncio.Task[None]] = {}

    def hooks(self, name: str) -> Any:
        from articast.service.webrtc import PeerHooks

        room, member = self, _Member(name)

        class Hooks(PeerHooks):
            mids = member.mids

            def prepare(self, pc: Any) -> None:
                for t in pc.getTransceivers():
                    if t.kind == "audio" and t._offerDirection == "sendonly":  # page receives
                        slot = SlotTrack()
                        t.direction = "sendonly"
                        t.sender.replaceTrack(slot.track)
                        member.slots.append(slot)
                        member.mids.append(t.mid)
                room.members[name] = member
                room.route()

            def audio(self, track: Any, receiver: Any = None) -> bool:
                if receiver is None:
                    return False
                try:
                    room.microphone(member, track, receiver)
                except RuntimeError as exc:  # drained, not relayed: the room goes on, mute
                    log.warning("room %s: %s's microphone: %s", room.name, name, exc)
                    return False
                return True

            def leave(self) -> None:
                room.remove(member)

        return Hooks()

    def microphone(self, member: _Member, track: Any, receiver: Any) -> None:
        """A member's microphone arrived: decoded (its level measured) always, its packets
        forwarded to the others."""
        member.audio = PacketTap(receiver)  # RuntimeError: nothing changed yet
        member.audio.relay = lambda payload, timestamp: self._relay(member.name, payload,
                                                                    timestamp)
        self._drains[member.name] = asyncio.ensure_future(self._drain(member, track))
        self.route()

    async def _drain(self, member: _Member, track: Any) -> None:
        import numpy as np
        from aiortc.mediastreams import MediaStreamError

        try:
            while True:
                frame = await track.recv()
                pcm = frame.to_ndarray().astype(np.float32) / 32768.0
                self.levels[member.name] = float(np.sqrt(np.mean(pcm * pcm)))
        except MediaStreamError:
            pass
        finally:
            if member.audio is not None:
                member.audio.end()

    def _relay(self, name: str, payload: bytes, timestamp: int) -> None:
        """One packet of a member's microphone to the room's other servers, if it has any."""
        if not self.others or self.members.get(name) is None:
            return
        voices = self._voices() if self._voices is not None else None
        if voices is not None:
            count = self.relayed.setdefault(name, [0, 0])
            count[0] += 1
            count[1] += voices.publish(self.name, name, payload, timestamp,
                                       self.levels.get(name, 0.0))

    def set_remote(self, names: list[str]) -> None:
        """The members on the room's other servers are ``names`` (from the server's reading
        of the room's Redis membership): their voices are read from Redis, ours relayed."""
        self.others = set(names) - set(self.members)
        # (the process's Redis connection is made when the room first has members elsewhere)
        voices = self._voices() if self._voices is not None and self.others else None
        changed = False
        for gone in [n for n in self.remote if n not in self.others]:
            for m in self.members.values():
                for s in m.slots:
                    if s.member == gone:
                        s.point("", None)
            self.remote.pop(gone).close()
            changed = True
        if voices is not None:
            for new in self.others - set(self.remote):
                self.remote[new] = RemoteVoice(voices, self.name, new)
                changed = True
        if changed:
            self.route()

    def log_voices(self, period: float) -> None:
        """One line on the voices through Redis (``--log-level info``), then counted anew."""
        parts = []
        for name, (packets, size) in sorted(self.relayed.items()):
            parts.append(f"{name}'s voice out: {packets / period:.1f} packets/s, "
                         f"{size / period / 1e3:.2f} kB/s")
        for name, v in sorted(self.remote.items()):
            d = sorted(v.delays)
            hop = (f", Redis hop p50 {1e3 * d[len(d) // 2]:.2f} ms, p95 "
                   f"{1e3 * d[int(0.95 * (len(d) - 1))]:.2f} ms, max {1e3 * d[-1]:.2f} ms"
                   if d else "")
            parts.append(f"{name}'s voice in: {v.packets / period:.1f} packets/s, "
                         f"{v.bytes / period / 1e3:.2f} kB/s{hop}")
            v.packets = v.bytes = 0
            v.delays = []
        self.relayed = {}
        if parts:
            log.info("room %s, voices through Redis over %g s: %s", self.name, period,
                     "; ".join(parts))

    def route(self) -> None:
        """Point every member's free slots at the other members' microphones (on this server
        or, through Redis, on another)."""
        sources: dict[str, Tap] = {o.name: o.audio for o in self.members.values()
                                   if o.audio is not None}
        for n, v in self.remote.items():
            sources.setdefault(n, v.tap)
        for m in self.members.values():
            carried = {s.member for s in m.slots if s.source is not None}
            for name, tap in sources.items():
                if name == m.name or name in carried:
                    continue
                free = next((s for s in m.slots if s.source is None), None)
                if free is None:
                    break
                free.point(name, tap.subscribe())
                carried.add(name)
        self.publish()

    def remove(self, member: _Member) -> None:
        drain = self._drains.get(member.name)
        if drain is not None and member.audio is not None and self.members.get(
                member.name) in (None, member):
            self._drains.pop(member.name).cancel()
        if self.members.get(member.name) is not member:
            return
        del self.members[member.name]
        for m in self.members.values():
            for s in m.slots:
                if s.member == member.name:
                    s.point("", None)
        for s in member.slots:
            s.point("", None)
        self.levels.pop(member.name, None)
        self.route()

    def publish(self) -> None:
        routes: dict[str, dict[str, Any]] = {
            m.name: {"slots": {s.member: mid for s, mid in zip(m.slots, m.mids, strict=True)
                               if s.member},
                     "level": round(self.levels.get(m.name, 0.0), 4)}
            for m in self.members.values()}
        for n, v in self.remote.items():  # members on other servers: their level, no slots
            routes.setdefault(n, {"slots": {}, "level": round(v.level, 4), "remote": True})
        self._publish(routes)

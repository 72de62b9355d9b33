"""Browser ingest: a participant's camera received over WebRTC (aiortc) becomes a session.

``POST /api/sessions/NAME/webrtc`` (:mod:`.http_sessions`) takes the join page's SDP
offer (``clients/web/join.html``) and answers it; the video track's frames are pushed into
the session's :class:`Feed`, a one-frame slot like a camera's, whose forwarder thread hands
the newest frame to the session's current worker (thread or process) through a pipe; the
worker reads it as a ``webrtc:NAME`` source (:class:`articast.service.sources.WebRTCSource`).
A frame the worker was too busy to take is replaced by the next one (counted in
:attr:`Feed.dropped`), as a camera's is. The participant leaving (the peer connection closed
or failed, the track ended) ends that session and no other; the same name can join again.

aiortc is an optional dependency (the ``webrtc`` extra): it is imported only when an offer
arrives, and :func:`missing` says in one line why ingest is off without it. Nothing here is
stored: frames live in memory until the next one replaces them.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger("articast.webrtc")

MAX_SDP_CHARS = 60000
"""An offer of one video and one audio track is 3-8 kB; far larger is not an offer."""


def missing() -> str:
    """Why WebRTC ingest cannot run here ("" when it can)."""
    try:
        import aiortc  # noqa: F401
    except ImportError as exc:
        return (f"WebRTC ingest needs aiortc, which is not installed ({exc}): "
                "pip install 'articast[webrtc]'")
    return ""


class Feed:
    """The newest frame of one participant, forwarded to the session's worker.

    :meth:`push` (the event loop) replaces the slot; a forwarder thread sends the slot's frame
    to the current inlet's writer, blocking only itself while the worker is busy;
    :meth:`new_inlet` (a new worker) hands it a new pipe; :meth:`close` sends the end.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._cond = threading.Condition()
        self._slot: tuple[float, Any, float] | None = None
        """(media time, the decoded frame, arrival): converted to I420 bytes by the
        forwarder thread, only when sent (most frames are replaced before a busy worker
        takes them) and never on the event loop."""
        self._writer: Any = None
        self._next_writer: Any = None
        self.ended = ""
        """Why the feed ended ("" while the participant is there)."""
        self.received = 0
        self.dropped = 0
        self.size: tuple[int, int] = (0, 0)
        """The last frame's (width, height): the browser lowers it when short of CPU or
        bandwidth (:attr:`resized` counts the changes)."""
        self.resized = 0
        self.on_close: Callable[[], None] | None = None
        """Closes the peer connection (set by :func:`answer`)."""
        self.peer: Any = None
        """The peer connection (set by :func:`answer`; its stats are logged)."""
        self.rtp: dict[str, tuple[int, int]] = {}
        """kind -> (RTP packets received, lost) as the receivers last counted."""
        self.on_end: Callable[[str], None] | None = None
        """Told why, once, when the feed ends (the media process tells the server)."""
        self._thread = threading.Thread(target=self._forward, name=f"feed {name}",
                                        daemon=True)
        self._thread.start()

    def push(self, t: float, frame: Any, arrived: float | None = None) -> None:
        """A frame of media time ``t``: an ``av.VideoFrame``, or ``(width, height,
        i420_bytes)``; ``arrived``: ``time.monotonic()`` when the server received it (the
        frame's capture time on the server's clock: the tracker reads it later, after the
        pipe and the previous frame's tracking). Cheap: called on the event loop."""
        with self._cond:
            if self.ended:
                return
            self.received += 1
            self.dropped += self._slot is not None
            size = (frame[0], frame[1]) if isinstance(frame, tuple) else (frame.width,
                                                                          frame.height)
            self.resized += self.size != (0, 0) and size != self.size
            self.size = size
            self._slot = (t, frame, time.monotonic() if arrived is None else arrived)
            self._cond.notify_all()

    def new_inlet(self) -> Any:
        """The reading end of a new pipe for a new worker; the forwarder writes there next
        (after the end, the pipe holds just the end)."""
        reader, writer = multiprocessing.Pipe(duplex=False)
        self.attach(writer)
        return reader

    def attach(self, writer: Any) -> None:
        """The writing end of a new worker's pipe (made here, or by the server and handed to
        the media process): the forwarder writes there next."""
        with self._cond:
            if not self.ended:
                if self._next_writer is not None:
                    self._next_writer.close()
                self._next_writer = writer
                self._cond.notify_all()
                return
        writer.send(("end", self.ended))  # a few bytes: never blocks
        writer.close()

    def close(self, reason: str) -> None:
        """The participant left (or the session was removed): the worker gets the end."""
        with self._cond:
            if self.ended:
                return
            self.ended = reason
            self._cond.notify_all()
        on_close, self.on_close = self.on_close, None
        if on_close is not None:
            on_close()
        on_end, self.on_end = self.on_end, None
        if on_end is not None:
            on_end(reason)

    def _next(self) -> tuple[Any, Any] | None:
        """(writer, item) to send next; None when the feed ended and was said."""
        with self._cond:
            while True:
                if self._next_writer is not None:  # a new worker: the old one is gone
                    if self._writer is not None:
                        self._writer.close()
                    self._writer, self._next_writer = self._next_writer, None
                if self._writer is not None and (self._slot is not None or self.ended):
                    item: Any = self._slot if self._slot is not None else ("end", self.ended)
                    self._slot = None
                    return self._writer, item
                if self.ended:
                    return None
                self._cond.wait()

    @staticmethod
    def _message(slot: tuple[float, Any, float]) -> tuple[float, int, int, bytes, float]:
        """The worker's message for a slot: ``(t, width, height, i420_bytes, arrived)``."""
        t, frame, arrived = slot
        if isinstance(frame, tuple):
            width, height, i420 = frame
        else:  # av.VideoFrame: the conversion copies the planes (with the GIL released)
            width, height = frame.width, frame.height
            i420 = frame.to_ndarray(format="yuv420p").tobytes()
        return (t, width, height, i420, arrived)

    def _forward(self) -> None:
        while (job := self._next()) is not None:
            writer, item = job
            if item[0] != "end":
                item = self._message(item)
            try:
                writer.send(item)  # blocks while the worker is busy: the slot fills meanwhile
                if item[0] != "end":
                    continue
            except (OSError, ValueError):  # that worker is gone: wait for the next one
                pass
            with self._cond:
                if self._writer is writer:
                    self._writer = None
            writer.close()


class PeerHooks:
    """What a room adds to a participant's peer connection (:mod:`articast.service.room`):
    :meth:`prepare` sees the connection once the offer is read, before the answer (it may
    turn the offer's receive-only audio transceivers into the server's senders);
    :meth:`audio` gets the participant's microphone track (without hooks it is drained)."""

    def prepare(self, pc: Any) -> None:  # pragma: no cover - the default does nothing
        pass

    def audio(self, track: Any, receiver: Any = None) -> bool:  # pragma: no cover
        """True when the track (of ``receiver``) was taken (and will be read); False: drain
        it."""
        return False


async def answer(offer_sdp: str, feed: Feed, hooks: PeerHooks | None = None) -> str:
    """Answer a participant's offer: returns the answer's SDP. Raises ValueError (one line)
    for an offer that cannot be answered. The video track's frames go to ``feed``; an audio
    track goes to ``hooks`` (a room relays it) or is received and dropped; the peer
    connection closing, failing or the video ending closes ``feed``."""
    from aiortc import RTCPeerConnection, RTCSessionDescription
    from aiortc.mediastreams import MediaStreamError

    pc = RTCPeerConnection()
    tasks: list[asyncio.Task[None]] = []
    loop = asyncio.get_running_loop()

    def close_peer() -> None:  # from any thread
        def close() -> None:
            for task in tasks:
                task.cancel()
            asyncio.ensure_future(pc.close())

        loop.call_soon_threadsafe(close)

    async def pump_video(track: Any) -> None:
        t0: float | None = None
        try:
            while True:
                frame = await track.recv()
                arrived = time.monotonic()
                t_media = frame.time if frame.time is not None else time.monotonic()
                t0 = t_media if t0 is None else t0
                # the frame as decoded: the feed's thread converts it if a worker takes it
                feed.push(t_media - t0, frame, arrived)
        except MediaStreamError:
            feed.close("the participant's video ended")

    async def drain(track: Any) -> None:
        try:
            while True:
                await track.recv()
        except MediaStreamError:
            pass

    @pc.on("track")
    def on_track(track: Any) -> None:
        if track.kind == "audio" and hooks is not None:
            receiver = next((r for r in pc.getReceivers() if r.track is track), None)
            if hooks.audio(track, receiver):
                return
        pump = pump_video if track.kind == "video" else drain
        tasks.append(asyncio.ensure_future(pump(track)))

    @pc.on("iceconnectionstatechange")
    async def on_ice() -> None:  # "failed" after a connection: consent checks went unanswered
        log.info("participant %s: ICE %s (received %d frames)", feed.name,
                 pc.iceConnectionState, feed.received)

    @pc.on("connectionstatechange")
    async def on_state() -> None:
        log.info("participant %s: %s", feed.name, pc.connectionState)
        if pc.connectionState in ("failed", "closed"):
            feed.close(f"the participant left (connection {pc.connectionState})")

    try:
        await pc.setRemoteDescription(RTCSessionDescription(sdp=offer_sdp, type="offer"))
        if any(r.track is not None and r.track.kind == "video" for r in pc.getReceivers()):
            if hooks is not None:
                hooks.prepare(pc)
            await pc.setLocalDescription(await pc.createAnswer())
            problem = ""
        else:
            problem = "the offer has no video track (the page sends the camera)"
    except Exception as exc:  # noqa: BLE001 - aiortc's parse errors: one line to the client
        first = str(exc).splitlines()[0] if str(exc).strip() else ""
        problem = "not a usable SDP offer: " + (
            first or f"aiortc could not read it ({type(exc).__name__})")
    if problem:
        await pc.close()
        raise ValueError(problem)
    feed.on_close = close_peer
    feed.peer = pc
    return pc.localDescription.sdp


async def count_rtp(feed: Feed) -> None:
    """Update ``feed.rtp`` from its peer connection's receivers (packets received, lost)."""
    pc = feed.peer
    if pc is None:
        return
    counts: dict[str, tuple[int, int]] = {}
    for receiver in pc.getReceivers():
        try:
            report = await receiver.getStats()
        except Exception:  # noqa: BLE001 - a closing connection: no figures this time
            continue
        for stats in report.values():
            if getattr(stats, "type", "") == "inbound-rtp":
                got, lost = counts.get(stats.kind, (0, 0))
                counts[stats.kind] = (got + stats.packetsReceived, lost + stats.packetsLost)
    feed.rtp = counts

"""Sessions (one per face) and the manager that runs several, restarts them, and stops them.

A :class:`Session` lives on the server's event loop. It supervises one worker at a time
(:mod:`articast.service.worker`), turns the worker's messages into hub events (frames, status,
ready),
and keeps the session's metrics. A crashed worker is restarted with backoff; a session whose
input is wrong (corrupt file, bad model) is reported ``failed`` once and not restarted; nothing
a session does can take the server down.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from articast.core.errors import InputError
from articast.service.hub import Hub
from articast.service.jsonsafe import dumps
from articast.service.metrics import SessionMetrics
from articast.service.settings import CaptureSettings, SessionPolicy
from articast.service.sources import check_uri, parse_uri
from articast.service.wire import FrameEvent, FrameRecord, ReadyEvent, StatusEvent, now
from articast.service.worker import ProcessWorker, SessionSpec, ThreadWorker, alive_interval

log = logging.getLogger("articast.session")
NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
TERMINAL = ("ended", "failed", "stopped")
PROBLEMS = ("unavailable", "failed")
TOLD = (*PROBLEMS, "ended")
"""States logged on the console at the default level (warning), with their reason (a crash
is logged where the restart is decided); a session that ended says so too."""
JOIN_TIMEOUT_S = 5.0
"""How long a stopped worker may take to finish its frame before its process is terminated."""


class Session:
    def __init__(self, spec: SessionSpec, sid: int, manager: SessionManager) -> None:
        self.spec, self.sid, self._m = spec, sid, manager
        self.state, self.detail = "starting", ""
        self.description: dict[str, Any] | None = None
        self.source_info: dict[str, Any] | None = None
        self.processor = ""
        self.worker_kind = ""
        self.metrics = SessionMetrics()
        self._mesh: tuple[np.ndarray, np.ndarray] | None = None
        self.outputs: Any = None  # articast.service.outputs.Outputs when the model has FAP points
        self._dense: bytes | None = None
        self._delegate: bytes | None = None
        self._worker: ThreadWorker | ProcessWorker | None = None
        self._vmc_model: Any = None
        self.preview: tuple[int, bytes] | None = None
        """(seq, JPEG) of the newest preview frame, when the session opted in."""
        self.neutral: tuple[tuple[float, ...], tuple[float, ...]] | None = None
        """The speaker's neutral head pose (rotation, translation): the first good frame, or
        the first after :meth:`recentre`. The streamed relative pose, the VMC head and the
        head FAPs are relative to it."""
        self._done = asyncio.Event()
        self._generation = 0
        """Which worker's messages count: bumped for each worker and when one is given up
        (a stalled thread cannot be killed; its late frames and its "stopped" are ignored)."""
        self.settled = asyncio.Event()
        """Set at the first frame, or when the session reports a problem (unavailable,
        failed, ended, restarting): what ``serve`` waits for before printing its URL."""
        self.streaming = asyncio.Event()
        """Set at the first frame: what ``serve`` waits for before printing its URL (a
        problem is said on the console meanwhile)."""
        self._outcome: tuple[str, str] = ("", "")
        self._stopping = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._loop = asyncio.get_running_loop()
        self._last_activity = time.monotonic()
        self._ready = False
        """The current worker said ``ready`` (source open, processor built): from then on it
        is ``running`` and held to the stall bound; before, to the longer start bound."""

    # ----------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._task = asyncio.create_task(self._supervise(), name=f"session {self.spec.name}")

    async def stop(self, timeout: float = 5.0) -> None:
        self._stopping.set()
        if self._worker is not None:
            self._worker.stop()
        if self._task is not None:
            try:
                await asyncio.wait_for(asyncio.shield(self._task), timeout)
            except TimeoutError:
                self._task.cancel()
        self._set_state("stopped", "session removed")

    @property
    def up(self) -> bool:
        return self.state == "running"

    def subscriber_arrived(self) -> None:
        if self._worker is not None:
            if not self._worker.go.is_set():
                self._last_activity = time.monotonic()  # the stall clock starts now
            self._worker.go.set()

    async def _supervise(self) -> None:
        try:
            await self._run_workers()
        finally:
            self._m.release_thread(self)

    async def _run_workers(self) -> None:
        policy = self._m.policy
        delay = policy.restart_initial_s
        while not self._stopping.is_set():
            self._done.clear()
            worker = self._worker = self._m.make_worker(self)
            self.worker_kind = worker.kind
            self._ready = False
            started = time.monotonic()
            try:
                # off the loop: a process worker's start waits for the fork server's fork
                # (seconds on a loaded machine, the first time while it imports), and the
                # loop meanwhile answers WebRTC's ICE checks and its sockets
                await asyncio.to_thread(worker.start)
                if not self.spec.wait_for_subscriber or self._m.hub.subscriber_count(
                        self.spec.name):
                    worker.go.set()
                self._last_activity = time.monotonic()
                await self._watch(worker)
            finally:
                worker.stop()
                await asyncio.to_thread(worker.join, JOIN_TIMEOUT_S)
            outcome, detail = self._outcome
            if self._stopping.is_set():
                return
            if outcome == "stopped":  # the worker alone was stopped (SIGTERM): not a crash
                self._set_state("stopped", detail or "the worker was stopped (SIGTERM)")
                return
            if outcome in ("ended", "failed"):
                self._set_state(outcome, detail)
                return
            self.metrics.restarts += 1
            if time.monotonic() - started > 60:
                delay = policy.restart_initial_s
            if self.metrics.restarts > policy.max_restarts:
                self._set_state("failed", f"crashed {self.metrics.restarts} times; last: {detail}")
                return
            self._set_state("restarting", f"{detail}; restarting in {delay:.1f} s")
            log.warning("session %s crashed: %s", self.spec.name, detail)
            try:
                await asyncio.wait_for(self._stopping.wait(), delay)
                return
            except TimeoutError:
                delay = min(delay * 2, policy.restart_max_s)

    async def _watch(self, worker: ThreadWorker | ProcessWorker) -> None:
        """Wait for the worker's end; declare it ``stalled`` and kill it if a running session
        produces nothing for ``worker_stall_s`` (a hung process, a frozen driver), or a
        starting one reports nothing for ``worker_start_s`` (a first run builds caches and
        compiles for several seconds, saying so: it is not stalled)."""
        policy = self._m.policy
        bounds = [b for b in (policy.worker_stall_s, policy.worker_start_s) if b > 0]
        tick = max(0.05, min(1.0, min(bounds) / 4)) if bounds else None
        while not self._done.is_set():
            try:
                await asyncio.wait_for(self._done.wait(), tick)
            except TimeoutError:
                quiet = time.monotonic() - self._last_activity
                starting = not self._ready and self.state in ("starting", "restarting")
                limit = policy.worker_start_s if starting else policy.worker_stall_s
                if ((self.state == "running" or starting) and worker.go.is_set() and limit > 0
                        and quiet > limit and not self._stopping.is_set()):
                    what = "still starting, nothing" if starting else "nothing"
                    log.warning("session %s stalled: %s for %.1f s", self.spec.name, what, quiet)
                    self._set_state("stalled", f"{'no start' if starting else 'no frame'} for "
                                    f"{quiet:.1f} s; restarting the worker")
                    self._outcome = ("crashed", f"stalled: {'no start' if starting else 'no frame'}"
                                     f" for {quiet:.1f} s")
                    self._generation += 1  # its "stopped" must not overwrite "crashed"
                    self._done.set()
                    worker.kill()
                    return

    # ----------------------------------------------------------------------- worker messages
    def emitter(self) -> Callable[[tuple[Any, ...]], None]:
        """The ``emit`` of a new worker: its messages count until it is given up."""
        self._generation += 1
        generation = self._generation
        return lambda msg: self.emit_threadsafe(msg, generation)

    def emit_threadsafe(self, msg: tuple[Any, ...], generation: int | None = None) -> None:
        """Called by worker threads (and process readers): hand over to the event loop."""
        try:
            self._loop.call_soon_threadsafe(self._on_message, msg, generation)
        except RuntimeError:  # loop closed during shutdown
            pass

    def _on_message(self, msg: tuple[Any, ...], generation: int | None = None) -> None:
        if generation is not None and generation != self._generation:
            return  # a worker given up (stalled): it no longer speaks for the session
        kind = msg[0]
        if kind != "status" or (msg[1], msg[2]) != (self.state, self.detail):
            self._last_activity = time.monotonic()  # a repeated status is no sign of life
        if kind == "frame":
            self._on_frame(msg[1])
        elif kind == "status":
            if msg[1] == "running" and not self._ready:  # the source is open, the tracker not
                self._set_state("starting", msg[2] or "source open; loading the tracker")
            else:
                self._set_state(msg[1], msg[2])
        elif kind == "progress":  # a slow start says what it does: on the console, to clients
            log.warning("session %s: %s", self.spec.name, msg[1])
            if not self._ready:
                self._set_state("starting", msg[1])
        elif kind == "preview":
            self.preview = (msg[1], msg[2])
        elif kind == "ready":
            self._on_ready(msg[1], msg[2], msg[3])
        elif kind == "done":
            if not self._done.is_set():  # the watchdog's reason beats the kill's exit code
                self._outcome = (msg[1], msg[2])
            self._done.set()

    def _on_ready(self, desc: dict[str, Any], source: dict[str, Any], processor: str) -> None:
        self._ready = True
        self.description, self.source_info, self.processor = desc, source, processor
        g = desc.get("geometry")
        if g:
            k = len(desc["param_names"])
            self._mesh = (np.asarray(g["mean"], np.float32),
                          np.asarray(g["basis"], np.float32).reshape(k, -1))
        from articast.service.outputs import make_outputs

        self.outputs = make_outputs(desc)
        self.neutral = None
        if self.outputs is not None:
            desc["fapu"] = self.outputs.fapu
        self._dense = None
        if self._m.vmc is not None and self.outputs is not None:
            self._vmc_model = self.outputs.model
        if g:
            desc["dense_url"] = f"/api/sessions/{self.spec.name}/dense"
        if self.spec.preview:
            desc["preview_url"] = f"/api/sessions/{self.spec.name}/preview.jpg"
        self._delegate = None
        if self._m.delegates and self.delegate_file() is not None:
            desc["delegate_url"] = f"/api/sessions/{self.spec.name}/delegate"
        self._m.hub.publish(self.spec.name, ReadyEvent(self.spec.name))
        self._set_state("running", "")

    def recentre(self) -> None:
        """Take the next good frame as the speaker's neutral head pose (streamed relative
        pose, VMC head, head FAPs)."""
        self.neutral = None
        if self.outputs is not None:
            self.outputs.recentre()

    def dense_json(self) -> bytes:
        """JSON of the dense face of this session's model (cached; blocking: call from a
        worker thread, as FastAPI does for plain ``def`` routes)."""
        if self._dense is None:

            from articast.core.synthetic.dense import dense_face
            from articast.service.wire import model_from_description

            model = model_from_description(self.description or {})
            self._dense = dumps(dense_face(model).to_dict()).encode()
        return self._dense

    def delegate_file(self) -> Any:
        """The speaker folder's delegate file (:mod:`articast.service.delegate`), or None."""
        from articast.service.delegate import delegate_path

        try:
            return delegate_path(self.spec.speaker, self.spec.media_roots)
        except InputError:
            return None

    def delegate_json(self) -> bytes:
        """JSON of the speaker's delegate (cached; blocking, like :meth:`dense_json`). Raises
        :class:`InputError` when there is none or it does not fit the session's model."""
        if self._delegate is None:
            from articast.service.delegate import delegate_json

            path = self.delegate_file()
            if path is None or not self._m.delegates:
                raise InputError(f"session {self.spec.name!r} has no delegate")
            self._delegate = delegate_json(path, (self.description or {})["param_names"])
        return self._delegate

    def _on_frame(self, rec: FrameRecord) -> None:
        if self.description is None:
            return
        m = self.metrics
        if self.neutral is None and rec.quality["ok"]:
            self.neutral = (rec.rotation, rec.translation)
        ev = FrameEvent(self.spec.name, self.sid, rec, self.description["param_names"],
                        self._mesh, self.outputs, self.neutral)
        self._m.hub.publish(self.spec.name, ev)
        self.settled.set()
        self.streaming.set()
        if self._m.vmc is not None and self._vmc_model is not None:
            from articast.core.faces.upper import UpperFace
            from articast.core.model.camera import Pose
            from articast.core.tracking.result import TrackResult

            # the eyes and brows travel as the record's blocks: without them VMC sent the
            # head and the mouth only (no blinks, eye bones or brows; issue 39)
            upper = UpperFace.from_dicts(rec.eyes, rec.brows)  # None without them
            res = TrackResult(rec.frame, rec.t, np.asarray(rec.alpha),
                              Pose(np.asarray(rec.rotation), np.asarray(rec.translation)),
                              bool(rec.quality["ok"]), upper=upper)
            neutral = None if self.neutral is None else Pose(*map(np.asarray, self.neutral))
            self._m.vmc.send(res, self._vmc_model, neutral=neutral)  # UDP, never blocks
        t = now()
        m.publish_latency.observe(t - rec.t_tracked)
        m.track_latency.observe(rec.t_tracked - rec.t_capture)
        m.frames += 1
        m.frames_failed += not rec.quality["ok"]
        if not rec.quality["ok"]:
            why = str(rec.quality.get("reason") or "?")[:60]
            m.failed_reasons[why] = m.failed_reasons.get(why, 0) + 1
        m.source_dropped = rec.source_dropped
        m.fps.tick()
        m.residual.observe(rec.quality["residual"])
        m.last_residual = rec.quality["residual"]

    def _set_state(self, state: str, detail: str) -> None:
        if self.state in TERMINAL and state != "stopped":
            return
        if (state, detail) == (self.state, self.detail):
            return
        previous = self.state
        self.state, self.detail = state, detail
        if state in TOLD and previous != state:
            log.warning("session %s: %s%s", self.spec.name, state, f": {detail}" if detail else "")
        elif state in ("running", "starting") and previous in PROBLEMS:
            log.warning("session %s: %s again", self.spec.name,
                        "running" if state == "running" else "source open")
        if state in PROBLEMS or state in TERMINAL or state == "restarting":
            self.settled.set()
        self._m.hub.publish(self.spec.name, StatusEvent(self.spec.name, state, detail, now()))

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.spec.name, "sid": self.sid, "state": self.state,
                "detail": self.detail, "spec": self.spec.to_dict(), "source": self.source_info,
                "processor": self.processor, "worker": self.worker_kind,
                "subscribers": self._m.hub.subscriber_count(self.spec.name),
                "frames": self.metrics.frames, "fps": round(self.metrics.fps.rate(), 2),
                "restarts": self.metrics.restarts}


class SessionManager:
    """All sessions of one server."""

    def __init__(self, hub: Hub[Any], capture: CaptureSettings | None = None,
                 policy: SessionPolicy | None = None, record_dir: str = "") -> None:
        self.hub = hub
        self.capture = capture or CaptureSettings()
        self.policy = policy or SessionPolicy()
        self.record_dir = record_dir
        self.vmc: Any = None  # articast.service.vmc.VmcSender when the server sends VMC
        self.delegates = True
        """Offer each speaker's delegate (False: ``serve --no-delegate``)."""
        self.sessions: dict[str, Session] = {}
        self.feeds: dict[str, Any] = {}
        """Session name -> its :class:`articast.service.webrtc.Feed` (a participant's camera
        received over WebRTC): each worker of that session gets a fresh inlet of it."""
        self._next_sid = 1
        self._thread_owner: Session | None = None

    def make_worker(self, s: Session) -> ThreadWorker | ProcessWorker:
        """``auto``: a process per session that tracks images; at most one light session
        (ground truth passed through) in a thread of this process.

        A tracker holding the GIL in the server's process delays the event loop that sends
        its frames: with 14 ms of GIL-held work per 60 fps frame and 100 subscribers, p99
        latency was 17 ms (max 42) in a thread and 12 ms (max 21) in a process
        (benchmarks/latency.py --busy-ms 14). Passing ground truth through costs nothing, so
        the first such session skips the process start-up and the pipe hop.
        """
        kind = self.policy.worker
        if kind == "auto":
            light = s.spec.processor == "truth" or (
                s.spec.processor == "auto" and parse_uri(s.spec.source).kind == "replay-record")
            kind = "thread" if light and self._thread_owner in (None, s) else "process"
        alive_s = alive_interval(self.policy.worker_stall_s, self.policy.worker_start_s)
        spec = s.spec
        feed = self.feeds.get(spec.name)
        if feed is not None:  # frames received here reach the worker through a pipe
            spec = replace(spec, inlet=feed.new_inlet())
        if kind == "thread":
            self._thread_owner = self._thread_owner or s
            return ThreadWorker(spec, self.capture, self.record_dir, s.emitter(), alive_s)
        if kind == "process":
            return ProcessWorker(spec, self.capture, self.record_dir, s.emitter(), alive_s)
        raise InputError(f"worker must be auto, thread or process, not {kind!r}")

    def release_thread(self, s: Session) -> None:
        """``s`` no longer runs workers: the next session may track in this process."""
        if self._thread_owner is s:
            self._thread_owner = None

    async def add(self, spec: SessionSpec) -> Session:
        """Validate and start a session. Raises InputError (bad name/URI) or KeyError (taken)."""
        if not NAME_RE.match(spec.name):
            raise InputError(f"session name {spec.name!r}: 1-64 of letters, digits, _ . -")
        if spec.name in self.sessions:
            raise KeyError(spec.name)
        check_uri(spec.source)
        s = Session(spec, self._next_sid, self)
        self._next_sid += 1
        self.sessions[spec.name] = s
        s.start()
        return s

    async def remove(self, name: str) -> None:
        s = self.sessions.pop(name)
        await s.stop(self.policy.restart_max_s)
        self._drop_feed(name)

    def _drop_feed(self, name: str) -> None:
        feed = self.feeds.pop(name, None)
        if feed is not None:  # its peer connection too: the participant is told it ended
            feed.close("the session was removed")

    async def close(self, timeout: float = 5.0) -> None:
        names = list(self.sessions)
        await asyncio.gather(*(self._stop_one(n, timeout) for n in names))

    async def _stop_one(self, name: str, timeout: float) -> None:
        s = self.sessions.pop(name, None)
        if s is not None:
            await s.stop(timeout)
        self._drop_feed(name)

"""A session's worker: source -> capture thread -> processor -> records, in a thread or process.

The worker never talks to subscribers: it hands each message to ``emit`` (a thread-safe
hand-over to the event loop, or a pipe to the server process) and goes on. Messages are
tuples:

``("status", state, detail)``           source state changes (``unavailable``, ``running``)
``("progress", text)``                  what a slow start is doing (building caches,
                                        compiling): the session is starting, not stalled
``("ready", description, source, processor)``  once the source is open (hello can be sent)
``("frame", FrameRecord)``              one per tracked frame
``("preview", seq, jpeg_bytes)``        a few per second, when the session opted in
``("alive",)``                          every ``alive_s`` while a recording's gap is waited
                                        out, or while work known to finish runs (the
                                        kernels' compilation: :func:`busy`), a fraction of
                                        the stall bound (:func:`alive_interval`)
``("done", outcome, detail)``           last message: ``ended``, ``failed`` (bad input, not
                                        restarted), ``crashed`` (restarted) or ``stopped``

Recording (``--record``) happens here, after the frame was handed over, so disk latency never
delays subscribers and a crash of the server loses at most the frame in flight.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from articast.core.errors import ArticastError
from articast.core.safe_io import check_confined
from articast.core.tracking.result import TrackResult
from articast.service.capture import Capture
from articast.service.preview import PreviewPolicy, render_preview
from articast.service.processors import (
    COMPILING,
    ProcessorContext,
    kernels_on_disk,
    load_assets,
    load_speaker,
    make_processor,
    warm_up_kernels,
)
from articast.service.record import Recorder
from articast.service.settings import CaptureSettings
from articast.service.sources import RecordSource, make_source
from articast.service.wire import FrameRecord, describe, epoch

Emit = Callable[[tuple[Any, ...]], None]


@dataclass(frozen=True)
class SessionSpec:
    """One face: a name, a source URI, optional model/appearance/camera files, options."""

    name: str
    source: str
    model: str = ""
    appearance: str = ""
    camera: str = ""
    processor: str = "auto"
    wait_for_subscriber: bool = False
    """Hold the source until the first subscriber arrives (replays that must not be missed)."""
    options: dict[str, Any] = field(default_factory=dict)
    speaker: str = ""
    """A speaker folder from ``articast enroll``: model, appearance and camera in one, tracked
    with the face finder (overrides model/appearance/camera)."""
    preview: bool = False
    """Encode a small, low-rate JPEG preview of the tracked video with the fitted mesh
    (:mod:`articast.service.preview`). Off by default: it is a picture of a face."""
    media_roots: tuple[str, ...] = ()
    """For a session added over HTTP: every file it opens (source, each image of a folder,
    model, appearance, camera, speaker), at every open and restart, must resolve under these
    folders. Empty: the operator's own session, not confined."""
    inlet: Any = field(default=None, compare=False, repr=False)
    """For a ``webrtc:`` source: the reading end of the pipe its frames arrive on (one per
    worker, :meth:`articast.service.session.SessionManager.make_worker`); closed by the
    worker when it ends."""

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "source": self.source, "model": self.model,
                "appearance": self.appearance, "camera": self.camera,
                "processor": self.processor, "wait_for_subscriber": self.wait_for_subscriber,
                "options": dict(self.options), "speaker": self.speaker,
                "preview": self.preview}


class _Event(Protocol):  # what a worker needs of threading.Event
    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool: ...


def alive_interval(*bounds: float) -> float:
    """How often a worker that waits (a recording's gap) says it is alive: a quarter of the
    shortest stall bound (0: none), at most 1 s. A sign of life once per bound raced the
    watchdog: a message handed over late restarted the session."""
    return min([1.0, *(b / 4 for b in bounds if b > 0)])


WORKER_NICE = 5
"""A process worker's niceness above the server's: a tracker takes every CPU cycle it gets
(it tracks the newest frame, dropping the rest), while the server's event loop must answer
in time (WebRTC's ICE consent checks: half a second each; its UDP sockets' queues). At equal
priority two trackers on a loaded 2-core machine starved the loop until the participants'
connections expired (issue 41)."""

BUSY_MAX_S = 900.0
"""How long :func:`busy` work may say it is alive: the kernels compile in 30-180 s on a
loaded 2-core machine; a compilation still running after 15 minutes is taken for a hang and
left to the start watchdog."""


@contextlib.contextmanager
def busy(text: str, progress: Callable[[str], None], emit: Emit,
         alive_s: float) -> Iterator[None]:
    """Work that is known to finish (compiling the tracker's kernels): say what it is once,
    then ``("alive",)`` every ``alive_s`` while it runs (at most :data:`BUSY_MAX_S`). A first
    run's compilation outlasted --worker-start-s under load, was declared stalled, killed as
    a crash, and compiled again in the next worker (issue 39): compiling is starting."""
    progress(text)
    done = threading.Event()

    def beat() -> None:
        end = time.monotonic() + BUSY_MAX_S
        while not done.wait(alive_s) and time.monotonic() < end:
            emit(("alive",))

    threading.Thread(target=beat, daemon=True, name="alive while busy").start()
    try:
        yield
    finally:
        done.set()


def run_worker(spec: SessionSpec, capture_settings: CaptureSettings, record_dir: str,
               emit: Emit, stop: _Event, go: _Event, alive_s: float = 1.0) -> None:
    """Run one session until its source ends, ``stop`` is set, or it fails. Never raises."""
    capture: Capture | None = None
    recorder: Recorder | None = None
    try:
        while not go.wait(0.1):
            if stop.is_set():
                emit(("done", "stopped", ""))
                return
        said: set[str] = set()

        def progress(text: str) -> None:
            if text not in said:  # the kernels' compilation may be announced twice
                said.add(text)
                emit(("progress", text))

        def busy_with(text: str) -> contextlib.AbstractContextManager[None]:
            return busy(text, progress, emit, alive_s)

        source = make_source(spec.source, spec.media_roots)
        if spec.inlet is not None and hasattr(source, "inlet"):
            source.inlet = spec.inlet
        if _tracks(spec, source):  # a first run compiles while its source opens (caches)
            threading.Thread(target=_compile_kernels, args=(busy_with, _kernels_for(spec)),
                             daemon=True, name="compile kernels").start()
        if hasattr(source, "progress"):
            source.progress = progress
        capture = Capture(source, capture_settings,
                          lambda state, detail: emit(("status", state, detail))).start()
        while not capture.opened.wait(0.1):
            if stop.is_set():
                emit(("done", "stopped", ""))
                return
        if capture.error is not None:
            raise capture.error
        assert capture.info is not None
        finish = getattr(source, "finish", None)
        for path in (spec.speaker, spec.model, spec.appearance, spec.camera):
            if path:
                check_confined(path, spec.media_roots)
        speaker = load_speaker(spec.speaker, capture.info) if spec.speaker else None
        if speaker is not None:
            model, appearance, camera = speaker.model, speaker.appearance, speaker.camera
        else:
            model, appearance, camera = load_assets(spec.model, spec.appearance, spec.camera,
                                                    capture.assets, capture.info)
        # what the source knows (e.g. the synthetic rig and start pose), then the session's own
        ctx = ProcessorContext(spec.name, capture.info, model, camera, appearance,
                               {**capture.assets.extra, **dict(spec.options)}, speaker,
                               progress, busy_with)
        used, processor = make_processor(spec.processor, ctx)
        from articast.core.model.face import PARAM_NAMES

        desc = describe(model, camera, tuple(model.param_names) if model else PARAM_NAMES)
        source_info = capture.info.to_dict()
        emit(("ready", desc, source_info, used))
        if record_dir:
            recorder = Recorder(record_dir, spec.name, desc, source_info)
        seq = 0
        preview_policy, next_preview = PreviewPolicy(), 0.0
        next_alive = 0.0
        if spec.preview:
            from articast.service.overlay import lip_contours

            contours = lip_contours(speaker)
        while not stop.is_set():
            frame = capture.get(timeout=0.1)
            if frame is None:
                if capture.done:
                    break
                if capture.pacing and time.monotonic() >= next_alive:
                    # a recording's gap: the source is waiting for its media time, which the
                    # stall watchdog must not take for a hang (it restarted from frame 0)
                    next_alive = time.monotonic() + alive_s
                    emit(("alive",))
                continue
            if finish is not None:  # (a picture decoded only now: a frame from Redis)
                frame = finish(frame)
            t0 = time.perf_counter()
            result = processor.process(frame)
            ms = (time.perf_counter() - t0) * 1000.0
            t_tracked = time.monotonic()
            rec = _record(seq, frame.index, frame.t, epoch(frame.t_capture), epoch(t_tracked),
                          result, ms, capture.dropped, model)
            emit(("frame", rec))
            if spec.preview and frame.image is not None and time.monotonic() >= next_preview:
                next_preview = time.monotonic() + 1.0 / preview_policy.rate_hz
                emit(("preview", seq, render_preview(frame.image, model, camera, result,
                                                     preview_policy, contours)))
            if recorder is not None:
                recorder.write(rec)
            seq += 1
        if stop.is_set():
            emit(("done", "stopped", ""))
        elif capture.error is not None:
            raise capture.error
        else:
            emit(("done", "ended", f"source ended after {capture.frames} frames"))
    except ArticastError as exc:
        emit(("done", "failed", str(exc)))
    except Exception as exc:  # noqa: BLE001 - a crash is reported and the session restarted
        detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        emit(("done", "crashed", detail))
    finally:
        if capture is not None:
            capture.stop()
        if recorder is not None:
            recorder.close()
        if spec.inlet is not None:  # the feed's writer then knows this worker is gone
            spec.inlet.close()


def _tracks(spec: SessionSpec, source: Any) -> bool:
    """Whether the session will run the tracker (not ground truth passed through)."""
    return spec.processor in ("auto", "tracker", "live") and not isinstance(
        source, RecordSource)


def _kernels_for(spec: SessionSpec) -> tuple[str, ...] | None:
    """The compiled kernels a tracking session will call: the live tracker's (a speaker), all;
    else the appearance tracker's (``articast demo``; a participant without a speaker)."""
    if spec.speaker or spec.processor == "live":
        return None
    from articast.core.tracking.kernels import TRACKER

    return TRACKER


def _compile_kernels(busy_with: Callable[[str], contextlib.AbstractContextManager[None]],
                     only: tuple[str, ...] | None = None) -> None:
    """Compile the tracker's kernels (``only``: those) if numba's cache lacks them (a first
    run), saying so and that it is alive; in a thread beside the source's opening, which on
    a first run builds its own caches."""
    if not kernels_on_disk(only):
        with busy_with(COMPILING):
            warm_up_kernels(only)


def _record(seq: int, index: int, t: float, t_capture: float, t_tracked: float,
            result: TrackResult, ms: float, source_dropped: int, model: Any = None
            ) -> FrameRecord:
    """A picklable, JSON-safe record: non-finite values never reach the wire (JSON has no NaN).

    Lip measures come from the result, else from ``model`` at the result's alpha (e.g. a
    ground-truth processor), else None."""
    alpha = [float(a) for a in result.alpha]
    ok, reason = bool(result.ok), str(result.reason)
    if not all(math.isfinite(a) for a in alpha):
        alpha = [a if math.isfinite(a) else 0.0 for a in alpha]
        ok, reason = False, reason or "the processor returned non-finite parameters"
    residual = float(result.residual)
    return FrameRecord(
        seq=seq, frame=index, t=t, t_capture=t_capture, t_tracked=t_tracked,
        alpha=tuple(alpha), rotation=tuple(float(v) for v in result.pose.rotation),
        translation=tuple(float(v) for v in result.pose.translation),
        quality={"ok": ok, "reason": reason,
                 "residual": residual if math.isfinite(residual) else -1.0,
                 "evals": int(result.evals), "iterations": int(result.iterations), "ms": ms},
        source_dropped=source_dropped,
        lips=_lips(result, model, alpha),
        eyes=None if result.upper is None else result.upper.eyes_dict(),
        brows=None if result.upper is None else result.upper.brows_dict(),
    )


def _lips(result: TrackResult, model: Any, alpha: list[float]) -> dict[str, float] | None:
    lips = result.lips
    if lips is None and model is not None:
        from articast.core.outputs.lips import lips_dict

        lips = lips_dict(model, np.asarray(alpha))
    if lips is None or not all(math.isfinite(v) for v in lips.values()):
        return None
    return {"aperture_mm": float(lips["aperture_mm"]), "width_mm": float(lips["width_mm"])}


# ----------------------------------------------------------------------------- runners
class ThreadWorker:
    """Runs :func:`run_worker` in a thread of the server process."""

    kind = "thread"

    def __init__(self, spec: SessionSpec, capture: CaptureSettings, record_dir: str,
                 emit: Emit, alive_s: float = 1.0) -> None:
        self.stop_event, self.go = threading.Event(), threading.Event()
        self._thread = threading.Thread(
            target=run_worker,
            args=(spec, capture, record_dir, emit, self.stop_event, self.go, alive_s),
            name=f"session {spec.name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self.stop_event.set()

    def kill(self) -> None:
        """A thread cannot be killed: told to stop, and abandoned if it does not."""
        self.stop_event.set()

    def join(self, timeout: float) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()


class _Flag:
    """``go``/``stop`` of a process worker, as seen by the server: a message on the pipe."""

    def __init__(self, conn: Any, word: str) -> None:
        self._conn, self._word, self._set = conn, word, False

    def set(self) -> None:
        if not self._set:
            self._set = True
            try:
                self._conn.send(self._word)
            except (OSError, ValueError):  # the worker is gone already
                pass

    def is_set(self) -> bool:
        return self._set


def _process_main(spec: SessionSpec, capture: CaptureSettings, record_dir: str,
                  conn: Any, alive_s: float = 1.0) -> None:
    """Worker process: control words (``go``, ``stop``) in, worker messages out, one pipe.

    A closed pipe (the server died) stops the worker, so no orphan keeps a camera open.
    """
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server stops us through the pipe
    with contextlib.suppress(OSError):  # tracking yields the CPU to the server's event loop
        os.nice(WORKER_NICE)
    stop, go = threading.Event(), threading.Event()
    # SIGTERM (systemd stops the whole group, terminate() after a join timeout) is a stop,
    # not a crash: finish the frame, say "stopped", exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    lock = threading.Lock()

    def control() -> None:
        while True:
            try:
                word = conn.recv()
            except (EOFError, OSError, TypeError, ValueError):
                # (closed, or closed by the finally below while we waited: its handle is
                # gone, which multiprocessing reports as a TypeError)
                stop.set()
                return
            (go if word == "go" else stop).set()

    def emit(msg: tuple[Any, ...]) -> None:
        with lock:
            try:
                conn.send(msg)
            except (OSError, ValueError):
                stop.set()

    threading.Thread(target=control, daemon=True).start()
    try:
        run_worker(spec, capture, record_dir, emit, stop, go, alive_s)
    finally:
        conn.close()


WORKER_MODULES = ("articast.service.worker", "articast.service.processors",
                  "articast.core.tracking.tracker", "articast.core.tracking.kernels",
                  "articast.core.synthetic", "articast.core.faces.live", "cv2", "numba",
                  "articast.service.preload")
"""What a worker process imports before its first frame (~1-2 s): preloaded once by the
fork server, so a worker starts as a fork of a process that has them."""


def _context() -> Any:
    """Workers fork from a fork server (a clean, single-threaded process that has imported
    :data:`WORKER_MODULES` once; no inherited threads, loop or sockets) where there is one;
    spawned elsewhere."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(list(WORKER_MODULES))
        return ctx
    return multiprocessing.get_context("spawn")


def start_worker_server() -> None:
    """Start the fork server now, in the background: it imports what workers need while the
    server imports its own (two cores, half the start-up). Idempotent; a failure only means
    the first worker starts it."""
    ctx = ProcessWorker._ctx
    if ctx.get_start_method() == "forkserver":
        try:
            from multiprocessing import forkserver

            forkserver.ensure_running()
        except (OSError, ValueError):  # pragma: no cover - started on first use instead
            pass


class ProcessWorker:
    """Runs :func:`run_worker` in its own process (forked from a fork server, or spawned: no
    inherited threads or loop).

    A reader thread in the server receives the worker's messages and passes them to ``emit``;
    if the process dies without saying ``done``, ``emit`` gets ``("done", "crashed", ...)``.
    The pipe carries no semaphores (unlike multiprocessing.Event), so nothing leaks when the
    server is killed.
    """

    kind = "process"
    _ctx = _context()

    def __init__(self, spec: SessionSpec, capture: CaptureSettings, record_dir: str,
                 emit: Emit, alive_s: float = 1.0) -> None:
        self._conn, child = self._ctx.Pipe(duplex=True)
        self._emit = emit
        self.stop_event, self.go = _Flag(self._conn, "stop"), _Flag(self._conn, "go")
        self.process = self._ctx.Process(
            target=_process_main, args=(spec, capture, record_dir, child, alive_s),
            name=f"articast session {spec.name}", daemon=True)
        self._child = child
        self._inlet = spec.inlet
        self._status = threading.Lock()
        """Held while the process's status is read: a forkserver process's exit code is a pipe
        read once, and two threads reading it raced (the loser took 255 for the code)."""
        self._reader = threading.Thread(target=self._read, name=f"reader {spec.name}",
                                        daemon=True)

    def start(self) -> None:
        self.process.start()
        self._child.close()  # the child holds the other end: EOF when it dies
        if self._inlet is not None:  # likewise its frames' pipe: the feed sees it die
            self._inlet.close()
        self._reader.start()

    def _read(self) -> None:
        done = False
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                break
            done = done or msg[0] == "done"
            self._emit(msg)
        self._wait(1.0)
        if not done:
            self._emit(("done", "crashed", f"worker process exited with code "
                        f"{self._exitcode()}"))

    def _wait(self, timeout: float) -> None:
        """Wait for the process to end (its sentinel; the status is not read here)."""
        from multiprocessing.connection import wait

        if self.process.pid is not None:  # (started)
            wait([self.process.sentinel], timeout)

    def _exitcode(self) -> int | None:
        with self._status:
            return self.process.exitcode

    def _running(self) -> bool:
        return self.process.pid is not None and self._exitcode() is None

    def stop(self) -> None:
        self.stop_event.set()

    def kill(self) -> None:
        """SIGKILL: the one signal a stopped (SIGSTOP) or hung process cannot ignore."""
        if self._running():
            self.process.kill()

    def join(self, timeout: float) -> bool:
        self._wait(timeout)
        if self._running():
            self.process.terminate()
            self._wait(1.0)
        if self._running():  # stuck in native code: SIGTERM waits for it
            self.process.kill()
            self._wait(1.0)
        if self._reader.is_alive():
            self._reader.join(1.0)
        self._conn.close()
        return not self._running()

"""The capture thread: reads a source, keeps only the newest frame in a one-frame slot.

* Live sources (cameras) and ``pace=realtime`` playback: a new frame replaces an unread one and
  the replaced frame is counted in :attr:`Capture.dropped` — a slow tracker never builds a
  queue, it just sees the newest frame.
* ``pace=fast`` playback is lossless: the thread waits until the slot is taken.
* ``pace=realtime`` playback drops a frame only for a consumer that did not keep up: each
  frame stays in the slot for its media period (until the next frame's media time, counted
  from when it was put), and a consumer already waiting for it is always handed it first. A
  capture thread that was descheduled puts its late frames back to back, and replaced the one
  an idle consumer had not been scheduled to take yet: a recording lost frames under load.
* Playback (files, recordings, the synthetic speaker) is not read before the consumer first
  asks for a frame: the frames a first run would render or decode, and drop, while its tracker
  compiles cost the compilation the CPU (issue 39: the demo's synthetic speaker, ~85 ms a
  frame, kept a core busy for the minute or two of a fresh install's compile). Cameras are
  read from the start (their driver's queue must not fill).
* :class:`~articast.service.sources.SourceUnavailable` (missing, busy, unplugged camera) is reported
  through ``on_status("unavailable", reason)`` and retried with exponential backoff.
* :class:`~articast.service.sources.SourceError` ends the capture with :attr:`Capture.error` set.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from articast.service.settings import CaptureSettings
from articast.service.source_types import Frame, Source, SourceAssets, SourceInfo, SourceUnavailable

StatusCallback = Callable[[str, str], None]


class Capture:
    def __init__(self, source: Source, settings: CaptureSettings | None = None,
                 on_status: StatusCallback | None = None) -> None:
        self.source = source
        self.settings = settings or CaptureSettings()
        self._on_status = on_status or (lambda state, detail: None)
        self._cond = threading.Condition()
        self._slot: Frame | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"capture {source.uri}",
                                        daemon=True)
        self.opened = threading.Event()
        self.info: SourceInfo | None = None
        self.assets = SourceAssets()
        self.error: BaseException | None = None
        self.finished = False
        self.frames = 0
        self.dropped = 0
        self.attempts = 0
        self.pacing = False
        """Waiting for the next frame's media time (a gap in a recording): not a stall."""
        self._lost = False  # unavailable since the last "running": say when it is back
        self._waiting = 0
        """Consumers inside :meth:`get` for a frame: idle, perhaps not yet scheduled."""
        self._slot_since = 0.0
        """When the frame in the slot was put (monotonic)."""
        self._wanted = threading.Event()
        """Set by the consumer's first :meth:`get`: playback is read from then on."""

    # ------------------------------------------------------------------ consumer side
    def start(self) -> Capture:
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout)

    def get(self, timeout: float) -> Frame | None:
        """The newest frame, or None after ``timeout`` s (check :attr:`done`)."""
        self._wanted.set()
        with self._cond:
            if self._slot is None and not self.finished:
                self._waiting += 1
                try:
                    self._cond.wait(timeout)
                finally:
                    self._waiting -= 1
            frame, self._slot = self._slot, None
            self._cond.notify_all()
            return frame

    @property
    def done(self) -> bool:
        """The source ended or failed and every frame was taken."""
        return self.finished and self._slot is None

    # ------------------------------------------------------------------ capture thread
    def _put(self, frame: Frame) -> None:
        lossless = not self.source.live and self.source.pace == "fast"
        paced = not self.source.live and not lossless
        with self._cond:
            while self._slot is not None and not self._stop.is_set():
                if lossless or (paced and self._waiting):
                    self._cond.wait(0.1)
                    continue
                # the unread frame's own period (its media time to this one's, at most 1 s),
                # from when it was put: a late capture thread does not shorten it
                left = (self._slot_since + min(max(frame.t - self._slot.t, 0.0), 1.0)
                        - time.monotonic()) if paced else 0.0
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.1))
            if self._slot is not None:
                self.dropped += 1
            self._slot, self._slot_since = frame, time.monotonic()
            self.frames += 1
            self._cond.notify_all()

    def _open(self) -> bool:
        """Open the source, retrying while it is unavailable. False if stopped meanwhile."""
        delay = self.settings.retry_initial_s
        while not self._stop.is_set():
            self.attempts += 1
            try:
                self.info = self.source.open()
                self.assets = self.source.assets()
                return True
            except SourceUnavailable as exc:
                self.source.close()
                self._lost = True
                self._on_status("unavailable", f"{exc}; retry {self.attempts} in {delay:.1f} s")
                if self._stop.wait(delay):
                    return False
                delay = min(delay * 2, self.settings.retry_max_s)
        return False

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, who reports it
            self.error = exc
        finally:
            self.source.close()
            with self._cond:
                self.finished = True
                self._cond.notify_all()
            self.opened.set()

    def _loop(self) -> None:
        index, t_offset, play = 0, 0.0, 0
        while not self._stop.is_set():
            if not self._open():
                return
            first_open = not self.opened.is_set()
            self.opened.set()
            if first_open or self._lost:  # not at every loop of a looping file
                self._on_status("running", "" if first_open else "source is back")
            self._lost = False
            t0_wall, t0_media, first_t, last_t = time.monotonic(), None, None, 0.0
            try:
                while not self._stop.is_set():
                    if not self.source.live and not self._wanted.is_set():
                        while not self._wanted.wait(0.1):  # nobody to give it to yet
                            if self._stop.is_set():
                                return
                        t0_wall = time.monotonic()  # paced from the first frame wanted
                    item = self.source.read()
                    if item is None:
                        break
                    t, image, truth = item
                    if not self.source.live and self.source.pace == "realtime":
                        t0_media = t if t0_media is None else t0_media
                        wait = t0_wall + (t - t0_media) - time.monotonic()
                        self.pacing = wait > 0
                        try:
                            if wait > 0 and self._stop.wait(wait):
                                return
                        finally:
                            self.pacing = False
                    last_t = t
                    first_t = t if first_t is None else first_t
                    # a source that knows when its frame arrived (WebRTC: received by the
                    # server before the pipe to this worker) says so; else: now
                    stamp = getattr(self.source, "captured", None)
                    self._put(Frame(index, t + t_offset,
                                    time.monotonic() if stamp is None else stamp, image, truth))
                    index += 1
            except SourceUnavailable as exc:
                self.source.close()
                self._lost = True
                self._on_status("unavailable", f"{exc}; reopening")
                continue
            self.source.close()
            if self.source.live and not getattr(self.source, "ends", False):
                continue  # a camera that stopped: reopened; a WebRTC peer that left: the end
            play += 1
            if self.source.loops and play >= self.source.loops:
                return
            # the next loop continues the time line one frame period after the last frame
            period = 1.0 / (self.info.fps if self.info and self.info.fps else 30.0)
            t_offset += last_t - (first_t or 0.0) + period  # a part (start=) begins late

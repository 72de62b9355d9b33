"""Frame sources, opened from a URI.

===================================================  ==========================================
``v4l2:/dev/video0?width=640&height=480&fps=60&fourcc=MJPG``  a camera through OpenCV's V4L2
                                                     backend; what the device actually gave is
                                                     reported in ``SourceInfo.detail``
``file:talk.mp4?pace=realtime|fast&loop=yes``        a video; timestamps from the container
``images:DIR?fps=30&pace=..&loop=..``                a folder of images in name order
``synthetic:seed=3&fps=60&pace=..&loop=..``          the built-in speaker, with ground truth
``replay-record:rec.jsonl?pace=..&loop=..``          a recording made by ``serve --record``
``webrtc:NAME?seed=1``                               a participant's browser camera, received
                                                     over WebRTC (:mod:`articast.service.ingest`);
                                                     ``seed``: track it with that synthetic
                                                     speaker's assets (no ``--speaker``)
===================================================  ==========================================

``loop=yes`` (or ``true``, ``on``, ``1``, ``forever``) plays a finite source forever,
``loop=no`` (``false``, ``off``, ``0``; the default) once, ``plays=N`` N times; then the
session is ``ended``. ``pace=realtime`` (the
default) delivers frames at their media time, ``pace=fast`` as fast as the tracker takes them,
losing none. A source only reads; pacing, looping, retries and the one-frame slot are the
capture thread's job (:mod:`articast.service.capture`).

Errors: :class:`SourceUnavailable` (a camera that is missing, busy or unplugged: retried with
backoff) and :class:`SourceError` (a wrong URI, a missing, corrupt or unreadable file: reported
once, never retried). Both are :class:`~articast.core.errors.ArticastError`.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl

import numpy as np

from articast.core.errors import InputError
from articast.core.tracking.result import TrackResult
from articast.service.record import parse_frame_line, read_header
from articast.service.source_types import (
    Frame,
    Source,
    SourceAssets,
    SourceError,
    SourceInfo,
    SourceUnavailable,
)


# ------------------------------------------------------------------------------- URI parsing
@dataclass(frozen=True)
class SourceURI:
    kind: str
    target: str
    params: dict[str, str]
    text: str


def parse_uri(uri: str) -> SourceURI:
    """Split ``kind:target?k=v&..`` (for ``synthetic:`` the target is itself ``k=v&..``)."""
    if not isinstance(uri, str) or ":" not in uri:
        hint = f" (a video file: file:{uri})" if isinstance(uri, str) and uri else ""
        raise SourceError(f"{uri!r}: a source is KIND:TARGET{hint}, KIND one of "
                          f"{sorted(SOURCE_KINDS)}")
    kind, rest = uri.split(":", 1)
    if kind not in SOURCE_KINDS:
        raise SourceError(f"{uri!r}: unknown source kind {kind!r}; known: {sorted(SOURCE_KINDS)}")
    target, _, query = rest.partition("?")
    if kind == "synthetic" and "=" in target:
        target, query = "", "&".join(x for x in (target, query) if x)
    params = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=False))
    known = SOURCE_KINDS[kind][1]
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise SourceError(f"{uri!r}: unknown option(s) {unknown} for {kind}; known: {known}")
    return SourceURI(kind, target, params, uri)


def _num(p: SourceURI, key: str, conv: Callable[[str], Any], default: Any, lo: float = 0) -> Any:
    if key not in p.params:
        return default
    try:
        v = conv(p.params[key])
    except ValueError:
        raise SourceError(f"{p.text!r}: {key}={p.params[key]!r} is not a number") from None
    if v < lo:
        raise SourceError(f"{p.text!r}: {key} must be >= {lo}")
    return v


LOOP_YES = ("yes", "true", "on", "1", "forever")
LOOP_NO = ("no", "false", "off", "0")


def loop_count(p: SourceURI) -> int:
    """Plays of a finite source (0 = forever) from ``loop=yes|no`` or ``plays=N``. ``loop``
    used to be a count in which 1 meant once: a ``loop=1`` that played once surprised
    everyone, so it is a switch now and a count has its own name."""
    loop = p.params.get("loop", "").strip().lower()
    if loop and loop not in LOOP_YES + LOOP_NO:
        raise SourceError(f"{p.text!r}: loop={p.params['loop']!r}: loop=yes plays forever, "
                          "loop=no once (the default); plays=N plays N times")
    plays = _num(p, "plays", int, None, 1)
    if plays is not None and loop in LOOP_YES:
        raise SourceError(f"{p.text!r}: loop=yes plays forever: drop it, or plays={plays}")
    if plays is not None:
        return int(plays)
    return 0 if loop in LOOP_YES else 1


class _Finite:
    """Pacing and looping options shared by every non-live source."""

    live = False
    roots: tuple[str, ...] = ()
    """Media roots the files must resolve under at every open (empty: not confined)."""

    def _open_file(self, path: Path) -> Any:
        """``path`` opened (a regular file, under the roots if any), as SourceError."""
        from articast.core.safe_io import open_confined

        try:
            return open_confined(path, self.roots)
        except InputError as exc:
            raise SourceError(str(exc)) from None

    def _playback(self, p: SourceURI) -> None:
        self.uri = p.text
        self.pace = p.params.get("pace", "realtime")
        if self.pace not in ("realtime", "fast"):
            raise SourceError(f"{p.text!r}: pace must be 'realtime' or 'fast'")
        self.loops = loop_count(p)

    def assets(self) -> SourceAssets:
        return SourceAssets()


# ------------------------------------------------------------------------------- V4L2
class V4L2Source:
    live = True
    pace = "realtime"
    loops = 1

    def __init__(self, p: SourceURI) -> None:
        self.uri = p.text
        self.device = p.target or "/dev/video0"
        self.want = {k: _num(p, k, int, None, 1) for k in ("width", "height")}
        self.want_fps = _num(p, "fps", float, None, 0.1)
        self.fourcc = p.params.get("fourcc", "")
        if self.fourcc and len(self.fourcc) != 4:
            raise SourceError(f"{p.text!r}: fourcc must be 4 characters, e.g. MJPG or YUYV")
        self._cap: Any = None
        self._t0 = 0.0

    def _index(self) -> int:
        real = os.path.realpath(self.device)
        name = os.path.basename(real)
        if self.device.isdigit():
            return int(self.device)
        if not os.path.exists(real):
            raise SourceUnavailable(f"{self.device}: no such device (camera not plugged in?)")
        if not (name.startswith("video") and name[5:].isdigit()):
            raise SourceError(f"{self.device}: not a V4L2 device node (/dev/videoN)")
        return int(name[5:])

    def open(self) -> SourceInfo:
        import cv2

        try:  # a missing camera is our status to report, not OpenCV's warning on stderr
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        except AttributeError:
            pass
        cap = cv2.VideoCapture(self._index(), cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise SourceUnavailable(f"{self.device}: cannot be opened (busy, or not a camera)")
        if self.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc))
        if self.want["width"]:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.want["width"])
        if self.want["height"]:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.want["height"])
        if self.want_fps:
            cap.set(cv2.CAP_PROP_FPS, self.want_fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a backlog in the driver
        code = int(cap.get(cv2.CAP_PROP_FOURCC))
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        got = {"width": width, "height": height, "fps": fps,
               "fourcc": "".join(chr((code >> 8 * i) & 0xFF) for i in range(4)).strip("\0")}
        self._cap, self._t0 = cap, time.monotonic()
        requested = {**self.want, "fps": self.want_fps, "fourcc": self.fourcc or None}
        return SourceInfo(self.uri, "v4l2", True, width, height, fps,
                          detail={"device": self.device, "requested": requested, "actual": got})

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        ok, image = self._cap.read()
        if not ok or image is None:
            raise SourceUnavailable(f"{self.device}: stopped delivering frames (unplugged?)")
        return time.monotonic() - self._t0, image, None

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def assets(self) -> SourceAssets:
        return SourceAssets()


# ------------------------------------------------------------------------------- video file
class FileSource(_Finite):
    """A video file; ``start``/``end`` (seconds, or frames with ``f``: ``start=12.5``,
    ``end=900f``) play a part of it, exactly (frames before the start are decoded and
    skipped)."""

    def __init__(self, p: SourceURI) -> None:
        from articast.service.video import Span

        self._playback(p)
        self.path = Path(p.target)
        if not p.target:
            raise SourceError(f"{p.text!r}: give a file, e.g. file:talk.mp4")
        try:
            self.span = Span(p.params.get("start"), p.params.get("end"), ("start", "end"))
        except InputError as exc:
            raise SourceError(f"{p.text!r}: {exc}") from None
        self._cap: Any = None
        self._fh: Any = None
        self._first: tuple[float, np.ndarray] | None = None
        self._n = 0

    def open(self) -> SourceInfo:
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # our error, not FFmpeg's noise
        import cv2

        from articast.service.video import VIDEO_SNIFF_BYTES, check_video_head, open_capture

        if not os.path.lexists(self.path):
            raise SourceError(f"{self.path}: no such file")
        self.close()
        self._fh = self._open_file(self.path)  # held open: OpenCV reads this very file
        try:  # a folder, FIFO or device failed above; text is no video (OpenCV "opens" it)
            check_video_head(os.pread(self._fh.fileno(), VIDEO_SNIFF_BYTES, 0), self.path)
        except InputError as exc:
            self.close()
            raise SourceError(str(exc)) from None

        cap = open_capture(f"/proc/self/fd/{self._fh.fileno()}" if self.roots
                           else str(self.path))
        if not cap.isOpened():
            cap.release()
            self.close()
            raise SourceError(f"{self.path}: not a readable video (OpenCV cannot decode it)")
        self._cap, self._n = cap, 0
        first = self._decode()
        if first is None and self._n == 0:
            cap.release()
            self.close()
            raise SourceError(f"{self.path}: corrupt or empty video (no frame could be decoded)")
        if first is None:
            cap.release()
            raise SourceError(f"{self.path}: no frame from {self.span.describe()}: the video "
                              f"has {self._n} frames")
        self._first = first
        fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
        if count and self.span:
            count = self.span.frames(count, fps or 30.0) or None
        height, width = int(first[1].shape[0]), int(first[1].shape[1])
        detail = {"path": str(self.path), "pace": self.pace, "loop": self.loops}
        if self.span:
            detail["span"] = self.span.describe()
        return SourceInfo(self.uri, "file", False, width, height, fps, count, detail)

    def _decode(self) -> tuple[float, np.ndarray] | None:
        """The next frame of the span (t, image); None at its end (or the file's)."""
        import cv2

        while True:
            ok, image = self._cap.read()
            if not ok or image is None:
                from articast.service.video import check_complete

                try:
                    check_complete(self.path, self._n, int(self._cap.get(
                        cv2.CAP_PROP_FRAME_COUNT) or 0))
                except InputError as exc:
                    raise SourceError(str(exc)) from None
                return None
            t = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            fps = self._cap.get(cv2.CAP_PROP_FPS) or 30.0
            if t <= 0 and self._n > 0:  # container without time stamps
                t = self._n / fps
            index = self._n
            self._n += 1
            if self.span.after(index, t):
                return None
            if not self.span.before(index, t):
                return t, image

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        if self._first is not None:
            (t, image), self._first = self._first, None
        else:
            item = self._decode()
            if item is None:
                return None
            t, image = item
        return t, image, None

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        if self._fh is not None:
            self._fh.close()
            self._fh = None


# ------------------------------------------------------------------------------- images
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")


class ImagesSource(_Finite):
    def __init__(self, p: SourceURI) -> None:
        self._playback(p)
        self.dir = Path(p.target)
        self.fps = _num(p, "fps", float, 30.0, 0.001)
        self._files: list[Path] = []
        self._i = 0

    def open(self) -> SourceInfo:
        if not self.dir.is_dir():
            raise SourceError(f"{self.dir}: " + ("not a folder" if os.path.lexists(self.dir)
                                                 else "no such folder"))
        self._files = sorted(f for f in self.dir.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        if not self._files:
            raise SourceError(f"{self.dir}: no images ({', '.join(IMAGE_SUFFIXES)})")
        self._i = 0
        first = self._load(self._files[0])
        return SourceInfo(self.uri, "images", False, first.shape[1], first.shape[0], self.fps,
                          len(self._files), {"dir": str(self.dir), "pace": self.pace})

    def _load(self, path: Path) -> np.ndarray:
        import cv2

        with self._open_file(path) as fh:  # each file, at each read: under the roots
            data = np.frombuffer(fh.read(), np.uint8)
        try:
            image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        except cv2.error:  # e.g. a PNG declaring 1e10 pixels: OpenCV refuses by assertion
            raise SourceError(f"{path}: not a readable image (OpenCV refused it: too large "
                              "or malformed)") from None
        if image is None:
            raise SourceError(f"{path}: not a readable image")
        return image

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        if self._i >= len(self._files):
            return None
        image = self._load(self._files[self._i])
        self._i += 1
        return (self._i - 1) / self.fps, image, None

    def close(self) -> None:
        self._files = []


# ------------------------------------------------------------------------------- recordings
class RecordSource(_Finite):
    """Replays a JSONL recording (``serve --record``, or ``articast track`` output)."""

    def __init__(self, p: SourceURI) -> None:
        self._playback(p)
        self.path = Path(p.target)
        self._lines: Iterator[tuple[int, str]] | None = None
        self._fh: Any = None
        self._assets = SourceAssets()

    def open(self) -> SourceInfo:
        from articast.core.safe_io import open_regular_text

        if not os.path.lexists(self.path):
            raise SourceError(f"{self.path}: no such file")
        self._open_file(self.path).close()  # a regular file (else what it is), under the roots
        header, self._assets, self.param_names = read_header(self.path)
        try:
            self._fh = open_regular_text(self.path, max_bytes=None)
        except InputError as exc:
            raise SourceError(str(exc)) from None
        self._lines = enumerate(self._fh, 1)
        self._last_t = -math.inf
        src = header.get("source") or {}
        return SourceInfo(self.uri, "replay-record", False, src.get("width"), src.get("height"),
                          src.get("fps"), None, {"path": str(self.path), "recorded": src})

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        assert self._lines is not None
        for n, line in self._lines:
            try:
                result = parse_frame_line(line, self.param_names)
            except ValueError as exc:
                if line.endswith("\n"):
                    raise SourceError(f"{self.path}:{n}: not a frame record ({exc})") from None
                return None  # the last line of a crashed recording: lost frame in flight
            if result is not None:
                if result.t < self._last_t:
                    raise SourceError(f"{self.path}:{n}: time stamp {result.t:.6g} goes back "
                                      f"in time (after {self._last_t:.6g})")
                self._last_t = result.t
                return result.t, None, result
        return None

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def assets(self) -> SourceAssets:
        return self._assets


# ------------------------------------------------------------------------------- synthetic
class SyntheticSource(_Finite):
    """The built-in speaker (``articast.core.synthetic``), imported only when a session opens it.

    ``articast.core.synthetic.open_stream(seed, fps, cache_dir=...)`` gives a stream with ``model``
    (FaceModel), ``camera`` (Camera), ``appearance`` (trained appearance, or None), optional
    ``frame_count`` (None: endless) and ``frames()`` yielding ``(t, image_bgr, truth)``
    (truth a :class:`~articast.core.tracking.result.TrackResult`). Only :meth:`open` touches it.
    """

    def __init__(self, p: SourceURI) -> None:
        self._playback(p)
        self.seed = _num(p, "seed", int, 1)
        self.fps = _num(p, "fps", float, 60.0, 0.001)
        self._it: Iterator[Any] | None = None
        self._assets = SourceAssets()
        self.progress: Callable[[str], None] | None = None
        """Told in one line when the first open builds the speaker's cached assets."""

    def open(self) -> SourceInfo:
        try:
            import articast.core.synthetic as synthetic

            open_stream = synthetic.open_stream
        except (ImportError, AttributeError) as exc:
            raise SourceError(
                "the synthetic speaker (core.synthetic) is not available in this "
                f"build: {exc}"
            ) from None
        stream = open_stream(seed=self.seed, fps=self.fps, cache_dir=cache_dir(),
                             progress=self.progress)
        extra = {k: getattr(stream, k) for k in ("initial_pose", "rig") if hasattr(stream, k)}
        self._assets = SourceAssets(stream.model, stream.camera,
                                    getattr(stream, "appearance", None), extra)
        self._it = iter(stream.frames())
        cam = stream.camera
        return SourceInfo(self.uri, "synthetic", False, cam.width, cam.height, self.fps,
                          getattr(stream, "frame_count", None), {"seed": self.seed})

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        assert self._it is not None
        item = next(self._it, None)
        return None if item is None else (float(item[0]), item[1], item[2])

    def close(self) -> None:
        self._it = None

    def assets(self) -> SourceAssets:
        return self._assets


def cache_dir() -> Path | None:
    """Where trained assets of the synthetic speaker are kept between runs:
    ``$ARTICAST_CACHE_DIR`` (``off``: no cache), else ``$XDG_CACHE_HOME/articast``, else
    ``~/.cache/articast``."""
    env = os.environ.get("ARTICAST_CACHE_DIR", "")
    if env:
        return None if env.lower() in ("off", "none", "0") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "articast"


# ------------------------------------------------------------------------------- WebRTC
INLET_WAIT_S = 5.0
"""How long a WebRTC source waits for a participant's frame before it says it has none."""


class WebRTCSource:
    """A participant's camera, received over WebRTC by the server process
    (:mod:`articast.service.webrtc`) and forwarded to this worker, thread or process, through
    an inlet: the reading end of a pipe, given by the worker (``SessionSpec.inlet``). Its
    messages are ``(t, width, height, i420_bytes)`` and, last, ``("end", reason)`` when the
    participant left: then :meth:`read` returns None and the session ends (``ends``), where a
    camera's None would be reopened. A tracker on another machine (``articast room-tracker``)
    reads the member's frames from Redis instead, as ``(t, width, height, jpeg, arrived,
    "jpeg")`` (:class:`articast.service.room_frames.RedisInlet`)."""

    live = True
    pace = "realtime"
    loops = 1
    ends = True

    def __init__(self, p: SourceURI) -> None:
        self.uri = p.text
        self.name = p.target
        self.seed = _num(p, "seed", int, None)
        self.inlet: Any = None
        self._first: tuple[float, np.ndarray] | None = None
        self._size: tuple[int, int] | None = None
        """(width, height) of the first frame: the session's image size."""
        self._assets = SourceAssets()
        self.progress: Callable[[str], None] | None = None
        self.captured: float | None = None
        """``time.monotonic()`` when the server received the frame :meth:`read` returned
        last (the capture loop stamps the frame with it, not with when it read it)."""

    def _recv(self, wait: float) -> Any:
        """The next message of the inlet; None when none came within ``wait`` s."""
        try:
            if not self.inlet.poll(wait):
                return None
            return self.inlet.recv()
        except (EOFError, OSError):  # the server dropped the feed (session removed)
            return ("end", "the server closed this participant's feed")

    def _image(self, item: tuple[Any, ...]) -> tuple[float, np.ndarray]:
        import cv2

        t, width, height, data = item[:4]
        self.captured = float(item[4]) if len(item) > 4 else None
        if len(item) > 5 and item[5] == "jpeg":  # through Redis (service/room_frames.py)
            image = self._decode(data)
        else:
            yuv = np.frombuffer(data, np.uint8).reshape(height * 3 // 2, width)
            image = cv2.cvtColor(yuv, cv2.COLOR_YUV2BGR_I420)
        return float(t), self._sized(image)

    def _sized(self, image: np.ndarray) -> np.ndarray:
        import cv2

        height, width = image.shape[:2]
        if self._size is None:
            self._size = (width, height)
        elif (width, height) != self._size:
            # a browser short of CPU or bandwidth sends smaller frames for a while: the
            # camera (intrinsics) is the first frame's size, so the image is scaled back
            image = cv2.resize(image, self._size, interpolation=cv2.INTER_LINEAR)
        return image

    @staticmethod
    def _decode(data: bytes) -> np.ndarray:
        import cv2

        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise SourceError("a frame from Redis is not a JPEG")
        return image

    def finish(self, frame: Frame) -> Frame:
        """The worker's frame, its picture decoded: a JPEG from Redis is decoded when the
        worker takes it, not when it arrives (a busy tracker takes a few of the 30 a second
        that arrive: decoding all of them cost it 2.4 ms each)."""
        if isinstance(frame.image, bytes):
            return replace(frame, image=self._sized(self._decode(frame.image)))
        return frame

    def open(self) -> SourceInfo:
        if self.inlet is None:
            raise SourceError(f"{self.uri!r}: a webrtc source is fed by a participant's browser "
                              "(POST /api/sessions/NAME/webrtc, the join page), not named")
        item = self._recv(INLET_WAIT_S)
        if item is None:
            raise SourceUnavailable(f"no video from the participant for {INLET_WAIT_S:g} s")
        if item[0] == "end":
            raise SourceError(f"the participant left before any video: {item[1]}")
        self._first = self._image(item)
        height, width = self._first[1].shape[:2]
        if self.seed is not None and not self._assets.model:
            try:
                from articast.core.synthetic import open_stream
            except ImportError as exc:
                raise SourceError(f"the synthetic speaker is not available: {exc}") from None
            stream = open_stream(seed=self.seed, cache_dir=cache_dir(), progress=self.progress)
            extra = {k: getattr(stream, k) for k in ("initial_pose", "rig")
                     if hasattr(stream, k)}
            self._assets = SourceAssets(stream.model, stream.camera,
                                        getattr(stream, "appearance", None), extra)
        return SourceInfo(self.uri, "webrtc", True, width, height, None,
                          detail={"participant": self.name, "seed": self.seed})

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None:
        if self._first is not None:
            (t, image), self._first = self._first, None
            return t, image, None
        item = self._recv(INLET_WAIT_S)
        if item is None:
            raise SourceUnavailable(f"no video from the participant for {INLET_WAIT_S:g} s")
        if item[0] == "end":
            return None
        if len(item) > 5 and item[5] == "jpeg":  # decoded by finish(), if the worker takes it
            self.captured = float(item[4])
            return float(item[0]), item[3], None
        t, image = self._image(item)
        return t, image, None

    def close(self) -> None:
        self._first = None  # the inlet stays: the worker closes it when it ends

    def assets(self) -> SourceAssets:
        return self._assets


_PLAYBACK = ("pace", "loop", "plays")
SOURCE_KINDS: dict[str, tuple[Callable[[SourceURI], Any], tuple[str, ...]]] = {
    "v4l2": (V4L2Source, ("width", "height", "fps", "fourcc")),
    "file": (FileSource, (*_PLAYBACK, "start", "end")),
    "images": (ImagesSource, (*_PLAYBACK, "fps")),
    "synthetic": (SyntheticSource, (*_PLAYBACK, "seed", "fps")),
    "replay-record": (RecordSource, _PLAYBACK),
    "webrtc": (WebRTCSource, ("seed",)),
}
"""Registry: kind -> (factory, accepted options)."""


def make_source(uri: str, roots: tuple[str, ...] = ()) -> Source:
    """Parse ``uri`` and build its source (no I/O yet: :meth:`Source.open` does that).
    ``roots``: the media roots every file it opens must resolve under (HTTP sessions)."""
    p = parse_uri(uri)
    source: Source = SOURCE_KINDS[p.kind][0](p)
    if roots:
        source.roots = tuple(roots)  # type: ignore[attr-defined]
    return source


def check_uri(uri: str) -> None:
    """Fail fast on a bad URI or a missing file, without opening anything."""
    p = parse_uri(uri)
    src = make_source(uri)
    if p.kind in ("file", "replay-record"):  # what the path is instead, in one line (its
        # status only: the worker opens and reads it, and fails the session if it is no video)
        from articast.service.video import file_problem

        problem = file_problem(p.target)
        if problem:
            raise SourceError(f"{p.target}: {problem}")
    if p.kind == "images" and not Path(p.target).is_dir():
        raise SourceError(f"{p.target}: " + ("not a folder" if os.path.lexists(p.target)
                                              else "no such folder"))
    del src


def parse_named(spec: str) -> tuple[str, str]:
    """``NAME=URI`` of ``--source`` -> (name, uri)."""
    name, sep, uri = spec.partition("=")
    if not sep or not name or not uri:
        raise InputError(f"--source takes NAME=URI (e.g. cam=v4l2:/dev/video0), got {spec!r}")
    return name, uri


def probe(uri: str) -> SourceInfo:
    """Open and close a finite source once: a corrupt file fails here with one clear error.
    The synthetic speaker is not opened (its options are checked): opening it loads, or on a
    first run builds, its model and appearance, which its worker does anyway (it cost
    `articast demo` seconds before its worker even started)."""
    src = make_source(uri)
    if src.live:
        return SourceInfo(uri, parse_uri(uri).kind, True)
    if isinstance(src, SyntheticSource):
        return SourceInfo(uri, "synthetic", False, detail={"seed": src.seed})
    try:
        return src.open()
    finally:
        src.close()

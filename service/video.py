"""Reading recorded videos and ground-truth/track JSON-lines files (offline commands)."""

from __future__ import annotations

import io
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import InputError
from articast.core.safe_io import MAX_TEXT_BYTES, require_regular

MAX_VIDEO_BYTES = 64 * 2**30
"""A video file: far above any clip (an hour of 1080p MJPG is ~40 GB)."""

SPAN_HELP = "seconds (12.5) or a frame number with f (300f)"

OPENCV_NOISE = (b"Unexpected element.",)
"""What OpenCV's built-in AVI reader prints itself (``fprintf`` to stderr, whatever
``OPENCV_LOG_LEVEL`` says) when it opens a truncated or corrupt file: a second line after
articast's own error."""


VIDEO_SNIFF_BYTES = 4096
"""How much of a file is read to tell text from a video before OpenCV opens it."""
TEXT_SUFFIXES = (".txt", ".text", ".md", ".nfo", ".asc", ".ans", ".art", ".diz", ".ice", ".vt",
                 ".json", ".jsonl", ".csv", ".log")
"""Names FFmpeg's ``tty`` demuxer (or nobody) takes for video: OpenCV "opened" a text file
as 640x400 frames of its characters (a landmark progress bar over "84 frames" of notes)."""


def file_problem(path: str | os.PathLike[str]) -> str:
    """What ``path`` is instead of a regular file, from its status alone (nothing opened):
    '' for a regular file, else "no such file", "is a folder, not a regular file", ..."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file" if not os.path.lexists(path) else "a link to no file"
    except OSError as exc:
        from articast.core.safe_io import open_failure

        return open_failure(exc)
    except ValueError:
        return "not a valid file name"
    if stat.S_ISREG(mode):
        return ""
    kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
            "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
            "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
    return f"is {kind}, not a regular file"


def require_file(path: str | os.PathLike[str], what: str = "") -> Path:
    """``path`` is a regular file, or one line saying what it is instead: no such file, a
    folder, a FIFO, a device (never "no such file" for something that is there)."""
    p = Path(path)
    if not os.path.lexists(p):
        raise InputError(f"{what + ' ' if what else ''}{p}: no such file")
    require_regular(p, what)
    return p


def check_video_head(head: bytes, path: str | os.PathLike[str]) -> None:
    """One clear error if the first bytes of ``path`` show it is no video: empty, text."""
    name = Path(path)
    if not head:
        raise InputError(f"{name}: an empty file, not a video")
    if head.startswith(b"YUV4MPEG2"):  # a raw video whose header is a line of text
        return
    if name.suffix.lower() in TEXT_SUFFIXES or _looks_like_text(head):
        raise InputError(f"{name}: a text file, not a video (give a clip: mp4, mov, avi, mkv, "
                         "webm, ... any format FFmpeg reads)")


def _looks_like_text(head: bytes) -> bool:
    """No NUL byte, and UTF-8 (the cut at the end aside) or nearly all printable ASCII: every
    video container has binary fields (sizes, codes) in its first kilobytes."""
    if b"\0" in head:
        return False
    try:
        head.decode("utf-8")
        return True
    except UnicodeDecodeError as exc:
        if exc.reason == "unexpected end of data" and exc.start >= len(head) - 3:
            return True
    printable = sum(32 <= b < 127 or b in b"\t\n\r\f" for b in head)
    return printable >= 0.95 * len(head)


def check_video_file(path: str | os.PathLike[str]) -> Path:
    """The one check before a video file is handed to OpenCV (enroll, track, delegate,
    replay, serve): it exists, is a regular file (a FIFO would block OpenCV for ever), and
    its first bytes are not text. One :class:`InputError` line otherwise, before any work."""
    from articast.core.safe_io import open_regular

    p = require_file(path)
    with open_regular(p, max_bytes=MAX_VIDEO_BYTES) as fh:
        head = fh.read(VIDEO_SNIFF_BYTES)
    check_video_head(head, p)
    return p


def open_capture(name: str, *api: int) -> Any:
    """``cv2.VideoCapture(name, *api)`` with OpenCV's own stderr lines (:data:`OPENCV_NOISE`)
    dropped: fd 2 goes to a temporary file while the container is parsed, and whatever else
    was written there meanwhile (another thread's log) is written back afterwards."""
    import sys
    import tempfile

    import cv2

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no stderr to protect
        return cv2.VideoCapture(name, *api)
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)
            cap = cv2.VideoCapture(name, *api)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        rest = b"".join(line for line in tmp.read().splitlines(keepends=True)
                        if not line.startswith(OPENCV_NOISE))
    if rest:
        os.write(2, rest)
    return cap


def parse_mark(text: str | None, option: str) -> tuple[float, str] | None:
    """``--start``/``--end`` (or a source's ``start=``/``end=``): seconds, or frames with a
    ``f`` suffix: (value, "s" | "f"); None when not given. One clear error otherwise."""
    if text is None or str(text).strip() == "":
        return None
    raw = str(text).strip().lower()
    unit = "f" if raw.endswith("f") else "s"
    number = raw[:-1] if raw.endswith(("f", "s")) else raw
    try:
        value = int(number) if unit == "f" else float(number)
    except ValueError:
        raise InputError(f"{option} {text!r}: expected {SPAN_HELP}") from None
    if not np.isfinite(value) or value < 0:
        raise InputError(f"{option} {text!r}: expected {SPAN_HELP}, not negative")
    return float(value), unit


class Span:
    """The part of a clip between ``start`` (included) and ``end`` (excluded), each in
    seconds of the container's time line or in frames (:func:`parse_mark`)."""

    def __init__(self, start: str | None = None, end: str | None = None,
                 names: tuple[str, str] = ("--start", "--end")) -> None:
        self.start = parse_mark(start, names[0])
        self.end = parse_mark(end, names[1])
        if self.start and self.end and self.start[1] == self.end[1] \
                and self.end[0] <= self.start[0]:
            raise InputError(f"{names[1]} {end} is not after {names[0]} {start}")

    def __bool__(self) -> bool:
        return self.start is not None or self.end is not None

    @staticmethod
    def _at(mark: tuple[float, str], i: int, t: float) -> float:
        return (i if mark[1] == "f" else t) - mark[0]

    def before(self, i: int, t: float) -> bool:
        """Frame ``i`` at ``t`` s comes before the start."""
        return self.start is not None and self._at(self.start, i, t) < -1e-6

    def after(self, i: int, t: float) -> bool:
        """Frame ``i`` at ``t`` s is at or past the end."""
        return self.end is not None and self._at(self.end, i, t) >= -1e-6

    def frames(self, total: int, fps: float) -> int:
        """How many frames of a clip of ``total`` frames at ``fps`` the span holds (0 if
        unknown)."""
        if not total:
            return 0
        def index(mark, default):
            if mark is None:
                return default
            return int(mark[0]) if mark[1] == "f" else int(round(mark[0] * (fps or 30.0)))
        return max(0, min(total, index(self.end, total)) - min(total, index(self.start, 0)))

    def describe(self) -> str:
        def one(mark):
            return "" if mark is None else (f"{int(mark[0])}f" if mark[1] == "f"
                                            else f"{mark[0]:g} s")
        return f"{one(self.start) or 'the start'} to {one(self.end) or 'the end'}"


def iter_video(path: str | os.PathLike[str], span: Span | None = None
               ) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield ``(index, t_seconds, bgr_image)`` for every frame of a video file (of ``span``
    only, when given: frames are decoded from the start, so the cut is exact).

    Time stamps come from the container (falling back to index / fps). Raises
    :class:`InputError` if the file is missing or no frame can be decoded, or if the span
    holds no frame.
    """
    import cv2

    p = check_video_file(path)
    cap = open_capture(str(p))
    if not cap.isOpened():
        raise InputError(f"{p}: cannot open as a video (unknown or corrupt container)")
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    declared = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)
    i = given = 0
    cut = False
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            t = ms / 1000.0 if ms > 0 or i == 0 else (i / fps if fps > 0 else float(i))
            if i > 0 and fps > 0 and ms <= 0:
                t = i / fps
            if span is not None and span.after(i, t):
                cut = True
                break
            if span is None or not span.before(i, t):
                given += 1
                yield i, t, frame
            i += 1
    finally:
        cap.release()
    if i == 0:
        raise InputError(f"{p}: no frame could be decoded (corrupt or empty video)")
    if given == 0:
        raise InputError(f"{p}: no frame from {span.describe() if span else ''}: the clip has "
                         f"{i} frames ({t:.1f} s)")
    if not cut:
        check_complete(p, i, declared)


def check_complete(path: str | os.PathLike[str], read: int, declared: int) -> None:
    """A video that stops before the frame count its container declares is truncated or
    corrupt: an error saying how far it got, never a silent half result. Slack of one frame
    or 2 % (Matroska and some AVIs estimate the count from duration x fps)."""
    if declared and declared - read > max(1, declared // 50):
        raise InputError(f"{path}: the video ended early: read {read} of the {declared} frames "
                         "its container declares (truncated or corrupt file)")


def video_frame_count(path: str | os.PathLike[str]) -> int:
    """Frame count the container declares (0 if unknown)."""
    import cv2

    check_video_file(path)
    cap = open_capture(str(path))
    try:
        return max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    finally:
        cap.release()


def read_jsonl(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Objects of a JSON-lines file; a malformed line is an InputError naming its number."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected a JSON-lines file")
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    from articast.core.safe_io import open_regular

    out = []
    n = 0
    try:
        with io.TextIOWrapper(open_regular(p, max_bytes=MAX_TEXT_BYTES), encoding="utf-8") as fh:
            for n, line in enumerate(fh, 1):  # noqa: B007 - n names the line in errors
                if not line.strip():
                    continue
                try:
                    obj = json.loads(line)
                except json.JSONDecodeError as exc:
                    raise InputError(f"{p}:{n}: not valid JSON ({exc.msg})") from None
                except RecursionError:
                    raise InputError(f"{p}:{n}: JSON nested too deeply") from None
                if not isinstance(obj, dict):
                    raise InputError(f"{p}:{n}: each line must be a JSON object")
                out.append(obj)
    except UnicodeDecodeError:
        raise InputError(f"{p}:{n + 1}: not UTF-8 text") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or type(exc).__name__})") from None
    return out


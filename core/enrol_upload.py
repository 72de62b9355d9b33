"""An enrolment clip uploaded from a browser (the meeting room's guided enrolment,
``service/room_enrol.py``): what is accepted, checked before a byte is decoded and after the
clip was counted, and how far the enrolment's stages have come. Pure functions: no I/O.

A browser records its camera with MediaRecorder as WebM (Chromium, Firefox) or MP4 (Safari);
anything else, or bytes that do not start as those containers do, is refused in one line
before the decoder sees it. The decoder's own verdict (a corrupt stream) comes after.
"""

from __future__ import annotations

MAX_UPLOAD_BYTES = 64 * 2**20
"""64 MB: a 60 s clip at MediaRecorder's 2.5 Mbit/s default is ~19 MB; the page asks for
2.5 Mbit/s and records ~24 s (~8 MB)."""

MIN_SECONDS = 18.0
"""The shortest clip enrolled. ``articast enroll`` asks for 20-60 s of reading aloud (and
warns below 20); the page records 24 s, of which a loaded browser may drop the first second
or two."""

MAX_SECONDS = 90.0
"""The longest clip decoded (the enrolment analyses a bounded number of frames of it)."""

MAX_PIXELS = 1920 * 1080
"""The largest frame: every analysed frame is held in memory while the model is built."""

TYPES = {"video/webm": "webm", "video/x-matroska": "webm", "video/mp4": "mp4"}
"""Content-Type (without parameters) -> container."""

_EBML = b"\x1a\x45\xdf\xa3"  # Matroska/WebM's first four bytes

STAGES: tuple[tuple[str, float], ...] = (
    ("upload", 0.03), ("decoding", 0.04), ("landmarks", 0.17), ("reader landmarks", 0.06),
    ("model", 0.35), ("delegate", 0.35))
"""The enrolment's stages in order and their share of its time (measured: 180 frames of a
640x480 clip at load 3 on 2 cores, 36 s: landmarks 5 s, the live reader 2 s, the model 12 s,
the delegate's texture 15 s)."""


def media_type(content_type: str) -> str:
    """``video/webm;codecs=vp8`` -> ``video/webm``."""
    return content_type.split(";", 1)[0].strip().lower()


def upload_problem(content_type: str, length: str | None) -> tuple[int, str]:
    """(HTTP status, one line) refusing an upload from its headers alone; (0, "") to read
    it. ``length`` is the Content-Length header (None when the body is chunked)."""
    kind = media_type(content_type)
    if kind not in TYPES:
        return 415, (f"the enrolment clip must be a camera recording ({', '.join(TYPES)}), "
                     f"not {kind or 'untyped data'!r}")
    if length is not None:
        if not length.isdigit():
            return 400, "Content-Length is not a number"
        if int(length) > MAX_UPLOAD_BYTES:
            return 413, (f"the clip is {int(length) / 2**20:.0f} MB: at most "
                         f"{MAX_UPLOAD_BYTES // 2**20} MB (record 20-60 s)")
        if int(length) == 0:
            return 400, "the clip is empty"
    return 0, ""


def container_problem(content_type: str, head: bytes) -> str:
    """One line when the first bytes are not the container the Content-Type names ("" when
    they are)."""
    kind = TYPES.get(media_type(content_type), "")
    if kind == "webm" and head[:4] == _EBML:
        return ""
    if kind == "mp4" and len(head) >= 8 and head[4:8] == b"ftyp":
        return ""
    return f"the clip's bytes are not a {kind or 'video'} file (its first bytes say otherwise)"


def clip_problem(seconds: float, frames: int, width: int, height: int) -> str:
    """One line when a decoded clip is not one to enrol ("" when it is)."""
    if frames == 0 or width <= 0 or height <= 0:
        return "the clip holds no video frame"
    if width * height > MAX_PIXELS:
        return f"the clip's frames are {width}x{height}: at most 1920x1080"
    if not seconds == seconds or seconds < MIN_SECONDS:  # (NaN too)
        return (f"the clip is {seconds:.1f} s long: the enrolment needs at least "
                f"{MIN_SECONDS:g} s of you reading aloud (20-60 s)")
    if seconds > MAX_SECONDS:
        return f"the clip is {seconds:.0f} s long: at most {MAX_SECONDS:g} s"
    return ""


def overall(stage: str, done: int = 0, of: int = 0) -> float:
    """The enrolment's progress (0-1) at ``done`` of ``of`` of ``stage`` (``of`` 0: the
    stage has begun); 1.0 for ``done``, 0 for a stage it does not know."""
    if stage == "done":
        return 1.0
    before = 0.0
    for name, share in STAGES:
        if name == stage:
            part = min(max(done / of, 0.0), 1.0) if of > 0 else 0.0
            return round(before + share * part, 4)
        before += share
    return 0.0

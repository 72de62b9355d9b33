"""The meeting room's enrolment from the browser (issue 41, item 2): a participant's camera
clip, recorded by their page (clients/web/room.js, the guided enrolment), becomes their speaker
folder ``SPEAKERS/NAME``, with which the room then tracks them as their own textured delegate.

``POST   /room/api/enrol/NAME``         the clip (``video/webm`` or ``video/mp4``, at most
                                        :data:`~articast.core.enrol_upload.MAX_UPLOAD_BYTES`)
                                        with NAME's participant token: the enrolment starts
``GET    /room/api/enrol/NAME``         how far it is (the page asks twice a second)
``POST   /room/api/enrol/NAME/cancel``  stop it (the page, when it is closed)
``DELETE /room/api/enrol/NAME``         stop it and delete NAME's speaker folder

A participant token acts only on its own name (403 otherwise). The enrolment runs in a
process of its own (from the workers' fork server, at their niceness: the server's event loop
and the trackers go first), one per participant and :attr:`RoomConfig.max_enrolments` at once
(429 past that). Its files are written in a private temporary folder beside the speaker
folders and moved into place by one rename, so a speaker folder is complete or absent.
A page that stops asking for :attr:`RoomConfig.enrol_lease_s` seconds (it was closed), an
upload cut off, a participant leaving the room, or a cancel: the process is killed and the
temporary folder removed. The clip itself is never kept.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from articast.core import enrol_upload as U

log = logging.getLogger("articast.room")

UPLOAD_ROUTE = "/room/api/enrol/"
"""The clips' route: the server's body limit (64 kB, 10 s) is :data:`MAX_UPLOAD_BYTES` and
:data:`UPLOAD_TIMEOUT_S` there."""

UPLOAD_TIMEOUT_S = 120.0
"""An upload not complete 2 minutes after it began is refused (8 MB at 0.5 Mbit/s)."""

KEY_FILE = "room-key"
"""In a folder the page enrolled: the secret its participant's token is bound to (a token
taken for the name before the enrolment no longer admits; ``articast room-token NAME
--speakers DIR`` reads it)."""

WORK = ".enrolling"
"""The temporary folders' parent, inside the speakers folder (the same file system: the
finished folder is moved into place by a rename). A name starting with "." is never a
participant's folder."""

ROOM_MAX_FRAMES = 120
"""Frames the room's enrolment analyses (``articast enroll --max-frames``; its default is
600). A 640x480 clip: 180 frames (120 spread over the clip and a run from its middle) took 36 s
at load 3 on 2 cores; 500 frames took 148 s and 1.4 GB. ``articast enroll`` offline enrols
with more frames."""


def default_speakers_dir(room: str) -> Path:
    """Where a room started without ``--speakers`` keeps its participants' enrolments:
    ``$XDG_DATA_HOME/articast/rooms/ROOM/speakers`` (``~/.local/share/...``), private."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local",
                                                           "share")
    return Path(base) / "articast" / "rooms" / room / "speakers"


def private_dir(path: Path) -> Path:
    """``path`` created (parents too) with the last folder 0700."""
    path.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(path, 0o700)
    return path


def may_enrol(name: str) -> bool:
    """Names that can be a speaker folder: not "." or "..", nor hidden (the room's own
    temporary folders)."""
    return bool(name) and not name.startswith(".")


class EnrolRefused(Exception):
    """An enrolment refused: ``status`` and one line."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status, self.detail = status, detail


@dataclass(eq=False)
class Job:
    name: str
    work: Path
    state: str = "uploading"
    """uploading | running | done | failed | cancelled"""
    stage: str = "upload"
    progress: float = 0.0
    detail: str = ""
    warnings: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.time)
    asked: float = field(default_factory=time.monotonic)
    """When the page last asked (the lease)."""
    proc: Any = None
    exitcode: int | None = None
    """The process's exit code, read by the job's reader thread alone (a forkserver process's
    status is a pipe read once: two threads polling it race, and the loser reads 255)."""
    secret: str = field(default_factory=lambda: secrets.token_urlsafe(18))
    """The folder's ``room-key`` once enrolled: the name's token is bound to it."""

    @property
    def active(self) -> bool:
        return self.state in ("uploading", "running")

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "stage": self.stage, "progress": self.progress,
                "detail": self.detail, "warnings": self.warnings,
                "seconds": round(time.time() - self.started, 1)}


class Enrolments:
    """The room's enrolments (one :class:`Job` per participant name, the last one kept for
    the page to read); methods on the server's loop unless said."""

    def __init__(self, root: Path, max_running: int = 1, lease_s: float = 20.0,
                 max_frames: int = ROOM_MAX_FRAMES) -> None:
        self.root, self.max_running, self.lease_s = root, max_running, lease_s
        self.max_frames = max_frames
        self.jobs: dict[str, Job] = {}
        self._lock = threading.Lock()
        """Held while a job's files are moved or removed (the reader thread and the loop)."""

    # ------------------------------------------------------------------ the folders
    def folder(self, name: str) -> Path:
        return self.root / name

    def enrolled(self, name: str) -> bool:
        return (self.folder(name) / "speaker.json").is_file()

    def secret(self, name: str) -> str:
        """The secret ``name``'s token is bound to ("" unless the page enrolled them)."""
        if not may_enrol(name):
            return ""
        try:
            with open(self.folder(name) / KEY_FILE, encoding="ascii") as fh:
                return fh.read(100).strip()
        except (OSError, ValueError):
            return ""

    def pending_secret(self, name: str) -> str:
        """The secret of ``name``'s enrolment under way (its page holds the token bound to
        it from the upload on; "" when there is none)."""
        job = self.jobs.get(name)
        return job.secret if job is not None and job.state in ("running", "done") else ""

    def clean(self) -> None:
        """Temporary folders a previous run left (killed mid-enrolment) are removed."""
        shutil.rmtree(self.root / WORK, ignore_errors=True)

    # ------------------------------------------------------------------ a job
    def begin(self, name: str) -> Job:
        """A new job for ``name`` (EnrolRefused 429 when one of theirs runs, or the room's
        cap is reached); its private temporary folder made."""
        if not may_enrol(name):
            raise EnrolRefused(400, f"{name!r} cannot be enrolled (a name starting with '.')")
        old = self.jobs.get(name)
        if old is not None and old.active:
            raise EnrolRefused(429, "your enrolment is already under way: one at a time "
                               "(wait for it, or cancel it)")
        running = sum(j.active for j in self.jobs.values())
        if running >= self.max_running:
            raise EnrolRefused(429, f"the server is enrolling {running} other participant"
                               f"{'s' if running > 1 else ''} (at most {self.max_running} at "
                               "once): try again in a minute")
        work = private_dir(self.root / WORK) / f"{name}-{secrets.token_hex(6)}"
        work.mkdir(mode=0o700)
        job = self.jobs[name] = Job(name, work)
        return job

    def start(self, job: Job, content_type: str) -> None:
        """The enrolment process on the uploaded clip (a thread's work: starting it may wait
        for the fork server), and the thread that reads what it says."""
        from articast.service.worker import ProcessWorker

        ctx = ProcessWorker._ctx
        conn, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_process_main, name=f"articast enrol {job.name}", daemon=True,
                           args=(child, str(job.work / "clip"), str(job.work / "speaker"),
                                 job.name, content_type, self.max_frames))
        with self._lock:
            if job.state != "uploading":  # cancelled meanwhile
                child.close()
                conn.close()
                return
            job.state, job.stage, job.progress = "running", "decoding", U.overall("decoding")
            proc.start()
            job.proc = proc
        child.close()
        threading.Thread(target=self._read, args=(job, conn), name=f"enrol {job.name}",
                         daemon=True).start()
        log.warning("room: enrolling %s (process %d)", job.name, proc.pid)

    def _read(self, job: Job, conn: Any) -> None:
        """What the enrolment process says, until it ends (a thread)."""
        result: tuple[Any, ...] = ("failed", "the enrolment process ended without a result")
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg[0] == "progress":
                _, stage, done, of = msg
                job.stage, job.progress = stage, U.overall(stage, done, of)
            elif msg[0] in ("done", "failed"):
                result = msg
        conn.close()
        if job.proc is not None:
            from multiprocessing.connection import wait as wait_ready

            if wait_ready([job.proc.sentinel], 5.0):
                job.exitcode = job.proc.exitcode
        with self._lock:
            if job.state != "running":  # cancelled: what the killed process left, removed
                shutil.rmtree(job.work, ignore_errors=True)
                return
            if result[0] == "done":
                try:
                    self._install(job)
                except OSError as exc:
                    result = ("failed", f"the speaker folder could not be kept: "
                              f"{exc.strerror or exc}")
            if result[0] == "done":
                job.state, job.stage, job.progress = "done", "done", 1.0
                job.warnings = list(result[1].get("warnings", []))
                job.detail = f"enrolled from {result[1].get('seconds', 0):.0f} s of video"
            else:
                job.state, job.detail = "failed", str(result[1])
            shutil.rmtree(job.work, ignore_errors=True)
        log.warning("room: enrolment of %s %s: %s", job.name, job.state, job.detail)

    def _install(self, job: Job) -> None:
        """The finished folder into place by a rename (its predecessor moved out first,
        then removed): a speaker folder is complete or absent."""
        new, final = job.work / "speaker", self.folder(job.name)
        os.chmod(new, 0o700)
        fd = os.open(new / KEY_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as fh:
            fh.write(job.secret + "\n")
        if final.exists():
            os.rename(final, job.work / "replaced")
        os.rename(new, final)

    def cancel(self, name: str, reason: str) -> bool:
        """Stop ``name``'s enrolment (its process killed, its temporary folder removed);
        True when one was under way."""
        job = self.jobs.get(name)
        if job is None or not job.active:
            return False
        with self._lock:
            if not job.active:
                return False
            job.state, job.detail = "cancelled", reason
            if job.proc is not None and job.exitcode is None:
                # (not ``is_alive()``: only the reader thread reads the status; it waits for
                # the process and removes what is left)
                job.proc.kill()
            shutil.rmtree(job.work, ignore_errors=True)
        log.warning("room: enrolment of %s cancelled (%s)", name, reason)
        return True

    def delete(self, name: str) -> bool:
        """``name``'s enrolment stopped and their speaker folder removed (moved aside by a
        rename first: the room never sees half a folder). True when there was one."""
        self.cancel(name, "the participant deleted their enrolment")
        self.jobs.pop(name, None)
        final = self.folder(name)
        if not may_enrol(name) or not final.is_dir():
            return False
        with self._lock:
            gone = private_dir(self.root / WORK) / f"{name}-deleted-{secrets.token_hex(6)}"
            os.rename(final, gone)
            shutil.rmtree(gone, ignore_errors=True)
        log.warning("room: %s deleted their speaker folder", name)
        return True

    def expire(self, now: float) -> None:
        """Enrolments whose page stopped asking (closed mid-enrolment) are cancelled."""
        for name, job in list(self.jobs.items()):
            if job.state == "running" and now - job.asked > self.lease_s:
                self.cancel(name, f"the page stopped asking for {self.lease_s:g} s (closed?)")

    def status(self, name: str) -> dict[str, Any]:
        job = self.jobs.get(name)
        if job is not None:
            job.asked = time.monotonic()
        return {"name": name, "enrolled": self.enrolled(name),
                "job": job.status() if job is not None else None}

    def close(self) -> None:
        for name in list(self.jobs):
            self.cancel(name, "the server stopped")


async def receive(job: Job, request: Any, enrolments: Enrolments) -> str:
    """The request's body into ``job.work/clip``, checked as it comes (its size, its first
    bytes); the content type. EnrolRefused (the job cancelled, its files removed) otherwise,
    and when the page goes away mid-upload."""
    from starlette.requests import ClientDisconnect

    content_type = request.headers.get("content-type", "")
    status, problem = U.upload_problem(content_type, request.headers.get("content-length"))
    size, head = 0, b""
    try:
        if problem:
            raise EnrolRefused(status, problem)
        with open(job.work / "clip", "wb") as fh:
            async for chunk in request.stream():
                if len(head) < 16:
                    head += chunk[:16 - len(head)]
                    if len(head) >= 8:
                        problem = U.container_problem(content_type, head)
                        if problem:
                            raise EnrolRefused(415, problem)
                size += len(chunk)
                if size > U.MAX_UPLOAD_BYTES:
                    raise EnrolRefused(413, f"the clip is over {U.MAX_UPLOAD_BYTES // 2**20} "
                                       "MB (record 20-60 s)")
                fh.write(chunk)
        if size < 1024:
            raise EnrolRefused(400, "the clip is empty" if not size else
                               f"the clip is {size} bytes: no camera recording is that small")
    except ClientDisconnect:
        enrolments.cancel(job.name, "the upload was cut off (the page closed?)")
        raise EnrolRefused(400, "the upload was cut off") from None
    except EnrolRefused as exc:
        enrolments.cancel(job.name, exc.detail)
        job.state = "failed"
        raise
    except BaseException:  # the body's own limits (413, 408), the server stopping
        enrolments.cancel(job.name, "the upload was refused")
        job.state = "failed"
        raise
    job.asked = time.monotonic()
    return content_type


# ----------------------------------------------------------------------------- the process
def _process_main(conn: Any, clip: str, out: str, name: str, content_type: str,
                  max_frames: int) -> None:
    """The enrolment (a child process): the clip counted and checked, then
    :func:`articast.service.commands.enroll.enrol_speaker`. Says ``("progress", stage, done,
    of)``, then ``("done", summary)`` or ``("failed", one line)``."""
    import signal
    import sys
    import traceback

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server stops us (kill)
    with contextlib.suppress(OSError):
        from articast.service.worker import WORKER_NICE

        os.nice(WORKER_NICE)
    last = [0.0]

    def progress(stage: str, done: int, of: int) -> None:
        now = time.monotonic()
        if now - last[0] >= 0.25 or done == of:
            last[0] = now
            conn.send(("progress", stage, done, of))

    from articast.core.errors import ArticastError

    try:
        frames, seconds, width, height = count_frames(clip)
        problem = U.clip_problem(seconds, frames, width, height)
        if problem:
            conn.send(("failed", problem))
            return
        from articast.service.commands.enroll import EnrolSettings, enrol_speaker

        done = enrol_speaker(Path(clip), Path(out), EnrolSettings(
            max_frames=max_frames, name=name, contact_sheet=False, total=frames,
            label="the clip"), quiet=True, progress=progress)
        conn.send(("done", {"seconds": seconds, "warnings": done.warnings,
                            "delegate": isinstance(done.report.get("delegate"), dict)}))
    except ArticastError as exc:
        conn.send(("failed", " ".join(str(exc).split())))
    except Exception as exc:  # noqa: BLE001 - one line to the page; the trace to the log
        traceback.print_exc(file=sys.stderr)
        conn.send(("failed", f"the enrolment failed ({type(exc).__name__}); the server's log "
                   "says more"))
    finally:
        conn.close()


def count_frames(path: str) -> tuple[int, float, int, int]:
    """Frames, seconds, width and height of a clip's first video stream, from its packets
    (a browser's WebM declares no frame count or duration); its first frame decoded. One
    line (InputError) when it is no video."""
    import av

    from articast.core.errors import InputError

    try:
        with av.open(path, "r") as box:
            if not box.streams.video:
                raise InputError("the clip holds no video")
            stream = box.streams.video[0]
            tb = float(stream.time_base or 0)
            frames, first, last, width, height = 0, None, None, 0, 0
            for packet in box.demux(stream):
                if packet.size == 0:
                    continue
                frames += 1
                if packet.pts is not None:
                    t = packet.pts * tb
                    first = t if first is None else min(first, t)
                    last = t if last is None else max(last, t)
                if frames == 1:
                    for frame in packet.decode():
                        width, height = frame.width, frame.height
                if frames > 60 * 200:
                    raise InputError("the clip has too many frames")
    except av.error.FFmpegError as exc:
        raise InputError(f"the clip cannot be read as video: {exc.strerror or exc}") from None
    step = (last - first) / max(frames - 1, 1) if first is not None and last is not None else 0
    seconds = (last - first + step) if first is not None and last is not None else 0.0
    return frames, float(seconds), width, height

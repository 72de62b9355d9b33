"""Sessions that run in another process: what a gateway knows of them, and how their events
travel through Redis.

Roles (docs/SERVICE.md, "Scale-out on Redis")::

    track-worker ──PUBLISH articast:<session>──> Redis ──> gateway ──> WebSocket subscribers
         └──HSET articast:sessions (every second)──┘└── HGETALL (every second) ──┘

* :class:`EventCodec` turns hub events into JSON bytes and back. A frame travels as its
  :class:`~articast.service.wire.FrameRecord` (~300 bytes); the receiving process re-wraps it
  in a :class:`~articast.service.wire.FrameEvent` with the session's mesh basis and FAP/ARKit
  outputs, built once per description, so encoding per subscriber view stays once per process.
* :class:`Directory` holds a :class:`RemoteSession` per session any worker announces: its
  description (what ``hello`` needs), state and detail. It is fed by ``ready``/``status``
  events and by polling the ``sessions`` hash, which workers rewrite every second: after a
  Redis restart (empty, no persistence) the descriptions are back within a second, and a
  worker that stops writing is reported ``unavailable``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from articast.core.errors import ArticastError
from articast.service.clock import CLOCK
from articast.service.jsonsafe import dumps
from articast.service.metrics import SessionMetrics
from articast.service.wire import FrameEvent, FrameRecord, ReadyEvent, StatusEvent, now

log = logging.getLogger("articast.remote")
HOST = os.uname().nodename if hasattr(os, "uname") else ""
RUN = f"{HOST}:{os.getpid()}:{time.time():.3f}"
"""This process's identity in announcements: a restarted worker is a new run (new hello)."""
HEARTBEAT_S = 1.0
"""Workers rewrite their sessions' entries this often; gateways poll as often."""
STALE_S = 5.0
"""A session whose worker has not written for this long is ``unavailable``."""
FORGET_S = 60.0
"""... and one missing from the hash this long is forgotten."""


def session_info(s: Any) -> dict[str, Any]:
    """What a gateway needs of a local :class:`~articast.service.session.Session`."""
    return {"name": s.spec.name, "sid": s.sid, "state": s.state, "detail": s.detail,
            "description": s.description, "source": s.source_info, "processor": s.processor,
            "worker": s.worker_kind, "restarts": s.metrics.restarts, "t": now(),
            "host": HOST, "run": RUN}


def to_redis_clock(info: dict[str, Any]) -> dict[str, Any]:
    """A session entry as it goes to Redis: its time stamp ``t`` in Redis's clock, with the
    clock it was converted from (:mod:`articast.service.clock`)."""
    offset, stamp = CLOCK.outgoing()
    return {**info, "t": info["t"] + offset, "clock": stamp} if stamp else info


def from_redis_clock(info: Any) -> Any:
    """An entry from Redis: ``t`` back on this machine's clock (anything malformed is left
    as it is, for :func:`entry_problem` to say)."""
    if isinstance(info, dict) and "clock" in info:
        info = dict(info)
        stamp = info.pop("clock")
        with contextlib.suppress(TypeError, ValueError):
            info["t"] = CLOCK.local(float(info["t"]), stamp)
    return info


def entry_problem(name: str, info: Any) -> str:
    """What is wrong with a worker's entry in the sessions hash ("" if nothing): another
    writer, a bug or a hand edit must fail that session only, and say so."""
    if not isinstance(info, dict):
        return "not a JSON object"
    if info.get("name") != name:
        return "its name differs from its key"
    t = info.get("t")
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        return "no valid time stamp 't'"
    if not isinstance(info.get("state", ""), str) or not isinstance(info.get("detail", ""), str):
        return "state/detail are not text"
    if not isinstance(info.get("sid", 0), int) or isinstance(info.get("sid", 0), bool):
        return "sid is not an integer"
    desc = info.get("description")
    if desc is not None and not (isinstance(desc, dict) and isinstance(
            desc.get("param_names"), list)):
        return "description is not a session description"
    return ""


class RemoteSession:
    """A session as a gateway sees it (the attributes the WebSocket layer reads)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.sid, self.run = 0, ""
        self.state, self.detail = "starting", ""
        self.description: dict[str, Any] | None = None
        self.source_info: dict[str, Any] | None = None
        self.processor = self.worker_kind = ""
        self.restarts = 0
        self.mesh: tuple[np.ndarray, np.ndarray] | None = None
        self.outputs: Any = None
        self.metrics = SessionMetrics()
        self.seen = 0.0
        self.t = 0.0  # the worker's time stamp of the entry taken last
        self._dense: bytes | None = None

    @property
    def up(self) -> bool:
        return self.state == "running"

    def subscriber_arrived(self) -> None:
        """Workers do not wait for a gateway's subscribers (``wait_for_subscriber`` is local)."""

    def update(self, info: dict[str, Any]) -> bool:
        """Take a worker's entry; True when the description is new (a new ``hello``).

        An entry older than the one taken last is ignored: when a worker is replaced, the
        hash may still hold its predecessor's entry for a beat after the new worker's
        ``ready`` arrived, and going back to it gave a second and third hello."""
        t = float(info.get("t", 0.0))
        if t < self.t:
            return False
        self.t = t
        self.seen = time.monotonic()
        self.state, self.detail = str(info.get("state", "")), str(info.get("detail", ""))
        self.source_info, self.processor = info.get("source"), str(info.get("processor", ""))
        self.worker_kind, self.restarts = str(info.get("worker", "")), int(
            info.get("restarts", 0))
        desc, sid, run = info.get("description"), int(info.get("sid", 0)), str(info.get("run", ""))
        if desc is None or ((sid, run) == (self.sid, self.run) and self.description is not None):
            return False
        from articast.service.outputs import make_outputs

        self.sid, self.run, self.description, self._dense = sid, run, desc, None
        g = desc.get("geometry")
        self.mesh = None
        if g:
            k = len(desc["param_names"])
            self.mesh = (np.asarray(g["mean"], np.float32),
                         np.asarray(g["basis"], np.float32).reshape(k, -1))
        self.outputs = make_outputs(desc)
        return True

    def frame_event(self, record: FrameRecord) -> FrameEvent | None:
        if self.description is None:
            return None
        self.metrics.frames += 1
        self.metrics.fps.tick()
        return FrameEvent(self.name, self.sid, record, self.description["param_names"],
                          self.mesh, self.outputs)

    def dense_json(self) -> bytes:
        if self._dense is None:
            from articast.core.synthetic.dense import dense_face
            from articast.service.wire import model_from_description

            model = model_from_description(self.description or {})
            self._dense = dumps(dense_face(model).to_dict()).encode()
        return self._dense

    def to_dict(self, subscribers: int = 0) -> dict[str, Any]:
        return {"name": self.name, "sid": self.sid, "state": self.state, "detail": self.detail,
                "source": self.source_info, "processor": self.processor,
                "worker": self.worker_kind, "subscribers": subscribers,
                "frames": self.metrics.frames, "fps": round(self.metrics.fps.rate(), 2),
                "restarts": self.restarts, "remote": True}


class Directory:
    """The sessions every worker announced, by name."""

    def __init__(self) -> None:
        self.sessions: dict[str, RemoteSession] = {}
        self._malformed: dict[str, str] = {}  # name -> the problem last logged

    def get(self, name: str) -> RemoteSession | None:
        return self.sessions.get(name)

    def update(self, info: dict[str, Any]) -> tuple[RemoteSession, bool]:
        """Take an entry; the session and whether its description is new."""
        name = str(info["name"])
        s = self.sessions.get(name)
        if s is None:
            s = self.sessions[name] = RemoteSession(name)
        return s, s.update(info)

    def sync(self, entries: dict[str, dict[str, Any]]) -> list[StatusEvent | ReadyEvent]:
        """Apply a poll of the ``sessions`` hash; events for what changed (a new description
        missed while Redis was away: ``ready``, so subscribers get a new ``hello``)."""
        events: list[StatusEvent | ReadyEvent] = []
        for name, info in entries.items():
            s = self.sessions.get(name)
            before = (s.state, s.detail) if s else None
            try:
                problem = entry_problem(name, info)
                if not problem:
                    t = float(info["t"])
                    if now() - t > STALE_S:
                        info = {**info, "state": "unavailable", "detail": "no heartbeat from "
                                f"its worker for over {STALE_S:g} s"}
                    s, new = self.update(info)
            except (ArticastError, ValueError, TypeError, KeyError, AttributeError,
                    IndexError, RecursionError) as exc:
                problem = f"{type(exc).__name__}: {str(exc)[:100]}"
            if problem:  # one bad entry: that session is failed, the others go on
                s = self.sessions.get(name) or self.sessions.setdefault(name,
                                                                        RemoteSession(name))
                s.seen = time.monotonic()
                s.state, s.detail = "failed", ("its entry in the shared sessions hash is "
                                               f"malformed ({problem})")
                new = False
                if self._malformed.get(name) != problem:
                    self._malformed[name] = problem
                    log.warning("session %s: %s", name, s.detail)
            else:
                self._malformed.pop(name, None)
            assert s is not None
            if new:
                events.append(ReadyEvent(name))
            if before != (s.state, s.detail) and (before is not None or problem):
                events.append(StatusEvent(name, s.state, s.detail, now()))
        # missing from the hash: Redis restarted (workers rewrite within a beat) or the worker
        # died; a removed session already said "stopped" on its channel
        t = time.monotonic()
        for name in set(self.sessions) - set(entries):
            s = self.sessions[name]
            if t - s.seen > FORGET_S:
                del self.sessions[name]
            elif t - s.seen > STALE_S and s.state != "unavailable":
                s.state, s.detail = "unavailable", f"no worker has announced it for {STALE_S:g} s"
                events.append(StatusEvent(name, s.state, s.detail, now()))
        return events


class EventCodec:
    """Hub events <-> JSON bytes, for :class:`~articast.service.redis_hub.RedisHub`.

    ``local`` finds a session of this process (to put its description into ``ready``);
    ``directory`` re-wraps what arrives. ``decode`` returns None for a frame of a session
    whose description has not arrived yet (no ``hello`` could precede it).
    """

    def __init__(self, directory: Directory,
                 local: Callable[[str], Any] | None = None) -> None:
        self.directory = directory
        self.local = local or (lambda name: None)

    def encode(self, ev: Any) -> bytes:
        if isinstance(ev, FrameEvent):
            r = dataclasses.asdict(ev.record)
            # the wall-clock stamps in Redis's clock: the receiver may be another machine
            offset, stamp = CLOCK.outgoing()
            r["t_capture"], r["t_tracked"] = r["t_capture"] + offset, r["t_tracked"] + offset
            doc: dict[str, Any] = {"k": "f", "s": ev.session, "sid": ev.sid, "r": r,
                                   "c": stamp}
        elif isinstance(ev, StatusEvent):
            offset, stamp = CLOCK.outgoing()
            doc = {"k": "s", "s": ev.session, "state": ev.state, "detail": ev.detail,
                   "t": ev.t + offset, "c": stamp}
        elif isinstance(ev, ReadyEvent):
            s = self.local(ev.session)
            info = session_info(s) if s is not None else None
            if info is not None:
                self.directory.update(info)  # this process's own subscribers see it at once
            doc = {"k": "r", "s": ev.session,
                   "info": to_redis_clock(info) if info is not None else None}
        else:
            raise TypeError(f"not a hub event: {type(ev).__name__}")
        return dumps(doc, separators=(",", ":")).encode()

    def decode(self, data: bytes) -> Any:
        doc = json.loads(data)
        kind, name = doc["k"], doc["s"]
        if kind == "f":
            s = self.directory.get(name)
            if s is None or s.sid != doc["sid"]:
                return None
            r, stamp = doc["r"], doc.get("c")
            record = FrameRecord(**{**r, "t_capture": CLOCK.local(r["t_capture"], stamp),
                                    "t_tracked": CLOCK.local(r["t_tracked"], stamp),
                                    "alpha": tuple(r["alpha"]),
                                    "rotation": tuple(r["rotation"]),
                                    "translation": tuple(r["translation"])})
            return s.frame_event(record)
        if kind == "s":
            s = self.directory.get(name)
            if s is not None:
                s.state, s.detail = doc["state"], doc["detail"]
                if s.state == "stopped":  # removed by its worker: forget it now
                    self.directory.sessions.pop(name, None)
            return StatusEvent(name, doc["state"], doc["detail"],
                               CLOCK.local(doc["t"], doc.get("c")))
        if kind == "r":
            # a new description only: the poll of the hash may have brought it first, and
            # one run gets one hello (a replaced worker gave three)
            if doc.get("info"):
                _, new = self.directory.update(from_redis_clock(doc["info"]))
                return ReadyEvent(name) if new else None
            return ReadyEvent(name)
        raise ValueError(f"unknown event kind {kind!r}")


# ----------------------------------------------------------------------------- the hash
class Announcer:
    """A worker's side of the ``sessions`` hash: rewrite every local session each second."""

    def __init__(self, redis: Any, key: str, sessions: Callable[[], dict[str, Any]]) -> None:
        self.redis, self.key, self.sessions = redis, key, sessions
        self.written: set[str] = set()
        self.task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self.task = asyncio.create_task(self._run(), name="session announcer")

    async def _run(self) -> None:
        while True:
            try:
                await self.write()
            except Exception as exc:  # noqa: BLE001 - Redis away: try again next beat
                log.debug("announcing sessions failed: %r", exc)
            await asyncio.sleep(HEARTBEAT_S)

    async def write(self) -> None:
        current = {name: dumps(to_redis_clock(session_info(s)))
                   for name, s in self.sessions().items()
                   if s.description is not None or s.state in ("failed", "unavailable")}
        gone = self.written - set(current)
        if current:
            await self.redis.hset(self.key, mapping=current)
        if gone:
            await self.redis.hdel(self.key, *gone)
        self.written = set(current)

    async def close(self) -> None:
        if self.task is not None:
            self.task.cancel()
        with contextlib.suppress(Exception):
            if self.written:
                await asyncio.wait_for(self.redis.hdel(self.key, *self.written), 1.0)


class Poller:
    """A gateway's side: read the hash each second into the directory; changes go to the hub."""

    def __init__(self, redis: Any, key: str, directory: Directory,
                 publish_local: Callable[[str, Any], None]) -> None:
        self.redis, self.key, self.directory = redis, key, directory
        self.publish_local = publish_local
        self.task: asyncio.Task[None] | None = None
        self.polled = asyncio.Event()

    def start(self) -> None:
        self.task = asyncio.create_task(self._run(), name="session poller")

    async def _run(self) -> None:
        while True:
            try:
                await self.poll()
            except Exception as exc:  # noqa: BLE001 - Redis away: keep what we know
                log.debug("polling sessions failed: %r", exc)
            await asyncio.sleep(HEARTBEAT_S)

    async def poll(self) -> None:
        raw = await self.redis.hgetall(self.key)
        entries = {}
        for k, v in raw.items():
            name = k.decode("utf-8", "replace") if isinstance(k, bytes) else str(k)
            try:
                entries[name] = from_redis_clock(json.loads(v))
            except (ValueError, RecursionError):
                entries[name] = None  # malformed: Directory.sync says so
        for ev in self.directory.sync(entries):
            self.publish_local(ev.session, ev)
        self.polled.set()

    def close(self) -> None:
        if self.task is not None:
            self.task.cancel()

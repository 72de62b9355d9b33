"""The virtual meeting room (issue 41): participants join from a browser, each is tracked as
a session of their own, and every page draws every participant's delegate in one scene.

``articast room`` (:mod:`articast.service.commands.room`) starts a server with one room. Its
routes live under ``/room`` and check the room's own credentials, never the server's token
(which only the operator holds: the session API, ``/ws``):

``GET  /room``                 the room page (``clients/web/room.html``), its query kept
``POST /room/api/join``        ``{"name"}`` with ``X-Room-Token: ROOM``: a participant token
``POST /room/api/offer``       the page's SDP offer with ``X-Participant-Token``: the answer
``GET  /room/api/delegate/N``  member N's delegate (their enrolled face), for members only
``POST|GET|DELETE /room/api/enrol/N``  N's enrolment from the page's clip, how it goes, and
                               its deletion, with N's token only (service/room_enrol.py)
``WS   /room/ws?key=PTOKEN``   the room: ``members`` updates, then every member's session in
                               the protocol's own ``hello``/``frame``/``status`` messages

Access. The room token admits; a participant token (``NAME.HMAC``, an HMAC of the name under
the room token: the server keeps no list, and ``articast room-token NAME`` mints the same
one offline) publishes and reads as NAME only: the offer route takes the session name from
the token, never from the page, so nobody can publish into another's session or drive
another's delegate; a name with an enrolled speaker folder (``--speakers DIR/NAME``) cannot be
taken with the room token alone (its token comes from the host), since its delegate shows a
real face. Wrong tokens from one address are slowed down as the server's own are
(:class:`articast.service.security.FailedAttempts`).

Media. The participants' WebRTC connections run in the server's media process
(:mod:`articast.service.media`), not on this loop. Each page offers its microphone and
``slots`` receive-only audio transceivers; the media process answers those as its own senders
and, as members come and go, points each slot at another member's microphone, forwarding its
Opus packets as they came (no renegotiation, no re-encoding); it reports which slot carries
whom, and ``members`` tells each page (``mid``). Frames carry ``t_capture``, when the server
received the video frame: the audio captured with it reached the server at the same time, so
a page plays a member's animation at ``t_capture`` + that member's audio delay
(clients/web/room.js, docs/ROOM.md).

More than one server (``articast room --hub redis://…``): every server of the room holds the
connections and trackers of the participants who joined on it; the membership is a Redis hash
per room (:mod:`articast.service.room_presence`: a name and a seat are taken atomically
across servers, each entry lapses ``member_ttl_s`` after its server last refreshed it), and
every member's frames go through the Redis hub, so a page on any server follows every
member. A member's enrolled delegate is shared through Redis too (written once per session
run by the server holding them, read by the others' delegate route); their voice stays on their
own server (not relayed yet).
With ``--remote-trackers`` a server tracks nobody: its media process puts each member's
frames in Redis and ``articast room-tracker`` processes on any machine track them under a
lease (:mod:`articast.service.room_frames`, :mod:`articast.service.room_tracker`); their
results come back through the hub as any other server's do.

A participant leaves when their page closes its room socket, their peer connection closes or
fails, or their video ends: their session ends, their slots are freed, the others' pages are
told; the same name can join again. Frames and audio live in memory; what is stored is a
participant's enrolment, if they make one (docs/ROOM.md, "What is stored").
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import logging
import os
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request, WebSocket
from fastapi.responses import RedirectResponse, Response

from articast.service.clock import wall
from articast.service.jsonsafe import dumps
from articast.service.room_enrol import Enrolments, EnrolRefused, receive
from articast.service.security import FailedAttempts, client_key

log = logging.getLogger("articast.room")

ROOM_HEADER = "x-room-token"
PARTICIPANT_HEADER = "x-participant-token"
STREAMS: list[Any] = ["articulatory", "pose"]


def participant_token(room_token: str, name: str, secret: str = "") -> str:
    """The token that publishes and reads as ``name`` in the room of ``room_token``; a name
    enrolled from the page has a ``secret`` of its own (its speaker folder's ``room-key``),
    so that a token taken for the name before it was enrolled no longer admits."""
    mac = hmac.new(room_token.encode(), b"articast room participant\0" + name.encode()
                   + (b"\0" + secret.encode() if secret else b""),
                   hashlib.sha256).hexdigest()[:40]
    return f"{name}.{mac}"


def new_room_token() -> str:
    return secrets.token_urlsafe(24)


@dataclass(frozen=True)
class RoomConfig:
    name: str = "room"
    token: str = ""
    """The room token (``articast room`` makes one when none is given)."""
    speakers: str = ""
    """A folder of enrolled speaker folders, one per participant name (``DIR/NAME``)."""
    max_participants: int = 8
    seed: int = 1
    """The synthetic speaker whose assets track a participant without a speaker folder."""
    max_enrolments: int = 1
    """Enrolments from the page at once (each takes a core for ~40 s; 429 past that)."""
    enrol_lease_s: float = 20.0
    """An enrolment whose page has not asked how it goes for this long is cancelled."""
    processor: str = "auto"
    """What tracks a member's video (``auto``: the tracker; ``pkg.mod:fn`` for tests)."""
    max_fps: float = 15.0
    """The most frames a second a page sends (its video sender's ``maxFramerate``): the
    tracker takes 6-9 a second per participant on this 2-core machine and 25 is the aim on
    a free one, while the browser would send 30 that the media process decodes (docs/ROOM.md,
    "Tracking is slow here")."""
    member_ttl_s: float = 10.0
    """With a Redis hub: a member's entry in the room's membership hash lapses this long
    after the server holding their connection last rewrote it (every third of it)."""
    max_shared_delegate: int = 4_000_000
    """With a Redis hub: the largest delegate (its JSON, bytes) shared with the room's other
    servers (``--max-shared-delegate`` MB); a larger one is refused in one line of the log
    (their pages show the generic head). One enrolled on the page is ~0.5 MB (its 256-pixel
    texture and its modes as PNG)."""
    remote_trackers: bool = False
    """With a Redis hub (``--remote-trackers``): this server tracks nobody; its media process
    puts each member's frames in Redis and an ``articast room-tracker`` on any machine tracks
    them (:mod:`articast.service.room_frames`)."""
    tracker_wait_s: float = 20.0
    """With remote trackers: a member no tracker has held for this long is told so and
    leaves (``--tracker-wait``)."""
    warm_media: bool = False
    """Start the media process (and the workers' fork server) when the server starts rather
    than on the first offer (``articast room``: the first participant does not wait ~5 s)."""

    def __repr__(self) -> str:  # never show the token
        return (f"RoomConfig(name={self.name!r}, token={'set' if self.token else 'none'}, "
                f"speakers={self.speakers!r}, max_participants={self.max_participants})")

    def speaker_of(self, name: str) -> str:
        """The enrolled speaker folder of participant ``name`` ("" when none)."""
        if not self.speakers:
            return ""
        path = Path(self.speakers) / name
        return str(path) if (path / "model.npz").is_file() or (path / "speaker.json").is_file() \
            else ""


@dataclass(eq=False)
class Member:
    name: str
    joined: float
    feed: Any = None
    """Their :class:`articast.service.media.RemoteFeed` (once their offer is answered)."""
    sockets: set[Any] = field(default_factory=set)
    mids: list[str] = field(default_factory=list)
    speaker: str = ""
    slot: int | None = None
    """Their seat in the room's Redis membership (None without Redis)."""
    shared: Any = None
    """With Redis: the session description (one per session run) whose delegate this server
    put in Redis for the room's other servers (None: not there)."""
    unshared: str = ""
    """Why their delegate is not shared with the other servers ("": it is, or will be)."""
    tracker: str = ""
    """With remote trackers: the tracker that holds them (its lease in Redis; "": none)."""
    tracked_at: float = 0.0
    """With remote trackers: when a tracker was last seen holding them (or they joined)."""
    untracked: str = ""
    """With remote trackers: why they leave (no tracker held them long enough)."""
    delegate_cache: Any = None
    """With remote trackers: (the tracker's description, their delegate's JSON for it)."""
    failed_since: float = 0.0
    """With remote trackers: since when their tracker's session has said it failed."""


class Room:
    """One room's members; lives on the server's event loop (their media: the media
    process)."""

    def __init__(self, config: RoomConfig, svc: Any) -> None:
        self.config, self.svc = config, svc
        self.members: dict[str, Member] = {}
        self.attempts = FailedAttempts()
        self._watcher: asyncio.Task[None] | None = None
        self.remote: dict[str, dict[str, Any]] = {}
        """With a Redis hub: the members other servers hold (their entries in the room's
        membership hash, :mod:`articast.service.room_presence`), as read last."""
        self.presence: Any = None
        """:class:`articast.service.room_presence.Presence` with a Redis hub, else None."""
        self._polled = 0.0
        self._sync: asyncio.Future[None] | None = None
        self._refreshed = 0.0
        self._redis_failing = False
        self._sharing: asyncio.Future[None] | None = None
        self.enrolments: Enrolments | None = None
        """The page's enrolments into the speakers folder (none without one)."""
        if config.speakers:
            self.enrolments = Enrolments(Path(config.speakers), config.max_enrolments,
                                         config.enrol_lease_s)
            self.enrolments.clean()

    def start(self) -> None:
        """The watcher (:meth:`watch`), once, on the server's loop; with a Redis hub (the
        service has started it by now) the room's membership goes through it."""
        if self.presence is None and getattr(self.svc.hub, "redis", None) is not None:
            from articast.service.remote import RUN
            from articast.service.room_presence import Presence

            self.presence = Presence(
                self.svc.hub.redis, f"{self.svc.config.hub_prefix}room:{self.config.name}:"
                "members", RUN, self.config.member_ttl_s)
        if self._watcher is None or self._watcher.done():
            self._watcher = asyncio.ensure_future(self.watch())

    def in_room(self, name: str) -> bool:
        """Is ``name`` a member, here or (Redis) on another of the room's servers?"""
        return name in self.members or name in self.remote

    def everyone(self) -> list[str]:
        """Every member's name: this server's and (Redis) the others'."""
        return list(self.members) + [n for n in self.remote if n not in self.members]

    async def claim(self, member: Member) -> None:
        """With a Redis hub: take the member's name and a seat in the room's membership
        (HTTPException 409 when another server has the name, 429 when the room is full
        across servers, 503 when Redis cannot be reached)."""
        if self.presence is None:
            return
        from articast.service.room_presence import Refused

        try:
            member.slot = await asyncio.wait_for(self.presence.claim(
                member.name, member.joined, bool(member.speaker),
                self.config.max_participants,
                "remote" if self.config.remote_trackers else "local"), 5.0)
        except Refused as exc:
            raise HTTPException(exc.status, exc.detail) from None
        except Exception as exc:  # noqa: BLE001 - Redis away: one line, nothing started
            log.warning("room %s: Redis refused %s's membership: %r", self.config.name,
                        member.name, exc)
            raise HTTPException(503, "the room's Redis cannot be reached: try again in a "
                                "moment") from None

    async def sync(self) -> None:
        """With a Redis hub: rewrite this server's members' entries (every third of their
        TTL) and read everyone's (each call: the watcher's every half second). A member
        another server holds now leaves here; after a TTL without reading Redis, the other
        servers' members are no longer shown."""
        if self.presence is None:
            return
        t = time.monotonic()
        try:
            if self.members and t - self._refreshed >= self.config.member_ttl_s / 3:
                for n, m in self.members.items():
                    if m.shared is not None and not self.config.speaker_of(n):
                        m.unshared = "their enrolment was deleted"  # (its folder is gone)
                mine = {n: {"joined": m.joined, "slot": m.slot,
                            "delegate": bool(m.speaker) and not m.unshared,
                            "tracking": "remote" if self.config.remote_trackers else "local"}
                        for n, m in self.members.items()}
                self._refreshed = t
                for name in await self.presence.refresh(mine):
                    self.remove(name, "another of the room's servers holds the name now",
                                leave_redis=False)
                await self._keep_delegates()
            entries = await self.presence.live()
            if self.config.remote_trackers:
                await self._check_trackers(t)
        except Exception as exc:  # noqa: BLE001 - Redis away: say so once, go on
            if not self._redis_failing:
                log.warning("room %s: Redis cannot be reached (%r): the other servers' "
                            "members go after %g s", self.config.name, exc,
                            self.config.member_ttl_s)
            self._redis_failing = True
            if t - self._polled > self.config.member_ttl_s and self.remote:
                self.remote = {}
                self.announce()
                self._tell_media()
            return
        if self._redis_failing:
            log.warning("room %s: Redis is back", self.config.name)
        self._redis_failing = False
        self._polled = t
        remote = {n: e for n, e in entries.items()
                  if n not in self.members and e.get("server") != self.presence.server}
        if remote.keys() != self.remote.keys():
            for gone in set(self.remote) - set(remote):
                log.warning("room %s: %s (on another server) left", self.config.name, gone)
            for new in set(remote) - set(self.remote):
                log.warning("room %s: %s joined on another server", self.config.name, new)
            self.remote = remote
            self.announce()
        self.remote = remote
        self._tell_media()

    async def _check_trackers(self, t: float) -> None:
        """With remote trackers: which tracker holds each member (their lease in Redis); one
        no tracker has held for ``tracker_wait_s`` is marked to leave (the watcher tells
        them)."""
        from articast.service.room_frames import holders

        mine = {n: m.joined for n, m in self.members.items() if m.feed is not None}
        held = await holders(self.presence.redis, self.svc.config.hub_prefix,
                             self.config.name, mine)
        for name, holder in held.items():
            m = self.members.get(name)
            if m is None:
                continue
            if holder:
                m.tracked_at = t
                if holder != m.tracker:
                    log.warning("room %s: %s is tracked by %s%s", self.config.name, name,
                                holder, f" (was {m.tracker})" if m.tracker else "")
            elif m.tracker:
                log.warning("room %s: %s's tracker %s let go of them", self.config.name, name,
                            m.tracker)
            m.tracker = holder
            if not holder and t - m.tracked_at > self.config.tracker_wait_s and not m.untracked:
                m.untracked = (f"no room tracker took your video for "
                               f"{self.config.tracker_wait_s:g} s: 'articast room-tracker' "
                               "must run")

    def _tell_media(self) -> None:
        """The media process hears the members on the room's other servers (their voices
        from Redis) and relays ours while there are any: said each half second (idempotent
        there; a media process started again is told within one)."""
        media = self.svc.media
        if media is not None:
            media.send(("remote", self.config.name, sorted(self.remote)))

    # ------------------------------------------------------------------ delegates in Redis
    async def _keep_delegates(self) -> None:
        """With a Redis hub (from :meth:`sync`, every third of the TTL): the shared delegates'
        TTLs renewed with the membership's; one no longer to be shared is deleted, one whose
        key lapsed (Redis was away) is written again."""
        gone = [n for n, m in self.members.items() if m.shared is not None and m.unshared]
        for name in gone:
            self.members[name].shared = None
            await self.presence.drop_delegate(name)
        kept = [n for n, m in self.members.items() if m.shared is not None]
        for name in await self.presence.keep_delegates(kept):
            if name in self.members:
                self.members[name].shared = None

    def _to_share(self) -> list[tuple[Member, Any]]:
        """The members whose delegate this server should put in Redis now, with their
        session: enrolled, their session running (a new run: a new description), not yet
        shared for it, not refused."""
        out = []
        for name, m in self.members.items():
            session = self.session_of(name)
            if m.speaker and not m.unshared and m.feed is not None and session is not None \
                    and session.description is not None and m.shared is not session.description:
                out.append((m, session))
        return out

    async def share(self) -> None:
        """With a Redis hub: put each member's delegate where the room's other servers read
        it (:meth:`Presence.share_delegate`), once per session run (the session's own cached
        JSON, made in a thread). A delegate over ``max_shared_delegate`` bytes, or none to
        make, is refused in one line of the log: the other servers' pages show the generic
        head (their list says ``delegate: false``). Redis away: tried again later."""
        for m, session in self._to_share():
            description = session.description
            try:
                body = await asyncio.to_thread(session.delegate_json)
            except Exception as exc:  # noqa: BLE001 - InputError: no delegate; one line
                m.unshared = " ".join(str(exc).split()) or type(exc).__name__
            else:
                if len(body) > self.config.max_shared_delegate:
                    m.unshared = (f"the delegate is {len(body) / 1e6:.2f} MB, over the "
                                  f"{self.config.max_shared_delegate / 1e6:g} MB shared "
                                  "through Redis (--max-shared-delegate)")
            if m.unshared:
                log.warning("room %s: %s's delegate is not shared with the room's other "
                            "servers (their pages show the generic head): %s",
                            self.config.name, m.name, m.unshared)
                continue
            t = time.monotonic()
            try:
                ok = await asyncio.wait_for(self.presence.share_delegate(m.name, body), 5.0)
            except Exception as exc:  # noqa: BLE001 - Redis away: the next watch step retries
                log.warning("room %s: %s's delegate could not be put in Redis (%r)",
                            self.config.name, m.name, exc)
                return
            if ok and self.members.get(m.name) is m:
                m.shared = description
                log.info("room %s: %s's delegate (%.2f MB) is in Redis for the room's other "
                         "servers (%.0f ms)", self.config.name, m.name, len(body) / 1e6,
                         1000 * (time.monotonic() - t))

    async def remote_delegate(self, name: str) -> bytes:
        """The delegate of ``name``, a member another of the room's servers holds, from
        Redis (HTTPException 404 when there is none; 503 when Redis cannot be reached). Their
        server writes it when their session has started: a page asking before that (it asks
        on the member's hello) is answered when it is there, within ``DELEGATE_WAIT_S``."""
        deadline = time.monotonic() + DELEGATE_WAIT_S
        while True:
            entry = self.remote.get(name)
            if entry is None or name in self.members or not entry.get("delegate") \
                    or self.presence is None:
                raise HTTPException(404, f"{name!r} has no delegate in this room (yet)")
            try:
                body = await asyncio.wait_for(
                    self.presence.delegate(name, str(entry.get("server", ""))), 5.0)
            except Exception as exc:  # noqa: BLE001 - Redis away: one line, generic head
                log.warning("room %s: %s's delegate could not be read from Redis (%r)",
                            self.config.name, name, exc)
                raise HTTPException(503, "the room's Redis cannot be reached: try again in "
                                    "a moment") from None
            if body is not None:
                return body
            if time.monotonic() >= deadline:
                raise HTTPException(404, f"{name!r} has no delegate in this room (yet)")
            await asyncio.sleep(0.25)

    def session_of(self, name: str) -> Any:
        """This server's member's session: the local one, or (``--remote-trackers``) the one
        their tracker announced, with a ``delegate_json`` made here from their speaker folder
        (the room's servers and trackers share it) for that session's model."""
        session = self.svc.manager.sessions.get(name)
        member = self.members.get(name)
        if session is None and self.config.remote_trackers and member is not None:
            remote = self.svc.lookup(name)
            if remote is not None and remote.description is not None:
                return _TrackedElsewhere(remote.description, member, self.config)
        return session

    # ------------------------------------------------------------------ access
    async def check(self, request_key: str, offered: str, expected: str) -> None:
        """HTTPException 401 unless ``offered`` is ``expected``. The right token is never
        held (compared first, in constant time); a wrong one counts against the address and,
        past the free ones, its answer waits its turn and its delay, then 429, as the
        server's own token (service/security.py ``FailedAttempts``)."""
        if offered and hmac.compare_digest(offered.encode("utf-8", "replace"),
                                           expected.encode()):
            return
        wait = 0.0
        if offered:  # (no token at all is no guess)
            async with self.attempts.turn(request_key):
                shared = await self._wrong_token(request_key)
                wait = self.attempts.failed(request_key, time.monotonic(), at_least=shared)
                if wait:
                    await asyncio.sleep(wait)
        if wait:
            raise HTTPException(429, "too many wrong tokens from this address: each is "
                                f"answered after {wait:g} s")
        raise HTTPException(401, "wrong or missing token")

    async def _wrong_token(self, request_key: str) -> int:
        """With a Redis hub: the address's wrong tokens on every server of the room, this one
        counted (0: Redis away or slow, then this server's own count holds)."""
        if self.presence is None:
            return 0
        try:
            return await asyncio.wait_for(
                self.presence.wrong_token(request_key, self.attempts.forget_s), 2.0)
        except Exception:  # noqa: BLE001 - Redis away: the local back-off still applies
            return 0

    async def name_of(self, ptoken: str, key: str) -> str:
        """The participant a participant token names (HTTPException 401/429 otherwise)."""
        from articast.service.session import NAME_RE

        name = ptoken.rpartition(".")[0]
        if not NAME_RE.match(name):
            await self.check(key, ptoken or "", "\0")  # a wrong token (none: no guess)
        pending = self.enrolments.pending_secret(name) if self.enrolments is not None else ""
        if pending and hmac.compare_digest(
                ptoken.encode("utf-8", "replace"),
                participant_token(self.config.token, name, pending).encode()):
            return name  # the token the enrolment under way gave its page
        secret = self.enrolments.secret(name) if self.enrolments is not None else ""
        await self.check(key, ptoken, participant_token(self.config.token, name, secret))
        return name

    # ------------------------------------------------------------------ members
    def add(self, name: str) -> Member:
        member = Member(name, time.time(), speaker=self.config.speaker_of(name),
                        tracked_at=time.monotonic())
        self.members[name] = member
        return member

    @property
    def audio(self) -> dict[str, dict[str, Any]]:
        """Member -> ``{"slots": {other: mid}, "level": rms}``: the media process's routing
        of the room's audio (:class:`articast.service.media.MediaRoom`), as it said last."""
        media = self.svc.media
        return media.rooms.get(self.config.name, {}) if media is not None else {}

    def stats(self, name: str) -> str:
        """One line on a member's media and tracking (the server's log, every 5 s): frames
        received, replaced before the tracker took them, tracked, tracked without a face
        (and why), and the video's size."""
        member = self.members.get(name)
        feed = member.feed if member is not None else None
        session = self.svc.manager.sessions.get(name)
        m = session.metrics if session is not None else None
        text = f"{name}: received {feed.received if feed else 0}"
        if feed is not None:
            text += f" (replaced {feed.dropped}, {feed.size[0]}x{feed.size[1]}, " \
                    f"resized {feed.resized})"
            rtp = getattr(feed, "rtp", {})
            if rtp:
                text += ", RTP " + ", ".join(f"{kind} {got} lost {lost}"
                                             for kind, (got, lost) in sorted(rtp.items()))
        if m is not None:
            text += f", tracked {m.frames} at {m.fps.rate():.1f} fps, no face {m.frames_failed}"
            if m.failed_reasons:
                text += " " + dumps(m.failed_reasons)
        return text

    def remove(self, name: str, reason: str, leave_redis: bool = True,
               dropped: bool = False) -> None:
        """``name`` leaves the room; ``dropped``: not by anyone's choice (their video or
        connection ended, their session failed): their page's sockets are closed with
        :data:`DROPPED`, and the page joins again by itself."""
        if name not in self.members:
            return
        log.warning("room %s: %s left (%s): %s", self.config.name, name, reason,
                    self.stats(name))
        member = self.members.pop(name)
        if self.presence is not None:  # their entry and this server's copy of their delegate
            asyncio.ensure_future(self._leave_redis(name, leave_redis))
        if self.enrolments is not None:  # leaving mid-enrolment: it stops, its files go
            self.enrolments.cancel(name, f"the participant left the room ({reason})")
        if member.feed is not None:  # the media process frees their audio slots
            member.feed.close(f"the participant left the room ({reason})")
        code, text = (DROPPED, _reason(f"your connection dropped ({reason})")) if dropped \
            else (1000, "you left the room")
        for ws in list(member.sockets):
            asyncio.ensure_future(_close(ws, code, text))
        self.announce()

    async def _leave_redis(self, name: str, entry: bool = True) -> None:
        """``name``'s entry (``entry``: unless another server holds it now) and this
        server's copy of their delegate leave Redis."""
        with contextlib.suppress(Exception):  # Redis away: both lapse after their TTL
            await asyncio.wait_for(self.presence.leave(name) if entry
                                   else self.presence.drop_delegate(name), 5.0)

    async def close(self) -> None:
        """The server stops: its members' entries leave the room's Redis at once."""
        if self.presence is not None:
            for name in list(self.members):
                await self._leave_redis(name)

    def members_message(self, member: Member) -> str:
        """Every member for ``member``'s page: ``slot`` is the audio slot (mid) that carries
        their voice there (None: not carried, as when the page's slots are all taken)."""
        audio = self.audio
        slot_of = audio.get(member.name, {}).get("slots", {})
        rows = [{"name": m.name, "self": m is member, "slot": slot_of.get(m.name),
                 "delegate": bool(m.speaker), "joined": m.joined,
                 "level": audio.get(m.name, {}).get("level", 0.0)}
                for m in self.members.values()]
        # members on another server: tracked there; their frames, their delegate and their
        # voice (a slot here, once this server's media process reads it) come through Redis
        rows += [{"name": n, "self": False, "slot": slot_of.get(n),
                  "delegate": bool(e.get("delegate")),
                  "joined": e.get("joined", 0.0),
                  "level": audio.get(n, {}).get("level", 0.0), "remote": True}
                 for n, e in self.remote.items() if n not in self.members]
        rows.sort(key=lambda r: (float(r["joined"] or 0.0), r["name"]))
        return dumps({"type": "members", "room": self.config.name, "you": member.name,
                      "t_server": wall(), "members": rows})

    def announce(self) -> None:
        for m in self.members.values():
            text = self.members_message(m)
            for ws in list(m.sockets):
                asyncio.ensure_future(_send(ws, text))

    async def watch(self) -> None:
        """Members whose session ended (their video stopped, the connection failed) leave;
        every second the members (and their microphone levels) are said again."""
        from articast.service.session import TERMINAL

        tick = 0
        lag = 0.0
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(0.25)
            lag = max(lag, time.monotonic() - t0 - 0.25)
            for name, m in list(self.members.items()):
                if m.feed is not None and self.config.remote_trackers:
                    self._watch_remote(name, m)
                    continue
                session = self.svc.manager.sessions.get(name)
                if m.feed is not None and (m.feed.ended or session is None
                                           or session.state in TERMINAL):
                    self.remove(name, m.feed.ended or "the session ended", dropped=True)
                elif m.feed is None and not m.sockets and time.time() - m.joined > 60:
                    self.remove(name, "joined but never sent video")
            if self.enrolments is not None:
                self.enrolments.expire(time.monotonic())
            tick += 1
            if self.presence is not None and tick % 2 == 0 and (
                    self._sync is None or self._sync.done()):
                self._sync = asyncio.ensure_future(self.sync())  # never holds this loop
            if self.presence is not None and (self._sharing is None or self._sharing.done()) \
                    and self._to_share():
                self._sharing = asyncio.ensure_future(self.share())  # (apart from sync: a
                # delegate's JSON takes 0.1-0.3 s to make, the membership must not wait)
            if tick % 4 == 0:
                self.announce()
            if tick % 20 == 0 and self.members:
                log.info("room %s: event loop late by up to %.0f ms; %s", self.config.name,
                         1000 * lag, "; ".join(self.stats(n) for n in self.members))
                lag = 0.0


    def _watch_remote(self, name: str, m: Member) -> None:
        """A member tracked elsewhere leaves when their video ends, when no tracker took
        them for ``tracker_wait_s`` (:meth:`_check_trackers`), or when their session failed
        on the tracker (its reason, as a local worker's failure is told)."""
        session = self.svc.lookup(name)
        if m.feed.ended:
            self.remove(name, m.feed.ended, dropped=True)
        elif m.untracked:
            self.remove(name, m.untracked, dropped=True)
        elif session is not None and session.state == "failed" and m.tracker:
            # (held by a tracker for this membership, its lease says; failed for half a
            # second: a former membership's failed session is gone by then)
            m.failed_since = m.failed_since or time.monotonic()
            if time.monotonic() - m.failed_since >= 0.5:
                self.remove(name, f"their tracker failed: {session.detail}", dropped=True)
        else:
            m.failed_since = 0.0


class _TrackedElsewhere:
    """A member tracked by a room tracker, as the delegate route and the sharing see a
    session: its description (the tracker's) and the member's delegate for its model (made
    once per description, from the speakers folder)."""

    def __init__(self, description: dict[str, Any], member: Member, config: RoomConfig) -> None:
        self.description, self._member, self._config = description, member, config

    def delegate_json(self) -> bytes:
        from articast.core.errors import InputError
        from articast.service.delegate import delegate_json, delegate_path

        cached = self._member.delegate_cache
        if cached is not None and cached[0] is self.description:
            return bytes(cached[1])
        path = delegate_path(self._member.speaker, (os.path.realpath(self._config.speakers),))
        if path is None:
            raise InputError(f"{self._member.name!r} has no delegate")
        body = delegate_json(path, self.description["param_names"])
        self._member.delegate_cache = (self.description, body)
        return body


async def _send(ws: WebSocket, text: str) -> None:
    with contextlib.suppress(Exception):
        await ws.send_text(text)


DELEGATE_WAIT_S = 5.0
"""How long a server waits for the delegate of a member another server holds to reach Redis
(a page asks for it on the member's hello, which may come before)."""

DROPPED = 4001
"""The room socket's close code when a member's media dropped (video ended, connection failed
or expired, session failed, the media process restarted) rather than the member leaving: the
page joins again by itself (clients/web/room.js, a few times, further apart each time)."""


def _reason(text: str) -> str:
    """A WebSocket close reason: at most 123 bytes of UTF-8."""
    data = text.encode()
    return text if len(data) <= 123 else data[:120].decode(errors="ignore") + "..."


async def _close(ws: WebSocket, code: int, reason: str) -> None:
    with contextlib.suppress(Exception):
        await ws.close(code, reason)


def _key(request: Request | WebSocket) -> str:
    return client_key((request.scope.get("client") or ("?",))[0])


def mount_room(app: Any, svc: Any, config: RoomConfig) -> Room:
    """The room's routes on ``app`` (the server's): see the module's docstring."""
    from articast.service import webrtc
    from articast.service.session import NAME_RE, TERMINAL
    from articast.service.worker import SessionSpec

    if not config.token:
        raise ValueError("a room needs a token")
    room = Room(config, svc)
    app.state.room = svc.room = room
    router = APIRouter()

    @router.get("/room", include_in_schema=False)
    async def room_page(request: Request) -> RedirectResponse:
        query = request.url.query
        return RedirectResponse("/avatar/room.html" + (f"?{query}" if query else ""))

    @router.post("/room/api/join")
    async def join(request: Request) -> dict[str, Any]:
        """``{"name"}`` with the room token: that participant's token."""
        room.start()
        await room.check(_key(request), request.headers.get(ROOM_HEADER, ""), config.token)
        body = await _json(request, {"name"})
        name = body.get("name")
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise HTTPException(400, "name: 1-64 of letters, digits, _ . - (it is shown "
                                "under your delegate)")
        if config.speaker_of(name):
            raise HTTPException(403, f"{name!r} is enrolled in this room: join with your own "
                                "link (kept by the page you enrolled on), or ask the room's "
                                "host for it (articast room-token NAME)")
        if room.in_room(name):
            raise HTTPException(409, f"{name!r} is in the room already: choose another name")
        return {"name": name, "token": participant_token(config.token, name),
                "room": config.name, "slots": config.max_participants - 1,
                "max_fps": config.max_fps}

    @router.get("/room/api/me")
    async def me(request: Request) -> dict[str, Any]:
        """Who a participant token is (a page opened with ``?key=`` asks first)."""
        name = await room.name_of(request.headers.get(PARTICIPANT_HEADER, ""), _key(request))
        return {"name": name, "room": config.name, "slots": config.max_participants - 1,
                "max_fps": config.max_fps}

    @router.post("/room/api/offer")
    async def offer(request: Request) -> dict[str, Any]:
        """The page's offer as the participant its token names: the answer."""
        room.start()
        name = await room.name_of(request.headers.get(PARTICIPANT_HEADER, ""), _key(request))
        reason = webrtc.missing()
        if reason:
            raise HTTPException(501, reason)
        body = await _json(request, {"type", "sdp"})
        if body.get("type") != "offer":
            raise HTTPException(400, f"type must be \"offer\", not {body.get('type')!r}")
        sdp = body.get("sdp")
        if not isinstance(sdp, str) or not sdp.startswith("v=0") or \
                len(sdp) > webrtc.MAX_SDP_CHARS:
            raise HTTPException(400, "sdp must be the offer's SDP text (starting v=0, at most "
                                f"{webrtc.MAX_SDP_CHARS} characters)")
        if room.in_room(name):
            raise HTTPException(409, f"{name!r} is in the room already (another page of "
                                "yours?): leave there first")
        if len(room.members) >= config.max_participants:
            raise HTTPException(429, f"the room is full ({config.max_participants} "
                                "participants)")
        old = svc.manager.sessions.get(name)
        old_feed = svc.manager.feeds.get(name)
        if old is not None and old.state not in TERMINAL and not (
                old_feed is not None and old_feed.ended):  # (a dropped one is ending: replaced)
            raise HTTPException(409, f"session {name!r} is running on this server")
        member = room.add(name)
        try:
            await room.claim(member)  # with Redis: the name and a seat, across servers
        except HTTPException:
            room.members.pop(name, None)
            raise
        try:
            answer, mids, feed = await svc.media_process().answer(sdp, name, config.name)
        except ValueError as exc:
            room.remove(name, "the offer was refused")
            raise HTTPException(400, str(exc)) from None
        if config.remote_trackers:  # their frames to Redis; a room tracker takes them
            if old is not None:
                await svc.manager.remove(name)
            if not feed.to_redis(config.name, member.joined):
                room.remove(name, "the media process is gone")
                raise HTTPException(503, "the server's media process is not running")
            member.feed = feed
            room.announce()
            return {"type": "answer", "sdp": answer, "name": name, "slots": mids}
        try:
            if old is not None:
                await svc.manager.remove(name)
            speaker = member.speaker
            spec = SessionSpec(name, f"webrtc:{name}" + (
                "" if speaker else f"?seed={config.seed}"), speaker=speaker,
                processor=config.processor,
                media_roots=(os.path.realpath(config.speakers),) if speaker else ())
            svc.manager.feeds[name] = feed
            await svc.manager.add(spec)
        except Exception as exc:  # noqa: BLE001 - one line to the page, the room unharmed
            svc.manager.feeds.pop(name, None)
            feed.close("the session could not start")
            room.remove(name, "the session could not start")
            raise HTTPException(409 if isinstance(exc, KeyError) else 400,
                                f"cannot start {name!r}: {' '.join(str(exc).split())}") from None
        member.feed = feed  # from now on the watcher ends the membership with the session
        room.announce()
        return {"type": "answer", "sdp": answer, "name": name, "slots": mids}

    @router.get("/room/api/delegate/{name}")
    async def delegate(name: str, request: Request) -> Response:
        """A member's delegate, for the room's participants only; never cached. A member on
        another of the room's servers (Redis): the copy their server put in Redis."""
        await room.name_of(request.headers.get(PARTICIPANT_HEADER, ""), _key(request))
        if name not in room.members and name in room.remote:
            return Response(await room.remote_delegate(name), media_type="application/json",
                            headers={"Cache-Control": "no-store"})
        session = room.session_of(name)
        if name not in room.members or session is None or session.description is None:
            raise HTTPException(404, f"{name!r} has no delegate in this room (yet)")
        try:
            body = await asyncio.to_thread(session.delegate_json)
        except Exception as exc:  # noqa: BLE001 - InputError: no delegate; said in one line
            raise HTTPException(404, " ".join(str(exc).split())) from None
        return Response(body, media_type="application/json",
                        headers={"Cache-Control": "no-store"})

    async def enrolling(request: Request, name: str) -> Enrolments:
        """The room's enrolments, for the participant whose token names ``name`` only."""
        room.start()
        own = await room.name_of(request.headers.get(PARTICIPANT_HEADER, ""), _key(request))
        if own != name:
            raise HTTPException(403, f"your participant token is {own!r}'s: it enrols and "
                                "deletes only its own name")
        if room.enrolments is None:
            raise HTTPException(404, "this room keeps no enrolments (start it with "
                                "--speakers DIR)")
        return room.enrolments

    @router.post("/room/api/enrol/{name}", status_code=202)
    async def enrol(name: str, request: Request) -> dict[str, Any]:
        """The page's enrolment clip (the body): the enrolment starts; the page asks how it
        goes (GET)."""
        enrolments = await enrolling(request, name)
        try:
            job = enrolments.begin(name)
            content_type = await receive(job, request, enrolments)
        except EnrolRefused as exc:
            raise HTTPException(exc.status, exc.detail) from None
        await asyncio.to_thread(enrolments.start, job, content_type)
        # the name's token once enrolled (bound to the folder's new secret): to this page only
        return {**enrolments.status(name),
                "token": participant_token(config.token, name, job.secret)}

    @router.get("/room/api/enrol/{name}")
    async def enrol_status(name: str, request: Request) -> Response:
        enrolments = await enrolling(request, name)
        return Response(dumps(enrolments.status(name)), media_type="application/json",
                        headers={"Cache-Control": "no-store"})

    @router.post("/room/api/enrol/{name}/cancel")
    async def enrol_cancel(name: str, request: Request) -> dict[str, Any]:
        enrolments = await enrolling(request, name)
        enrolments.cancel(name, "the page cancelled it")
        return enrolments.status(name)

    @router.delete("/room/api/enrol/{name}")
    async def enrol_delete(name: str, request: Request) -> dict[str, Any]:
        """The participant's speaker folder deleted (and an enrolment under way stopped);
        if they are in the room as their delegate, they leave it (their face is no longer
        theirs to show: joining again shows the generic head)."""
        enrolments = await enrolling(request, name)
        deleted = enrolments.delete(name)
        member = room.members.get(name)
        if member is not None and member.speaker:
            room.remove(name, "their enrolment was deleted")
        return {"name": name, "deleted": deleted, "enrolled": enrolments.enrolled(name)}

    @router.websocket("/room/ws")
    async def room_socket(ws: WebSocket) -> None:
        key = ws.query_params.get("key", "")
        try:
            name = await room.name_of(key, _key(ws))
        except HTTPException as exc:
            from articast.service.middleware import deny

            await deny(ws.scope, ws.receive, ws.send, exc.status_code, str(exc.detail))
            return
        await ws.accept()
        member = room.members.get(name)
        if member is None:
            await ws.send_text(dumps({"type": "error", "code": "not_joined",
                                           "reason": f"{name!r} has not joined: send your "
                                           "offer first"}))
            await ws.close(1008, "not joined")
            return
        member.sockets.add(ws)
        await ws.send_text(room.members_message(member))
        pumps: dict[str, asyncio.Task[None]] = {}

        async def follow() -> None:  # one pump per member, started and ended with them
            while True:
                everyone = room.everyone()
                for n in everyone:
                    if n not in pumps or pumps[n].done():
                        pumps[n] = asyncio.create_task(_pump(svc, ws, n, room))
                for n in [n for n in pumps if n not in everyone]:
                    pumps.pop(n).cancel()
                await asyncio.sleep(0.1)

        follower = asyncio.create_task(follow())
        try:
            while True:
                msg = await ws.receive()
                if msg["type"] == "websocket.disconnect":
                    break
                text = msg.get("text") or ""
                if text == "ping":
                    await ws.send_text(dumps({"type": "pong", "t_server": wall()}))
        except Exception as exc:  # noqa: BLE001 - one broken socket, never the room
            log.debug("room socket of %s ended: %r", name, exc)
        finally:
            follower.cancel()
            for task in pumps.values():
                task.cancel()
            member.sockets.discard(ws)
            if not member.sockets and room.members.get(name) is member:
                room.remove(name, "the page closed")

    app.include_router(router)
    return room


async def _pump(svc: Any, ws: WebSocket, name: str, room: Room) -> None:
    """One member's session to one page, as the protocol's hello, frame and status. A member
    on another of the room's servers (Redis) is tracked there: their session is the one its
    worker announced (:class:`articast.service.remote.RemoteSession`), their frames come
    through the Redis hub as every session's do there."""
    from articast.client import protocol as P
    from articast.service.wire import FrameEvent, ReadyEvent, StatusEvent, status_text

    req = P.Subscribe(session=name, streams=STREAMS)
    view = (tuple(sorted(STREAMS)), "json")
    sub = svc.hub.subscribe(name, max_queue=8)
    said: Any = None
    try:
        while room.in_room(name):
            session = svc.manager.sessions.get(name) or svc.lookup(name)
            if session is not None and session.description is not None and \
                    said is not session.description:
                await ws.send_text(svc.hello_text(req, session, STREAMS))
                said = session.description
            try:
                ev = await asyncio.wait_for(sub.get(), 0.5)
            except TimeoutError:
                continue
            if isinstance(ev, FrameEvent) and said is not None:
                out = ev.for_subscriber(view, sub.dropped)
                await (ws.send_text(out) if isinstance(out, str) else ws.send_bytes(out))
            elif isinstance(ev, StatusEvent):
                await ws.send_text(status_text(ev, sub.dropped))
            elif isinstance(ev, ReadyEvent):
                said = None
    except asyncio.CancelledError:
        pass
    except Exception as exc:  # noqa: BLE001 - a closed socket ends this pump only
        log.debug("room pump %s ended: %r", name, exc)
    finally:
        sub.close()


async def _json(request: Request, fields: set[str]) -> dict[str, Any]:
    try:
        body = json.loads(await request.body())
    except (ValueError, RecursionError):
        raise HTTPException(400, "the body is not JSON") from None
    if not isinstance(body, dict):
        raise HTTPException(400, "the body must be a JSON object")
    unknown = sorted(set(body) - fields)
    if unknown:
        raise HTTPException(400, f"unknown field(s) {unknown}: {', '.join(sorted(fields))}")
    return body

"""The session API: list, start, stop and recentre sessions, and a participant's browser
joining as one over WebRTC.

``GET /api/sessions``                  the sessions and their state (token when configured)
``POST /api/sessions``                 start one (:class:`.admission.SessionCreate`)
``DELETE /api/sessions/{name}``        stop one
``POST /api/sessions/{name}/recentre`` the next good frame is the neutral head pose
``POST /api/sessions/{name}/webrtc``   a participant's camera as session NAME

Starting, stopping and joining always need the token (403 when none is configured).
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, HTTPException, Request

from articast.core.errors import ArticastError
from articast.service.admission import (
    SessionCreate,
    authorise,
    authorise_admin,
    confined_spec,
    path_name_problem,
)
from articast.service.worker import SessionSpec

if TYPE_CHECKING:
    from articast.service.state import Service


def session_routes(svc: Service) -> APIRouter:
    """The session API's routes on ``svc``."""
    router = APIRouter()
    config, access = svc.config, svc.config.access

    @router.get("/api/sessions")
    async def list_sessions(request: Request) -> list[dict[str, Any]]:
        authorise(access, request)
        return svc.session_dicts()

    @router.post("/api/sessions", status_code=201)
    async def create_session(body: SessionCreate, request: Request) -> dict[str, Any]:
        authorise_admin(access, request)
        if config.role == "gateway":
            raise HTTPException(409, "this is a gateway: sessions run in 'articast "
                                "track-worker' processes")
        if body.processor not in config.http_processors:
            raise HTTPException(400, f"processor {body.processor!r} is not allowed over HTTP "
                                f"(allowed: {list(config.http_processors)}; start the server "
                                "with --processor to allow another)")
        if len(svc.manager.sessions) >= config.policy.max_sessions:
            raise HTTPException(429, f"the server runs its maximum of "
                                f"{config.policy.max_sessions} sessions (--max-sessions)")
        spec = confined_spec(access, body)
        try:
            s = await svc.manager.add(spec)
        except KeyError:
            raise HTTPException(409, f"session {body.name!r} exists") from None
        except ArticastError as exc:
            raise HTTPException(400, str(exc)) from None
        except (OSError, ValueError) as exc:  # a file the checks above let through
            raise HTTPException(400, f"cannot start session {body.name!r}: "
                                f"{type(exc).__name__}: {getattr(exc, 'strerror', '') or exc}"
                                ) from None
        return s.to_dict()

    @router.delete("/api/sessions/{name}")
    async def delete_session(name: str, request: Request) -> dict[str, Any]:
        authorise_admin(access, request)
        if name not in svc.manager.sessions:
            raise HTTPException(404, f"no session {name!r}")
        await svc.manager.remove(name)
        return {"name": name, "state": "stopped"}

    @router.post("/api/sessions/{name}/recentre")
    async def recentre_session(name: str, request: Request) -> dict[str, Any]:
        """Take the session's next good frame as the speaker's neutral head pose."""
        authorise_admin(access, request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        session.recentre()
        return {"name": name, "recentred": True}

    @router.post("/api/sessions/{name}/webrtc")
    async def webrtc_offer(name: str, request: Request) -> dict[str, Any]:
        """A participant's browser joins as session NAME: ``{"type": "offer", "sdp": ...,
        "speaker"?: DIR}`` answered with ``{"type": "answer", "sdp": ..., "session": ...}``.
        Their camera becomes the session's source (:mod:`articast.service.webrtc`), tracked
        as the speaker (a folder under the media roots) or, without one, with the synthetic
        speaker's assets (``seed``, default 1) as ``demo`` does. A session of that name that
        ended (the participant left) is replaced; one still running is not (409)."""
        authorise_admin(access, request)  # a face enters the server: as starting any session
        if config.role == "gateway":
            raise HTTPException(409, "this is a gateway: sessions run in 'articast "
                                "track-worker' processes")
        from articast.service import webrtc
        from articast.service.session import NAME_RE, TERMINAL

        reason = webrtc.missing()
        if reason:
            raise HTTPException(501, reason)
        if not NAME_RE.match(name):
            raise HTTPException(400, f"session name {name!r}: 1-64 of letters, digits, _ . -")
        offer = await _offer(request, webrtc.MAX_SDP_CHARS)
        old = svc.manager.sessions.get(name)
        if old is not None and (old.state not in TERMINAL or name not in svc.manager.feeds):
            raise HTTPException(409, f"session {name!r} exists" + (
                " and has a participant" if name in svc.manager.feeds else ""))
        if old is None and len(svc.manager.sessions) >= config.policy.max_sessions:
            raise HTTPException(429, f"the server runs its maximum of "
                                f"{config.policy.max_sessions} sessions (--max-sessions)")
        speaker = offer["speaker"]
        if speaker:
            problem = path_name_problem(speaker)
            if problem:
                raise HTTPException(400, f"speaker: {problem}")
            access.check_session_files("webrtc", "", {"speaker": speaker})
            speaker = access.resolve(speaker)
        try:
            sdp, _, feed = await svc.media_process().answer(offer["sdp"], name)
        except ValueError as exc:
            raise HTTPException(400, str(exc)) from None
        if old is not None:
            await svc.manager.remove(name)
        source = f"webrtc:{name}" + ("" if speaker else f"?seed={offer['seed']}")
        spec = SessionSpec(name, source, speaker=speaker,
                           media_roots=tuple(os.path.realpath(r) for r in access.media_roots)
                           if speaker else ())
        svc.manager.feeds[name] = feed
        try:
            s = await svc.manager.add(spec)
        except (KeyError, ArticastError) as exc:
            svc.manager.feeds.pop(name, None)
            feed.close("the session could not start")
            raise HTTPException(409 if isinstance(exc, KeyError) else 400,
                                f"session {name!r} exists" if isinstance(exc, KeyError)
                                else str(exc)) from None
        return {"type": "answer", "sdp": sdp, "session": s.to_dict()}

    async def _offer(request: Request, limit: int) -> dict[str, Any]:
        """The join page's offer, checked; HTTPException(400) in one line otherwise."""

        try:
            body = json.loads(await request.body())
        except (ValueError, RecursionError):
            raise HTTPException(400, "the body is not JSON: send {\"type\": \"offer\", "
                                "\"sdp\": ...}") from None
        if not isinstance(body, dict):
            raise HTTPException(400, "the body must be a JSON object {\"type\": \"offer\", "
                                "\"sdp\": ...}")
        unknown = sorted(set(body) - {"type", "sdp", "speaker", "seed"})
        if unknown:
            raise HTTPException(400, f"unknown field(s) {unknown}: type, sdp, speaker, seed")
        if body.get("type") != "offer":
            raise HTTPException(400, f"type must be \"offer\", not {body.get('type')!r}")
        sdp = body.get("sdp")
        if not isinstance(sdp, str) or not sdp.startswith("v=0") or len(sdp) > limit:
            raise HTTPException(400, "sdp must be the offer's SDP text (starting v=0, at most "
                                f"{limit} characters)")
        speaker = body.get("speaker", "")
        if not isinstance(speaker, str):
            raise HTTPException(400, "speaker must be a folder name (a string)")
        seed = body.get("seed", 1)
        if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**31:
            raise HTTPException(400, "seed must be a whole number >= 0 (the synthetic "
                                "speaker whose assets track a participant without a speaker)")
        return {"sdp": sdp, "speaker": speaker, "seed": seed}

    return router

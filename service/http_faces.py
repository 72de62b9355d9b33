"""The routes that read a session's face: its preview picture, its dense mesh, the speaker's
delegate and VRM, and the server's bound head scan animated by it. Each is a picture or a
shape of a face: the token is needed as for subscribing.

``GET /api/sessions/{name}/preview.jpg``   the newest tracking preview (sessions that opt in)
``GET /api/sessions/{name}/dense``         the dense face mesh and modes (JSON)
``GET /api/sessions/{name}/delegate``      the speaker's delegate (never cached)
``GET /api/sessions/{name}/vrm``           the speaker's face as a VRM 1.0 avatar
``GET /api/sessions/{name}/scan``          the bound head scan (``--scan``) and its texture
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response

from articast.core.errors import ArticastError, InputError
from articast.service.admission import authorise

if TYPE_CHECKING:
    from articast.service.state import Service


def face_routes(svc: Service) -> APIRouter:
    """The face-reading routes on ``svc`` (the head scan, ``--scan``, is loaded here)."""
    router = APIRouter()
    config, access = svc.config, svc.config.access

    @router.get("/api/sessions/{name}/preview.jpg")
    async def preview(name: str, request: Request) -> Response:
        """The newest tracking preview of a session that opted in (404 otherwise): a picture
        of a face, so the token is needed like for subscribing."""
        authorise(access, request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if not session.spec.preview:
            raise HTTPException(404, f"session {name!r} has no preview (off by default for "
                                "privacy: start it with --preview or \"preview\": true)")
        if session.preview is None:
            raise HTTPException(409, f"session {name!r} has no preview frame yet")
        seq, jpeg = session.preview
        return Response(jpeg, media_type="image/jpeg",
                        headers={"Cache-Control": "no-store", "X-Articast-Seq": str(seq)})

    @router.get("/api/sessions/{name}/dense")
    def dense_mesh(name: str, request: Request) -> Response:
        """The session's dense face mesh and dense modes (METHOD.md §5), built once per model
        (a fraction of a second, in the thread pool) and served as JSON:
        ``{n_points, mean (3M), basis (K*3M), triangles (3T), linearity_error_mm}``."""
        authorise(access, request)
        session = svc.lookup(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if session.description is None or not session.description.get("geometry"):
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        return Response(session.dense_json(), media_type="application/json")

    def delegate_session(name: str, request: Request) -> Any:
        """The session whose speaker's face a request asks for (their delegate or VRM): the
        token checked as for subscribing, 404 when there is none or the server serves none."""
        authorise(access, request)
        session = svc.manager.sessions.get(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r} on this server")
        if not config.delegates:
            raise HTTPException(404, "this server serves no delegate (--no-delegate)")
        return session

    @router.get("/api/sessions/{name}/delegate")
    def delegate(name: str, request: Request) -> Response:
        """The speaker's delegate (:mod:`articast.service.delegate`): a picture of their face,
        so the token is needed like for subscribing; never cached, never logged."""
        session = delegate_session(name, request)
        if session.description is None:
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        try:
            body = session.delegate_json()
        except ArticastError as exc:
            raise HTTPException(404, str(exc)) from None
        return Response(body, media_type="application/json",
                        headers={"Cache-Control": "no-store"})

    @router.get("/api/sessions/{name}/vrm")
    def speaker_vrm(name: str, request: Request) -> Response:
        """The speaker's face as a VRM 1.0 avatar (service/vrm.py): token, no-store, as the
        delegate."""
        session = delegate_session(name, request)
        desc = session.description
        path = session.delegate_file() if desc is not None else None
        if desc is None or path is None:
            raise HTTPException(404, f"session {name!r} has no delegate to make a VRM of")
        from articast.service.vrm import vrm_bytes

        try:
            body = vrm_bytes(path, desc)
        except ArticastError as exc:
            raise HTTPException(404, str(exc)) from None
        return Response(body, media_type="model/gltf-binary",
                        headers={"Cache-Control": "no-store"})

    from articast.service.scan import ScanAsset

    scan = ScanAsset(config.server.scan) if config.server.scan else None

    @router.get("/api/sessions/{name}/scan")
    def scan_mesh(name: str, request: Request) -> Response:
        """The server's bound head scan (``--scan``) animated by this session's model: dense
        modes and the render mesh as JSON (service/scan.py); 404 without ``--scan``."""
        authorise(access, request)
        session = _scan_session(name)
        from articast.service.wire import model_from_description

        assert scan is not None
        try:
            body = scan.json_for(model_from_description(session.description))
        except InputError as exc:
            raise HTTPException(409, str(exc)) from None
        return Response(body, media_type="application/json")

    @router.get("/api/sessions/{name}/scan/texture")
    def scan_texture(name: str, request: Request) -> Response:
        """The scan's texture image: a picture of a face, so the token is needed."""
        authorise(access, request)
        _scan_session(name)
        assert scan is not None
        return Response(scan.texture.image, media_type=scan.texture.mime,
                        headers={"Cache-Control": "private, max-age=3600"})

    def _scan_session(name: str) -> Any:
        if scan is None:
            raise HTTPException(404, "this server shows no head scan (start it with --scan "
                                "BINDING)")
        session = svc.lookup(name)
        if session is None:
            raise HTTPException(404, f"no session {name!r}")
        if session.description is None or not session.description.get("geometry"):
            raise HTTPException(409, f"session {name!r} has no face model (yet)")
        return session

    return router

"""The FastAPI application: ``WS /ws`` and the HTTP API, put together by :func:`create_app`.

``WS /ws``                     subscribe to sessions (protocol v1, :mod:`articast.client.protocol`):
                               :mod:`articast.service.subscribe`
``GET /api/sessions``          the sessions and their state
``POST /api/sessions``         start one: ``{"name", "source", "model"?, "appearance"?,
                               "camera"?, "processor"?, "wait_for_subscriber"?, "preview"?}``
``DELETE /api/sessions/{name}`` stop one (these, recentre and WebRTC: :mod:`.http_sessions`)
``GET /api/sessions/{name}/…`` a session's preview, dense mesh, delegate, VRM, scan:
                               :mod:`articast.service.http_faces`
``GET /api/protocol``          the JSON Schema of the protocol
``GET /healthz``               liveness and session states
``GET /metrics``               Prometheus text (these three: :mod:`.http_status`)
``/avatar/``                   the browser pages, static files (:mod:`.avatar`)

What the app holds (the hub, the sessions, the connections) is :class:`~.state.Service`.

Access (:mod:`articast.service.security`, :mod:`articast.service.admission`): every request
must name this server in ``Host`` and, from a browser, come from an allowed ``Origin`` (403
otherwise); with a token configured, everything but ``/healthz``, ``/api/protocol`` and the
avatar's static files needs it (401); the session API (POST/DELETE) needs a token always (403
when none is configured).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator, Callable

from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import JSONResponse

from articast.client import protocol as P
from articast.service.http_faces import face_routes
from articast.service.http_sessions import session_routes
from articast.service.http_status import status_routes
from articast.service.middleware import BodyLimit, BodyTimeout, BodyTooLarge, Guard, TokenGate
from articast.service.security import FailedAttempts, Forbidden
from articast.service.state import Service, ServiceConfig
from articast.service.subscribe import serve_connection

__all__ = ["Service", "ServiceConfig", "create_app"]

log = logging.getLogger("articast.app")


def create_app(config: ServiceConfig | None = None,
               on_live: Callable[[dict[str, str]], None] | None = None) -> FastAPI:
    """The app. ``on_live(failed)`` is called once the initial sessions stream (see
    :meth:`Service._announce`)."""
    config = config or ServiceConfig()
    svc = Service(config, on_live)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await svc.start()
        try:
            yield
        finally:
            await svc.stop()

    app = FastAPI(title="articast", version=str(P.PROTOCOL_VERSION), lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    app.state.service = svc
    from articast.service.avatar import mount_avatar

    mount_avatar(app)
    if config.room is not None:
        from articast.service.room import mount_room

        mount_room(app, svc, config.room)

    uploads: tuple[tuple[str, str, int, float], ...] = ()
    if config.room is not None:  # the room's enrolment clips (service/room_enrol.py)
        from articast.core.enrol_upload import MAX_UPLOAD_BYTES
        from articast.service.room_enrol import UPLOAD_ROUTE, UPLOAD_TIMEOUT_S

        uploads = (("POST", UPLOAD_ROUTE, MAX_UPLOAD_BYTES, UPLOAD_TIMEOUT_S),)
    app.add_middleware(BodyLimit, limit=config.hub.max_message_bytes,
                       timeout_s=config.hub.header_timeout_s, uploads=uploads)
    app.add_middleware(TokenGate, access=config.access,
                       attempts=FailedAttempts(free=config.hub.max_token_failures,
                                               max_s=config.hub.token_delay_max_s))
    app.add_middleware(Guard, access=config.access)

    @app.exception_handler(BodyTooLarge)
    async def too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 413, headers={"Connection": "close"})

    @app.exception_handler(BodyTimeout)
    async def too_slow(request: Request, exc: BodyTimeout) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 408, headers={"Connection": "close"})

    @app.exception_handler(Exception)
    async def internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("internal error on %s", request.url.path)
        return JSONResponse({"detail": "internal error (see the server log)"}, 500)

    @app.exception_handler(Forbidden)
    async def forbidden(request: Request, exc: Forbidden) -> JSONResponse:
        return JSONResponse({"detail": exc.reason}, exc.status)

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        await serve_connection(svc, websocket)

    app.include_router(session_routes(svc))
    app.include_router(face_routes(svc))
    app.include_router(status_routes(svc))
    return app

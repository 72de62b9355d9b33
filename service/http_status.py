"""The status routes: ``/healthz`` (liveness, and the sessions' states with the token),
``/api/protocol`` (the protocol's JSON Schema) and ``/metrics`` (Prometheus text, token)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from articast.client import protocol as P
from articast.service.admission import authorise
from articast.service.clock import CLOCK

if TYPE_CHECKING:
    from articast.service.state import Service


def status_routes(svc: Service) -> APIRouter:
    """The status routes on ``svc``."""
    router = APIRouter()
    access = svc.config.access

    @router.get("/api/protocol")
    async def protocol_schema() -> dict[str, Any]:
        return P.protocol_schema()

    @router.get("/healthz")
    async def healthz(request: Request) -> dict[str, Any]:
        out: dict[str, Any] = {"status": "ok", "protocol": P.PROTOCOL_VERSION}
        if CLOCK.uncertainty is not None:  # on Redis: this machine's clock against Redis's
            out["clock"] = CLOCK.status()
        if access.token_ok(request.headers.get("authorization"),
                           request.scope.get("query_string", b"")):
            out["sessions"] = svc.states()
            out["connections"] = len(svc.connections)
        return out

    @router.get("/metrics", response_class=PlainTextResponse)
    async def metrics(request: Request) -> PlainTextResponse:
        authorise(access, request)
        return PlainTextResponse(svc.metrics_text(),
                                 media_type="text/plain; version=0.0.4; charset=utf-8")

    return router

"""The browser avatar (``clients/web``, import name ``articast.web``) served at ``/avatar/`` as
static files."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

WEB = Path(str(files("articast.web")))


def mount_avatar(app: FastAPI) -> None:
    """Serve the avatar page at ``/avatar/`` (``/avatar`` redirects there), the VRM page
    at ``/avatar/vrm.html`` (``/vrm`` redirects there) and the participant page at
    ``/avatar/join.html`` (``/join`` redirects there)."""
    if not (WEB / "index.html").is_file():
        return  # an installation without the web client: the API works all the same

    @app.get("/avatar", include_in_schema=False)
    async def avatar_redirect() -> RedirectResponse:
        return RedirectResponse("/avatar/")

    @app.get("/vrm", include_in_schema=False)
    async def vrm_redirect(request: Request) -> RedirectResponse:
        """The VRM page (clients/web/vrm.html), its query kept."""
        query = request.url.query
        return RedirectResponse("/avatar/vrm.html" + (f"?{query}" if query else ""))

    @app.get("/join", include_in_schema=False)
    async def join_redirect(request: Request) -> RedirectResponse:
        """The participant page (clients/web/join.html), its query kept."""
        query = request.url.query
        return RedirectResponse("/avatar/join.html" + (f"?{query}" if query else ""))

    app.mount("/avatar", StaticFiles(directory=WEB, html=True), name="avatar")

"""The tracking preview: off by default (404 with the reason), and for a session that opts in,
small JPEGs of the tracked video with the fitted mesh drawn, named in hello and shown by the
browser avatar beside the face."""

import json
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from articast.service.app import ServiceConfig
from articast.service.settings import ServerSettings
from articast.service.worker import SessionSpec
from tests.browser import CHROMIUM, Browser
from tests.service_helpers import TIMEOUT, ServerThread


def get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, r.headers, r.read()


def wait_for_preview(url):
    import time

    deadline = time.monotonic() + 6 * TIMEOUT
    while time.monotonic() < deadline:
        try:
            return get(url)
        except urllib.error.HTTPError as exc:
            if exc.code != 409:  # 409: no frame yet
                raise
        time.sleep(0.2)
    raise TimeoutError("no preview frame")


def hello_of(url, session):
    from websockets.sync.client import connect

    with connect(url, open_timeout=TIMEOUT) as ws:
        ws.send(json.dumps({"type": "subscribe", "session": session, "geometry": False}))
        while True:
            m = json.loads(ws.recv(timeout=6 * TIMEOUT))
            if m["type"] == "hello":
                return m


@pytest.fixture(scope="module")
def server():
    uri = "synthetic:seed=1&fps=15&loop=yes"
    config = ServiceConfig(server=ServerSettings(log_level="critical"),
                           sessions=(SessionSpec("shown", uri, preview=True),
                                     SessionSpec("private", uri)))
    with ServerThread(config) as srv:
        yield srv


def test_preview_is_off_by_default(server):
    with pytest.raises(urllib.error.HTTPError) as exc:
        get(f"{server.http}/api/sessions/private/preview.jpg")
    assert exc.value.code == 404 and "privacy" in json.load(exc.value)["detail"]
    assert hello_of(server.url, "private")["preview_url"] is None


def test_preview_shows_the_tracked_video_with_the_mesh(server):
    assert hello_of(server.url, "shown")["preview_url"] == "/api/sessions/shown/preview.jpg"
    status, headers, body = wait_for_preview(f"{server.http}/api/sessions/shown/preview.jpg")
    assert status == 200 and headers["Content-Type"] == "image/jpeg"
    assert headers["Cache-Control"] == "no-store" and int(headers["X-Articast-Seq"]) >= 0
    img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (240, 320, 3)
    b, g, r = (img[..., i].astype(int) for i in range(3))
    mesh = (g - r > 40) & (g - b > 30)  # the green fitted mesh (translucent: the lips show)
    assert mesh.sum() > 300, mesh.sum()
    # the mesh lies on the face: the lower face fills the head rig's frame centre
    ys, xs = np.nonzero(mesh)
    assert 60 < np.median(xs) < 260 and 40 < np.median(ys) < 200
    assert len(body) < 60_000  # small: a few per second cost little


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_the_avatar_page_shows_the_preview(server):
    with Browser(f"{server.http}/avatar/?session=shown") as b:
        b.wait_for("(window.articast.previews || 0) > 2", 60)
        assert b.evaluate("document.getElementById('previewbox').hidden") is False
        b.wait_for("document.getElementById('preview').naturalWidth === 320", 30)
    with Browser(f"{server.http}/avatar/?session=private") as b:
        b.wait_for("window.articast.rendered > 3", 60)
        assert b.evaluate("document.getElementById('previewbox').hidden") is True


def test_with_a_token_the_preview_needs_it():
    """A preview is a picture of a face: nobody without the token sees it."""
    from articast.service.security import AccessPolicy

    config = ServiceConfig(server=ServerSettings(log_level="critical"),
                           sessions=(SessionSpec("shown", "synthetic:seed=1&fps=15&loop=yes",
                                                 preview=True),),
                           access=AccessPolicy(token="s3cret"))
    with ServerThread(config) as srv:
        url = f"{srv.http}/api/sessions/shown/preview.jpg"
        with pytest.raises(urllib.error.HTTPError) as e:
            get(url)
        assert e.value.code == 401
        status, headers, body = wait_for_preview(url + "?token=s3cret")
        assert status == 200 and body[:2] == b"\xff\xd8"

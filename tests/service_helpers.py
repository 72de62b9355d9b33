"""Helpers for the service tests: a real uvicorn server in a thread, small inputs on disk."""

from __future__ import annotations

import asyncio
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.model.camera import Camera, Pose
from articast.core.model.face import PARAM_NAMES, FaceModel
from articast.core.tracking.result import TrackResult

TIMEOUT = float(os.environ.get("ARTICAST_TEST_TIMEOUT", "1")) * 10.0
"""Generous timeout (s) for any wait in service tests; scale with ARTICAST_TEST_TIMEOUT."""


def small_model(n: int = 12, seed: int = 0) -> FaceModel:
    rng = np.random.default_rng(seed)
    mean = rng.normal(0, 20, (n, 3))
    basis = rng.normal(0, 1, (len(PARAM_NAMES), n, 3))
    tri = np.array([[i, i + 1, i + 2] for i in range(n - 2)], np.int32)
    return FaceModel(mean, basis, triangles=tri, name="test-speaker")


def truth(i: int, fps: float) -> TrackResult:
    alpha = np.sin(0.1 * i + np.arange(len(PARAM_NAMES)))
    pose = Pose(np.array([np.pi, 0.01 * i, 0.0]), np.array([0.0, 0.0, 400.0 + i]))
    return TrackResult(i, i / fps, alpha, pose, residual=0.01 * i)


def write_recording(path: Path, frames: int = 30, fps: float = 30.0,
                    model: FaceModel | None = None) -> list[TrackResult]:
    """A recording as ``serve --record`` writes it (header + one line per frame)."""
    from articast.service.wire import describe

    model = model or small_model()
    desc = describe(model, Camera.default(64, 48), model.param_names)
    results = [truth(i, fps) for i in range(frames)]
    with path.open("w") as fh:
        fh.write(json.dumps({"type": "header", "format": "articast-record", "version": 1,
                             "session": "rec", "source": {"kind": "test", "fps": fps},
                             **desc}) + "\n")
        for i, r in enumerate(results):
            d = r.to_dict(model.param_names)
            fh.write(json.dumps({"type": "frame", "seq": i, **d}) + "\n")
    return results


def write_speaker(folder: Path, texture: int = 256, seed: int = 0) -> Path:
    """A small complete speaker folder (as ``articast enroll`` writes one: model, appearance,
    camera, speaker.json) with a delegate whose texture is ``texture`` pixels of noise (its
    JSON ~0.3 MB at 256, near an enrolled one's ~0.5 MB); tracked by a test processor, not
    the tracker. Returns the folder."""
    from articast.core.appearance.models import AppearanceModel, SamplePoints
    from articast.core.delegate.build import Delegate
    from articast.core.delegate.geometry import DelegateMesh
    from articast.core.faces.speaker import SPEAKER_KIND, SPEAKER_VERSION

    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    model = small_model(seed=seed)
    k, s = model.n_params, 5
    model.save(folder / "model.npz")
    AppearanceModel("la_lin", SamplePoints(rng.integers(0, model.n_points, (s, 3)),
                                           np.full((s, 3), 1 / 3)), (0,),
                    rng.normal(size=(1, k + 1, s * 8)), np.ones((1, s * 8)), 2.5,
                    np.array([0.9])).save(folder / "appearance.npz")
    Camera.default(64, 48).save(folder / "camera.json")
    (folder / "speaker.json").write_text(json.dumps({
        "kind": SPEAKER_KIND, "version": SPEAKER_VERSION, "rig": "desk", "name": folder.name,
        "residual": {"median": 1.0, "p95": 2.0, "p99": 3.0, "frames": 10}}))
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 1]])
    Delegate(DelegateMesh(v, rng.normal(0, 1, (k, 4, 3)),
                          np.array([[0, 0], [1, 0], [0, 1], [1, 1.0]]),
                          np.array([[0, 1, 2], [1, 3, 2]], np.int32), np.arange(4)),
             rng.integers(0, 256, (texture, texture, 3), dtype=np.uint8),
             np.zeros((k, texture, texture, 3), np.float32),
             np.ones((texture, texture), np.float32), model.param_names
             ).save(folder / "delegate.npz")
    return folder


def write_video(path: Path, frames: int = 20, fps: float = 25.0, size=(64, 48)) -> list[float]:
    """An MJPG AVI whose frame i is a flat grey of level 10*i (+ a gradient). Returns levels."""
    import cv2

    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert w.isOpened()
    for i in range(frames):
        img = np.full((size[1], size[0], 3), (10 * i) % 250, np.uint8)
        img[:, : size[0] // 2, 0] = 255 - (10 * i) % 250
        w.write(img)
    w.release()
    return [float(10 * i % 250) for i in range(frames)]


class ImageStats:
    """A test FrameProcessor that reads the image: alpha = mean of each channel, 4 zeros."""

    def __init__(self, context: Any) -> None:
        pass

    def process(self, frame: Any) -> TrackResult:
        m = frame.image.reshape(-1, 3).mean(0)
        alpha = np.concatenate([m, np.zeros(len(PARAM_NAMES) - 3)])
        return TrackResult(frame.index, frame.t, alpha, Pose(), residual=float(m.sum()))


class Crashy:
    """A test FrameProcessor that raises on frame 3 of every run (exercises restarts)."""

    def __init__(self, context: Any) -> None:
        self.n = 0

    def process(self, frame: Any) -> TrackResult:
        self.n += 1
        if self.n == 3:
            raise RuntimeError("boom (test crash)")
        return frame.truth


class ServerThread:
    """A real uvicorn server on 127.0.0.1, port 0, in a background thread."""

    def __init__(self, config: Any) -> None:
        import uvicorn

        from articast.service.server import bound_socket, uvicorn_config

        self.sock = bound_socket("127.0.0.1", 0)
        self.port = self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn_config(config))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.token = config.access.token
        self.url = f"ws://127.0.0.1:{self.port}/ws" + (f"?token={self.token}" if self.token
                                                      else "")
        self.http = f"http://127.0.0.1:{self.port}"
        self.headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def client(self) -> Any:
        """An httpx client of this server, with its token."""
        import httpx

        return httpx.Client(base_url=self.http, timeout=TIMEOUT, headers=self.headers)

    def _run(self) -> None:
        asyncio.run(self.server.serve(sockets=[self.sock]))

    def __enter__(self) -> ServerThread:
        self.thread.start()
        deadline = time.monotonic() + TIMEOUT
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("server did not start")
            time.sleep(0.01)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.server.should_exit = True
        self.thread.join(TIMEOUT)
        self.sock.close()

    @property
    def service(self) -> Any:
        return self.server.config.loaded_app.app.state.service  # type: ignore[union-attr]


class SlowStart:
    """A test FrameProcessor whose construction takes ``start_s`` seconds (session option),
    saying so halfway, as a first run that builds caches does; then passes truth through."""

    def __init__(self, context: Any) -> None:
        start_s = float(context.options.get("start_s", 1.0))
        time.sleep(start_s / 2)
        if context.progress is not None:
            context.progress("building test caches (first run only)")
        time.sleep(start_s / 2)

    def process(self, frame: Any) -> TrackResult:
        return frame.truth


class BusyStart:
    """A test FrameProcessor whose construction is ``start_s`` seconds (session option) of
    work known to finish, run inside ``context.busy`` as the kernels' first compilation is;
    then passes truth through."""

    def __init__(self, context: Any) -> None:
        with context.busy("compiling test kernels (first run only)"):
            time.sleep(float(context.options.get("start_s", 1.0)))

    def process(self, frame: Any) -> TrackResult:
        return frame.truth


class Occludes:
    """A test FrameProcessor that passes truth through but reports frames 3-5 of every run
    as the tracker reports a hand over the mouth: ok false, reason ``occluded: ...``, the
    last good state held."""

    def __init__(self, context: Any) -> None:
        self.n, self.last = 0, None

    def process(self, frame: Any) -> TrackResult:
        self.n += 1
        if 4 <= self.n <= 6 and self.last is not None:
            return TrackResult(frame.index, frame.t, self.last.alpha, self.last.pose, False,
                               "occluded: 5 of 40 sample points on the lips (test)")
        self.last = frame.truth
        return frame.truth


class RefusesVideo:
    """A test FrameProcessor that refuses video files (a session that fails at start, as a
    clip of another aspect ratio than the enrolment does) and passes truth through else."""

    def __init__(self, context: Any) -> None:
        from articast.core.errors import InputError

        if context.source.kind == "file":
            raise InputError("test: this processor refuses video files")

    def process(self, frame: Any) -> TrackResult:
        return frame.truth


class RefusesAll:
    """A test FrameProcessor that refuses every source (a session that fails at start)."""

    def __init__(self, context: Any) -> None:
        from articast.core.errors import InputError

        raise InputError("test: this processor refuses every source")


class HardCrash:
    """A test FrameProcessor whose process dies on frame 3 (no exception, no goodbye)."""

    def __init__(self, context: Any) -> None:
        self.n = 0

    def process(self, frame: Any) -> TrackResult:
        self.n += 1
        if self.n == 3:
            os._exit(3)
        return frame.truth


async def collect(url, session, streams, until_end=True, n=None):
    """(hello, frames) of one subscription until the session ends (or ``n`` frames)."""
    import websockets

    frames, hello = [], None
    async with websockets.connect(url, max_size=2**24, close_timeout=1) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": session, "streams": streams,
                                  "queue": 256}))
        while True:
            m = json.loads(await asyncio.wait_for(ws.recv(), 20 * TIMEOUT))
            if m["type"] == "hello":
                hello = m
            elif m["type"] == "frame":
                frames.append(m)
                if n and len(frames) >= n:
                    return hello, frames
            elif m["type"] == "status" and m["state"] in ("ended", "failed"):
                assert m["state"] == "ended", m
                return hello, frames
            elif m["type"] == "error":
                raise AssertionError(m)

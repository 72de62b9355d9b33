"""The instant demo: the synthetic speaker's trained assets are cached on disk (keyed by the code
that shapes them), and ``articast demo`` prints its URL only once the face streams.
The start-up time itself is measured by ``benchmarks/demo_start.py`` (not a timed test)."""

import json
import os
import subprocess
import sys
import urllib.request

import numpy as np

from articast.core.synthetic.stream import asset_key, open_stream, speaker_assets


def test_assets_are_cached_and_reloaded_identically(tmp_path):
    model, app = speaker_assets(1, "head", "la_quad", tmp_path)
    folder = tmp_path / asset_key(1, "head", "la_quad")
    stamp = (folder / "appearance.npz").stat().st_mtime_ns
    model2, app2 = speaker_assets(1, "head", "la_quad", tmp_path)
    assert (folder / "appearance.npz").stat().st_mtime_ns == stamp  # loaded, not retrained
    np.testing.assert_array_equal(model2.mean, model.mean)
    np.testing.assert_array_equal(model2.basis, model.basis)
    np.testing.assert_array_equal(app2.weights, app.weights)
    np.testing.assert_array_equal(app2.samples.index, app.samples.index)
    # the texture atlas comes from the cache, identical to a built one
    from articast.core.synthetic import texture

    assert (folder / "atlas.npy").is_file() and 1 in texture._PRESET_ATLASES
    np.testing.assert_array_equal(texture.make_atlas(1).image, texture._make_atlas(1).image)
    # the stream tracks with what was cached
    stream = open_stream(1, 30.0, cache_dir=tmp_path)
    np.testing.assert_array_equal(stream.appearance.weights, app.weights)
    # a damaged entry is rebuilt, not fatal
    (folder / "appearance.npz").write_bytes(b"not an npz")
    _, app3 = speaker_assets(1, "head", "la_quad", tmp_path)
    np.testing.assert_allclose(app3.weights, app.weights)


def test_a_stream_started_later_gives_the_same_frames_unrendered_before(tmp_path):
    """``frames(start)`` yields what skipping the first ``start`` frames of a fresh stream
    yields, across a chunk's end (at 0.4 fps a 10 s chunk is 4 frames), without rendering
    the ones before."""
    from articast.core.synthetic import stream as stream_module

    def first(start, n):
        s = open_stream(2, 0.4, cache_dir=tmp_path)
        out = []
        for t, image, truth in s.frames(start):
            out.append((t, image, truth.alpha))
            if len(out) == n:
                return out
        return out

    skipped = first(0, 7)[5:]
    rendered = []
    real = stream_module.default_speaker

    class Counting:
        def __init__(self, seed):
            self.speaker = real(seed)

        def render(self, *a, **k):
            rendered.append(1)
            return self.speaker.render(*a, **k)

    stream_module.default_speaker = Counting
    try:
        started = first(5, 2)
    finally:
        stream_module.default_speaker = real
    assert len(rendered) == 2  # (the five before were not drawn)
    for (t0, im0, a0), (t1, im1, a1) in zip(skipped, started, strict=True):
        assert t0 == t1
        np.testing.assert_array_equal(im0, im1)
        np.testing.assert_array_equal(a0, a1)


def test_key_follows_inputs_and_code():
    keys = {asset_key(1, "head", "la_quad"), asset_key(2, "head", "la_quad"),
            asset_key(1, "desk", "la_quad"), asset_key(1, "head", "la_lin")}
    assert len(keys) == 4
    assert asset_key(1, "head", "la_quad") == asset_key(1, "head", "la_quad")


def test_demo_prints_its_url_once_the_face_streams(tmp_path):
    speaker_assets(1, "head", "la_quad", tmp_path)  # what a first run leaves in the cache
    env = {**os.environ, "ARTICAST_CACHE_DIR": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-m", "articast.service.cli", "demo", "--port", "0",
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line, proc.stderr.read()
        info = json.loads(line)
        http = info["url"].replace("ws://", "http://").rsplit("/ws", 1)[0]
        with urllib.request.urlopen(f"{http}/api/sessions", timeout=10) as r:
            demo = json.load(r)[0]
        assert demo["state"] == "running" and demo["frames"] >= 1, demo
        assert info["avatar"] == f"{http}/avatar/?session=demo"
        with urllib.request.urlopen(info["avatar"], timeout=10) as r:  # the page is served
            assert b'id="overlay"' in r.read()
    finally:
        proc.terminate()
        proc.wait(30)


def test_a_source_that_cannot_open_is_logged_on_the_console():
    """At the default log level, with the reason; and no URL over a page with no face
    (issue 39: the URL was printed for a missing camera): it follows once a face streams."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "serve", "--port", "0", "--json",
         "--source", "cam=v4l2:/dev/video99", "--processor", "tests.service_helpers:ImageStats"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=root)
    try:
        err = ""
        while "unavailable" not in err:
            err = proc.stderr.readline()
            assert err, "no warning on the console"
        assert "session cam: unavailable: /dev/video99" in err and "no such device" in err
        assert "Traceback" not in err
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert out == "", out  # the camera never came: no URL was printed

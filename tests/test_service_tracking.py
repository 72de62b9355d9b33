"""The real tracker behind the service: a fast file replay equals offline `articast track`,
and a session streams MPEG-4 FAPs and ARKit blendshapes consistent with its articulation."""

import asyncio
import json

import numpy as np
import pytest

from articast.service.app import ServiceConfig
from articast.service.cli import main
from articast.service.settings import ServerSettings
from articast.service.worker import SessionSpec
from tests.service_helpers import TIMEOUT, ServerThread, collect


@pytest.fixture(scope="module")
def synthetic_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("syn")
    assert main(["synth", "sequence", "-o", str(d / "train"), "--seed", "1", "--frames", "40",
                 "--fps", "6"]) == 0
    assert main(["synth", "sequence", "-o", str(d / "test"), "--seed", "2", "--frames", "25"]) == 0
    assert main(["train-appearance", str(d / "train/video.mp4"), "--truth",
                 str(d / "train/truth.jsonl"), "--model", str(d / "train/model.npz"), "--camera",
                 str(d / "train/camera.json"), "-o", str(d / "app.npz")]) == 0
    return d


def test_fast_replay_equals_offline_track_and_streams_fap(synthetic_files, tmp_path):
    d = synthetic_files
    track = tmp_path / "track.jsonl"
    assert main(["track", str(d / "test/video.mp4"), "--model", str(d / "train/model.npz"),
                 "--appearance", str(d / "app.npz"), "--camera", str(d / "test/camera.json"),
                 "--init-truth", str(d / "test/truth.jsonl"), "-o", str(track), "--quiet"]) == 0
    offline = [json.loads(x) for x in track.read_text().splitlines()]
    pose0 = json.loads((d / "test/truth.jsonl").read_text().splitlines()[0])["pose"]
    spec = SessionSpec("talk", f"file:{d / 'test/video.mp4'}?pace=fast",
                       model=str(d / "train/model.npz"), appearance=str(d / "app.npz"),
                       camera=str(d / "test/camera.json"), processor="tracker",
                       wait_for_subscriber=True,
                       options={"initial_pose": pose0["rotation"] + pose0["translation"]})
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,))
    with ServerThread(config) as srv:
        hello, frames = asyncio.run(collect(srv.url, "talk",
                                            ["articulatory", "pose", "fap", "arkit"]))
        import httpx

        dense = httpx.get(srv.http + hello["dense_url"], timeout=30).json()
    # the dense face: linear in alpha like the sparse one; stated tolerance 1.5 mm at +-2 s.d.
    m = dense["n_points"]
    assert m > 10 * hello["geometry"]["n_points"]
    assert len(dense["basis"]) == 7 * 3 * m and len(dense["triangles"]) % 3 == 0
    assert dense["linearity_error_mm"] < 1.5
    assert len(frames) == len(offline) == 25
    names = list(offline[0]["alpha"])
    served = np.array([[f["values"]["articulatory"][k] for k in names] for f in frames])
    local = np.array([[o["alpha"][k] for k in names] for o in offline])
    np.testing.assert_allclose(served, local, atol=1e-9)
    assert [f["quality"]["ok"] for f in frames] == [o["quality"]["ok"] for o in offline]
    # FAP units in hello, a FAP stream whose jaw opening follows jaw1
    assert hello["fapu"]["MNS0"] > 0 and hello["fapu"]["MW0"] > 0
    jaw = np.array([f["values"]["fap"]["values"]["3"] for f in frames])
    assert np.corrcoef(jaw, served[:, 0])[0, 1] > 0.9
    assert all(3 in f["values"]["fap"]["mask"] for f in frames)
    # ARKit weights in 0..1, jawOpen rising with jaw1
    jo = np.array([f["values"]["arkit"]["jawOpen"] for f in frames])
    assert ((0 <= jo) & (jo <= 1)).all()
    assert np.corrcoef(jo, served[:, 0])[0, 1] > 0.9


def test_serve_sends_vmc_bundles_while_streaming(tmp_path):
    """--vmc: a real OSC server on loopback receives ARKit blendshapes of a served session."""
    import threading

    from pythonosc.dispatcher import Dispatcher
    from pythonosc.osc_server import ThreadingOSCUDPServer

    from tests.service_helpers import write_recording

    got = []
    disp = Dispatcher()
    disp.map("/VMC/Ext/Blend/Val", lambda addr, name, value: got.append((name, value)))
    osc = ThreadingOSCUDPServer(("127.0.0.1", 0), disp)
    threading.Thread(target=osc.serve_forever, daemon=True).start()
    try:
        from articast.core.synthetic import default_speaker

        rec = tmp_path / "talk.jsonl"
        write_recording(rec, frames=20, fps=30, model=default_speaker(0).model())
        spec = SessionSpec("talk", f"replay-record:{rec}?pace=fast", wait_for_subscriber=True)
        config = ServiceConfig(server=ServerSettings(log_level="critical",
                                                     vmc=f"127.0.0.1:{osc.server_address[1]}"),
                               sessions=(spec,))
        with ServerThread(config) as srv:
            _, frames = asyncio.run(collect(srv.url, "talk", ["articulatory"]))
            import time

            deadline = time.monotonic() + TIMEOUT
            while len({n for n, _ in got if n == "JawOpen"}) == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        osc.shutdown()
    assert frames
    names = {n for n, _ in got}
    assert "JawOpen" in names and all(0.0 <= v <= 1.0 for _, v in got)

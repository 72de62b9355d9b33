"""VMC as receivers expect it, checked with python-osc as the independent parser, and the VRM
vowel presets A I U E O following the synthetic speaker's vowels."""

import json
import threading
import time
import urllib.request

import numpy as np
import pytest
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_packet import OscPacket
from pythonosc.osc_server import ThreadingOSCUDPServer

from articast.core.model.build import invert
from articast.core.model.camera import Camera
from articast.core.outputs.vowels import VOWELS, VowelMapper
from articast.core.synthetic import default_speaker, rest_pose
from articast.service.app import ServiceConfig
from articast.service.security import AccessPolicy
from articast.service.settings import ServerSettings
from articast.service.vmc import MAX_DATAGRAM
from articast.service.wire import describe
from articast.service.worker import SessionSpec
from tests.service_helpers import TIMEOUT, ServerThread
from tests.test_arkit_vmc import vmc_frames

TOKEN = "vmc-test-token-0123456789"


def vowel_states(seed):
    sp = default_speaker(seed)
    corpus, model = sp.corpus(), sp.model()
    alpha = invert(model, corpus.postures)
    names = list(corpus.posture_names)
    return model, {v: alpha[names.index(v)] for v in ("a", "e", "i", "o", "u", "rest")}


def test_vowels_of_the_demo_speaker():
    model, states = vowel_states(1)
    mapper = VowelMapper(model)
    for v in "aeiou":
        w = mapper.weights_dict(states[v])
        assert max(w, key=w.get) == v.upper(), (v, w)
        assert w[v.upper()] > 0.5, (v, w)
        assert all(0.0 <= x <= 1.0 for x in w.values()) and sum(w.values()) <= 1.0 + 1e-9
    assert sum(mapper.weights_dict(states["rest"]).values()) < 0.05  # closed mouth: no vowel


def test_vowels_of_held_out_speakers():
    """Prototypes were set on seeds 0-9; seeds 10-29 are new speakers to them."""
    hits = {v: 0 for v in "aeiou"}
    for seed in range(10, 30):
        model, states = vowel_states(seed)
        mapper = VowelMapper(model)
        for v in "aeiou":
            w = mapper.weights_dict(states[v])
            hits[v] += max(w, key=w.get) == v.upper()
        assert sum(mapper.weights_dict(states["rest"]).values()) < 0.1
    assert hits["a"] == 20 and hits["u"] >= 18, hits
    assert sum(hits.values()) >= 80, hits  # 83 when written


class Bundles(Dispatcher):
    """Every datagram parsed by python-osc: (is_bundle, [(address, args)])."""

    def __init__(self):
        super().__init__()
        self.packets = []
        self.lock = threading.Lock()

    def call_handlers_for_packet(self, data, client_address):
        msgs = [(m.message.address, tuple(m.message.params)) for m in OscPacket(data).messages]
        with self.lock:
            self.packets.append((OscBundle.dgram_is_bundle(data), msgs))
            self.largest = max(getattr(self, "largest", 0), len(data))
        return super().call_handlers_for_packet(data, client_address)


@pytest.fixture
def receiver():
    rec = Bundles()
    server = ThreadingOSCUDPServer(("127.0.0.1", 0), rec)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address, rec
    server.shutdown()
    server.server_close()
    thread.join(TIMEOUT)


HOLD = 12  # frames per vowel


def vowel_recording(path, model, states, fps=30.0, nod_from=None):
    """The speaker holding rest, a, e, i, o, u in turn, head at the rig's rest pose (pitched
    6.5 degrees towards a frontal camera's axis, as in the issue's report); from frame
    ``nod_from`` on, the head is nodded down by 0.1 rad."""
    from articast.core.model.camera import Pose, axis_angle, rotation_matrix

    desc = describe(model, Camera.default(640, 480), model.param_names)
    rest = rest_pose("head")
    nodded = Pose(axis_angle(rotation_matrix(rest.rotation) @ rotation_matrix([0.1, 0, 0])),
                  rest.translation).to_dict()
    rest = rest.to_dict()
    order = ["rest", "a", "e", "i", "o", "u"]
    with path.open("w") as fh:
        fh.write(json.dumps({"type": "header", "format": "articast-record", "version": 1,
                             "session": "v", "source": {"kind": "test", "fps": fps},
                             **desc}) + "\n")
        for i in range(HOLD * len(order)):
            a = states[order[i // HOLD]]
            pose = nodded if nod_from is not None and i >= nod_from else rest
            fh.write(json.dumps({"type": "frame", "seq": i, "frame": i, "t": i / fps,
                                 "alpha": dict(zip(model.param_names, map(float, a))),
                                 "pose": pose, "quality": {"ok": True, "reason": "",
                                 "residual": 0.0, "evals": 0, "iterations": 0, "ms": 0.0}})
                     + "\n")
    return order


@pytest.mark.parametrize("style", ["perfect-sync", "arkit"])
def test_bundles_a_receiver_accepts(receiver, tmp_path, style):
    address, rec = receiver
    model, states = vowel_states(1)
    order = vowel_recording(tmp_path / "v.jsonl", model, states)
    spec = SessionSpec("v", f"replay-record:{tmp_path / 'v.jsonl'}?loop=no",
                       wait_for_subscriber=False)
    config = ServiceConfig(server=ServerSettings(log_level="critical",
                                                 vmc=f"{address[0]}:{address[1]}",
                                                 vmc_names=style), sessions=(spec,),
                           access=AccessPolicy(token=TOKEN))  # recentre is an admin POST
    n = HOLD * len(order)
    with ServerThread(config) as srv:
        deadline = time.monotonic() + 6 * TIMEOUT
        session = srv.service.manager.sessions["v"]
        while session.state != "ended" and time.monotonic() < deadline:
            time.sleep(0.05)
        vmc = srv.service.manager.vmc
        while (len(vmc_frames(list(rec.packets))) < vmc.frames_sent
               and time.monotonic() < deadline):
            time.sleep(0.05)
        published = session.metrics.frames
        with urllib.request.urlopen(urllib.request.Request(
                f"{srv.http}/api/sessions/v/recentre", method="POST",
                headers=srv.headers), timeout=10) as r:
            assert json.load(r) == {"name": "v", "recentred": True}
    time.sleep(0.1)
    with rec.lock:
        packets = vmc_frames(rec.packets)
        assert rec.largest <= MAX_DATAGRAM  # every bundle fits one Ethernet frame
    # one bundle per published frame, every one received (realtime pacing: under load the
    # capture may skip a frame, which is then neither published nor sent)
    assert vmc.frames_sent + vmc.frames_dropped == published and vmc.frames_dropped == 0
    assert len(packets) == published and published >= n // 2
    jaw = "JawOpen" if style == "perfect-sync" else "jawOpen"
    dominant, times = [], []
    for msgs in packets:
        addr = [a for a, _ in msgs]
        assert addr[:4] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos", "/VMC/Ext/Bone/Pos"]
        assert addr[-1] == "/VMC/Ext/Blend/Apply"
        ok, t, root, head = (args for _, args in msgs[:4])
        assert ok == (1,) and isinstance(ok[0], int)
        assert len(t) == 1 and isinstance(t[0], float)
        times.append(t[0])
        assert root[0] == "root" and root[1:] == (0.0,) * 6 + (1.0,)
        assert head[0] == "Head" and len(head) == 8
        # at rest relative to the speaker's neutral: no rotation (not the rig's 6.5 degrees)
        np.testing.assert_allclose(head[4:], [0, 0, 0, 1], atol=1e-6)
        blends = dict(args for a, args in msgs if a == "/VMC/Ext/Blend/Val")
        assert jaw in blends and set(VOWELS) <= set(blends)
        assert all(isinstance(v, float) and 0.0 <= v <= 1.0 for v in blends.values())
        names = set(blends) - set(VOWELS)
        assert all(n[0].isupper() for n in names) == (style == "perfect-sync")
        w = {v: blends[v] for v in VOWELS}
        dominant.append(max(w, key=w.get) if sum(w.values()) > 0.5 else "-")
    assert np.all(np.diff(times) >= 0)
    # the held vowels drive their presets, in order: runs of one dominant preset per vowel
    runs = [[dominant[0], 0]]
    for d in dominant:
        if d == runs[-1][0]:
            runs[-1][1] += 1
        else:
            runs.append([d, 1])
    assert [r[0] for r in runs] == ["-" if v == "rest" else v.upper() for v in order], runs
    assert all(r[1] >= HOLD // 3 for r in runs) and sum(r[1] for r in runs) == published, runs


def test_streamed_pose_is_relative_to_the_neutral_and_recentres(tmp_path):
    from websockets.sync.client import connect

    model, states = vowel_states(1)
    vowel_recording(tmp_path / "v.jsonl", model, states, nod_from=20)
    spec = SessionSpec("v", f"replay-record:{tmp_path / 'v.jsonl'}?loop=no",
                       wait_for_subscriber=True)
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,),
                           access=AccessPolicy(token=TOKEN))  # recentre is an admin POST

    def frames(ws, until):
        while True:
            m = json.loads(ws.recv(timeout=TIMEOUT))
            if m["type"] == "frame":
                yield m
                if until(m):
                    return

    with ServerThread(config) as srv, connect(srv.url, open_timeout=TIMEOUT) as ws:
        ws.send(json.dumps({"type": "subscribe", "session": "v", "streams": ["pose"]}))
        got = list(frames(ws, lambda m: m["frame"] >= 30))
        with urllib.request.urlopen(urllib.request.Request(
                f"{srv.http}/api/sessions/v/recentre", method="POST",
                headers=srv.headers), timeout=10) as r:
            assert r.status == 200
        after = list(frames(ws, lambda m: m["frame"] >= 60))
    for f in got:
        pose = f["values"]["pose"]
        nod = 0.1 if f["frame"] >= 20 else 0.0
        np.testing.assert_allclose(pose["head"]["rotation"], [nod, 0, 0], atol=1e-6)
        np.testing.assert_allclose(pose["head"]["translation"], 0.0, atol=1e-6)
        if f["frame"] < 20:  # the camera-frame pose is the rig's, 6.5 degrees off frontal
            np.testing.assert_allclose(pose["rotation"], rest_pose("head").rotation, atol=1e-9)
    # after the re-centre, the nodded head is the new neutral
    late = [f for f in after if f["frame"] >= 40]
    assert late
    for f in late:
        np.testing.assert_allclose(f["values"]["pose"]["head"]["rotation"], 0.0, atol=1e-6)


def test_every_arkit_mouth_and_jaw_shape_is_driven():
    from articast.core.outputs.arkit import ARKIT_BLENDSHAPES, ArkitMapper

    model = default_speaker(1).model()
    mouth_jaw = {n for n in ARKIT_BLENDSHAPES if n.startswith(("mouth", "jaw"))}
    mapper = ArkitMapper(model)
    assert set(mapper.populated) == mouth_jaw
    # each one really moves within the speaker's range (not a constant 0; the sideways jaw
    # shifts are the smallest: ~0.3 mm, 0.13-0.16 of the 2 mm minimum full scale)
    rng = np.random.default_rng(0)
    s = model.stats
    alpha = rng.uniform(s.min, s.max, size=(400, model.n_params))
    w = mapper.weights(alpha)
    idx = [ARKIT_BLENDSHAPES.index(n) for n in sorted(mouth_jaw)]
    assert np.all(w[:, idx].max(0) > 0.05), dict(zip(sorted(mouth_jaw), w[:, idx].max(0)))

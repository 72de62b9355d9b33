"""ARKit blendshapes from the articulation, and the VMC sender against a real OSC server."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_packet import OscPacket
from pythonosc.osc_server import ThreadingOSCUDPServer

from articast.core.errors import InputError
from articast.core.model.camera import FRONTAL, Pose, axis_angle, rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.outputs.arkit import ARKIT_BLENDSHAPES, ArkitMapper
from articast.core.tracking.result import TrackResult
from articast.service.vmc import (
    DEFAULT_PORT,
    MAX_DATAGRAM,
    VmcSender,
    head_bone,
    parse_host_port,
    quaternion_xyzw,
)
from tests.handmade_face import make_face_model

MODEL = make_face_model()
TIMEOUT = 5.0 * float(os.environ.get("ARTICAST_TEST_TIMEOUT_SCALE", "1"))


def one(name: str, value: float) -> np.ndarray:
    a = np.zeros(MODEL.n_params)
    a[MODEL.param_names.index(name)] = value
    return a


def test_names_are_arkits_52_and_only_mouth_and_jaw_are_driven():
    assert len(ARKIT_BLENDSHAPES) == 52 and len(set(ARKIT_BLENDSHAPES)) == 52
    mapper = ArkitMapper(MODEL)
    assert set(mapper.populated) <= set(ARKIT_BLENDSHAPES)
    assert all(n.startswith(("mouth", "jaw")) for n in mapper.populated)
    assert {"jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft",
            "mouthStretchRight", "mouthLowerDownLeft", "mouthUpperUpRight",
            "mouthRollLower", "mouthRollUpper"} <= set(mapper.populated)


def test_weights_stay_in_0_1_even_far_outside_training(rng):
    w = ArkitMapper(MODEL).weights(rng.normal(scale=4.0, size=(500, 7)))
    assert w.shape == (500, 52) and w.min() >= 0.0 and w.max() <= 1.0
    idx = [ARKIT_BLENDSHAPES.index(n) for n in ARKIT_BLENDSHAPES if n.startswith("eye")]
    assert np.all(w[:, idx] == 0.0)


def test_jaw_open_follows_the_jaw_and_spans_the_training_range():
    mapper = ArkitMapper(MODEL)
    s = MODEL.stats
    jaw = np.linspace(s.min[0], s.max[0], 11)
    w = mapper.weights(np.array([one("jaw1", a) for a in jaw]))
    j = w[:, ARKIT_BLENDSHAPES.index("jawOpen")]
    assert np.all(np.diff(j) > 0) and j[0] == pytest.approx(0.0) and j[-1] == pytest.approx(1.0)
    drop = MODEL.mean[MODEL.point("2.1"), 1] - MODEL.shape(np.array([one("jaw1", a) for a in jaw]))[
        :, MODEL.point("2.1"), 1]
    np.testing.assert_allclose(j, (drop - drop[0]) / (drop[-1] - drop[0]), atol=1e-12)


def test_spreading_and_rounding_are_symmetric_shapes():
    mapper = ArkitMapper(MODEL)
    spread = mapper.weights_dict(one("lips1", 2.5))
    assert spread["mouthStretchLeft"] > 0.5 and spread["mouthStretchLeft"] == pytest.approx(
        spread["mouthStretchRight"])
    assert spread["mouthPucker"] == 0.0 and spread["mouthFunnel"] == 0.0
    rounded = mapper.weights_dict(one("lips1", -2.5))
    assert rounded["mouthPucker"] > 0.2 and rounded["mouthStretchLeft"] == 0.0
    opened = mapper.weights_dict(one("lips1", -2.5) + one("jaw1", 2.5))
    assert opened["mouthFunnel"] > rounded["mouthFunnel"]  # an open rounded mouth funnels
    smile = mapper.weights_dict(one("lips4", 2.5))
    assert smile["mouthSmileLeft"] > 0.5 and smile["mouthFrownLeft"] == 0.0


def test_left_is_the_users_own_left():
    basis = MODEL.basis.copy()
    basis[6] = 0.0
    basis[6, MODEL.point("8.3"), 1] = 2.0  # lar1 replaced: raise the +x (speaker's left) corner
    lopsided = FaceModel(mean=MODEL.mean, basis=basis, stats=MODEL.stats,
                         feature_points=MODEL.feature_points, name="lopsided")
    w = ArkitMapper(lopsided).weights_dict(one("lar1", 2.0))
    assert w["mouthSmileLeft"] > 0.5 and w["mouthSmileRight"] == 0.0


def test_geometry_and_alpha_give_the_same_weights(rng):
    mapper = ArkitMapper(MODEL)
    alpha = rng.uniform(-2.5, 3.0, size=(20, 7))
    np.testing.assert_allclose(mapper.weights_from_geometry(MODEL.shape(alpha)),
                               mapper.weights(alpha), atol=1e-12)
    pts = MODEL.mean.copy()
    pts[MODEL.point("2.1"), 1] -= 100.0  # a jaw far beyond training saturates at 1
    assert mapper.weights_from_geometry(pts)[ARKIT_BLENDSHAPES.index("jawOpen")] == 1.0


def test_unlabelled_points_leave_their_shapes_at_zero():
    fp = {k: v for k, v in MODEL.feature_points.items() if k not in ("8.5", "8.6")}
    m = FaceModel(mean=MODEL.mean, basis=MODEL.basis, stats=MODEL.stats, feature_points=fp)
    mapper = ArkitMapper(m)
    assert "mouthUpperUpLeft" not in mapper.populated and "jawOpen" in mapper.populated
    with pytest.raises(InputError, match=r"shape \(F, 7\)"):
        mapper.weights(np.zeros((2, 6)))


def test_quaternion_round_trip(rng):
    for r in rng.normal(size=(50, 3)):
        q = quaternion_xyzw(rotation_matrix(r))
        x, y, z, w = q
        back = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])  # fmt: skip
        np.testing.assert_allclose(back, rotation_matrix(r), atol=1e-12)


def test_head_bone_in_unity_conventions():
    def bone(rot_head, shift_cam=(0.0, 0.0, 0.0)):
        rot = axis_angle(rotation_matrix(FRONTAL) @ rot_head)
        return head_bone(rot, np.array([0.0, 0.0, 400.0]) + shift_cam, FRONTAL,
                         np.array([0.0, 0.0, 400.0]))

    _, q = bone(rotation_matrix([0.2, 0, 0]))  # pitch down: + about Unity x (nose down)
    np.testing.assert_allclose(q, [np.sin(0.1), 0, 0, np.cos(0.1)], atol=1e-12)
    _, q = bone(rotation_matrix([0, 0.2, 0]))  # to the speaker's left: - about Unity y
    np.testing.assert_allclose(q, [0, -np.sin(0.1), 0, np.cos(0.1)], atol=1e-12)
    # the head moves to the image's right = the speaker's left = Unity -x; 10 mm = 0.01 m
    pos, q = bone(np.eye(3), (10.0, 0.0, 0.0))
    np.testing.assert_allclose(pos, [-0.01, 0, 0], atol=1e-12)
    np.testing.assert_allclose(q, [0, 0, 0, 1], atol=1e-12)


def test_parse_host_port():
    assert parse_host_port("10.0.0.2:39540") == ("10.0.0.2", 39540)
    assert parse_host_port("localhost") == ("localhost", DEFAULT_PORT)
    with pytest.raises(InputError, match="HOST:PORT"):
        parse_host_port("host:http")


class RecordingDispatcher(Dispatcher):
    """Records each datagram as (is_bundle, [(address, args), ...]) and counts Apply."""

    def __init__(self) -> None:
        super().__init__()
        self.packets: list[tuple[bool, list[tuple[str, tuple]]]] = []
        self.cond = threading.Condition()

    def call_handlers_for_packet(self, data, client_address):
        msgs = [(m.message.address, tuple(m.message.params)) for m in OscPacket(data).messages]
        with self.cond:
            self.packets.append((OscBundle.dgram_is_bundle(data), msgs))
            self.largest = max(getattr(self, "largest", 0), len(data))
            self.cond.notify_all()
        return super().call_handlers_for_packet(data, client_address)


def vmc_frames(packets):
    """Datagrams [(is_bundle, [(address, args)])] -> one message list per frame, in time
    order. Each bundle must start with /VMC/Ext/OK and /VMC/Ext/T; a frame's bundles share
    its T (a threaded receiver may swap them: the root/head one goes first, Apply's last)."""
    by_t = {}
    for is_bundle, msgs in packets:
        assert is_bundle
        assert [a for a, _ in msgs[:2]] == ["/VMC/Ext/OK", "/VMC/Ext/T"], msgs[:2]
        by_t.setdefault(msgs[1][1][0], []).append(msgs)
    frames = []
    for t in sorted(by_t):
        parts = sorted(by_t[t], key=lambda m: (m[2][0] != "/VMC/Ext/Root/Pos",
                                               m[-1][0] == "/VMC/Ext/Blend/Apply"))
        frames.append(parts[0][:2] + [m for p in parts for m in p[2:]])
    return frames


@pytest.fixture
def osc_server():
    dispatcher = RecordingDispatcher()
    server = ThreadingOSCUDPServer(("127.0.0.1", 0), dispatcher)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server, dispatcher
    server.shutdown()
    server.server_close()
    thread.join(TIMEOUT)


def test_vmc_sender_bundles_per_frame_to_a_real_osc_server(osc_server):
    server, rec = osc_server
    jaw = np.linspace(-2.0, 3.0, 12)
    results = [
        TrackResult(frame=i, t=i / 30, alpha=one("jaw1", a),
                    pose=Pose(axis_angle(rotation_matrix(FRONTAL) @ rotation_matrix([0.02 * i,
                              0, 0])), [0.0, 0.0, 400.0]))
        for i, a in enumerate(jaw)
    ]
    with VmcSender(*server.server_address) as sender:
        expected = 0
        for r in results:  # one at a time: the threaded server may reorder
            expected += len(sender.bundles(r, MODEL, neutral=results[0].pose))
            assert sender.send(r, MODEL, neutral=results[0].pose)
            with rec.cond:
                assert rec.cond.wait_for(lambda n=expected: len(rec.packets) >= n, TIMEOUT)
    time.sleep(0.05)
    assert len(rec.packets) == expected > len(results)  # split: each under one MTU
    assert rec.largest <= MAX_DATAGRAM
    frames = vmc_frames(rec.packets)
    assert len(frames) == len(results) and sender.frames_sent == len(results)
    jaw_open, pitch = [], []
    for msgs in frames:
        addresses = [a for a, _ in msgs]
        assert addresses[:4] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos",
                                 "/VMC/Ext/Bone/Pos"]
        assert addresses[-1] == "/VMC/Ext/Blend/Apply"
        assert set(addresses[4:-1]) == {"/VMC/Ext/Blend/Val"}
        name, *pose = msgs[3][1]
        assert name == "Head" and len(pose) == 7
        pitch.append(pose[3])  # quaternion x: nodding down over the sequence
        values = {k: v for (k, v) in (args for a, args in msgs if a == "/VMC/Ext/Blend/Val")
                  if k not in ("A", "I", "U", "E", "O")}
        # perfect-sync names by default: ARKit's with the first letter capitalised
        arkit = {n[0].upper() + n[1:] for n in ARKIT_BLENDSHAPES}
        assert set(values) <= arkit and "JawOpen" in values
        assert all(0.0 <= v <= 1.0 for v in values.values())
        jaw_open.append(values["JawOpen"])
    assert np.all(np.diff(jaw_open) > 0) and jaw_open[-1] > 0.9 and jaw_open[0] < 0.1
    assert np.all(np.diff(pitch) > 0) and pitch[0] == pytest.approx(0.0, abs=1e-6)


def test_vmc_sender_refuses_a_bad_port():
    with pytest.raises(InputError, match="port"):
        VmcSender("127.0.0.1", 70000)

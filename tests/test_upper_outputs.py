"""The eyes and brows in every output: ARKit weights, FAPs (stream and .fap files read back),
VMC bundles received and parsed by ``vmcp`` (a VMC library nobody here wrote), the wire
frame's blocks."""

from __future__ import annotations

import math
import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from articast.core.faces.upper import UpperFace
from articast.core.model.camera import FRONTAL, Pose
from articast.core.outputs.fap import FapEncoder, read_fap, write_fap
from articast.core.outputs.upper import (
    BROW_FULL_MM,
    GAZE_FULL_DEG,
    SQUINT_FULL,
    WIDE_DEAD,
    WIDE_FULL,
    arkit_upper,
    eye_rotation,
    fap_upper,
    upper_from_faps,
)
from articast.core.tracking.result import TrackResult
from articast.service.vmc import VmcSender
from tests.handmade_face import make_face_model

MODEL = make_face_model()
TIMEOUT = 5.0 * float(os.environ.get("ARTICAST_TEST_TIMEOUT_SCALE", "1"))


def face(cl: float = 0.2, cr: float = 0.9, yaw: float = 12.0, pitch: float = -6.0,
         brows: tuple[float, float, float, float] = (4.0, 2.0, -2.0, 1.0),
         wide: tuple[float, float] = (0.0, 0.3), lower: tuple[float, float] = (0.1, -0.05),
         squeeze: tuple[float, float] = (1.5, -0.5)) -> UpperFace:
    li, lo, ri, ro = brows
    return UpperFace(True, "", cl, cr, yaw, pitch, "reader", True, "", li, lo, ri, ro,
                     max(0.0, -(li + ri) / 2), *wide, *lower, *squeeze)


def test_arkit_eyes_and_brows():
    w = arkit_upper(face())
    assert w["eyeBlinkLeft"] == pytest.approx(0.2) and w["eyeBlinkRight"] == pytest.approx(0.9)
    # looking to the speaker's left: the left eye looks out, the right one in
    assert w["eyeLookOutLeft"] == pytest.approx(12.0 / GAZE_FULL_DEG) == w["eyeLookInRight"]
    assert w["eyeLookInLeft"] == 0.0 == w["eyeLookOutRight"]
    assert w["eyeLookDownLeft"] == pytest.approx(6.0 / GAZE_FULL_DEG) and w["eyeLookUpLeft"] == 0
    assert w["browInnerUp"] == pytest.approx(1.0 / BROW_FULL_MM)
    assert w["browOuterUpLeft"] == pytest.approx(2.0 / BROW_FULL_MM)
    assert w["browDownRight"] > 0 and w["browDownLeft"] == 0.0
    # wide: beyond the usual open eye, past the measure's noise; squint: the lower lid's rise
    assert w["eyeWideLeft"] == 0.0
    assert w["eyeWideRight"] == pytest.approx((0.3 - WIDE_DEAD) / WIDE_FULL)
    assert w["eyeSquintLeft"] == pytest.approx(0.1 / SQUINT_FULL) and w["eyeSquintRight"] == 0
    assert all(0.0 <= v <= 1.0 for v in w.values())
    # a speaker enrolled before the squint: no eyeSquint rather than a made-up 0
    old = arkit_upper(face(lower=(None, None)))  # type: ignore[arg-type]
    assert "eyeSquintLeft" not in old and "eyeBlinkLeft" in old
    # absent, not zero: nothing for eyes or brows not seen
    assert arkit_upper(UpperFace.absent("not_seen: head rig")) == {}
    assert arkit_upper(None) == {}


def test_eye_rotation_points_the_gaze():
    fwd = eye_rotation(face(yaw=20.0, pitch=10.0)) @ [0.0, 0.0, 1.0]
    assert math.degrees(math.atan2(fwd[0], fwd[2])) == pytest.approx(20.0, abs=1e-6)
    assert math.degrees(math.asin(fwd[1])) == pytest.approx(10.0, abs=1e-6)
    assert eye_rotation(UpperFace.absent("x: y")) is None


def test_fap_eyelids_eyeballs_brows_write_and_read_back(tmp_path: Path):
    enc = FapEncoder(MODEL, reference_rotation=FRONTAL)
    frames = [face(c, 1 - c, 10 * c, -5 * c, (3 * c, c, -c, 2 * c), lower=(0.2 * c, -0.1 * c),
                   squeeze=(2 * c, -c)) for c in (0.0, 0.5, 1.0)]
    vals = np.zeros((3, 68), np.int64)
    mask = enc.mask.copy()
    for i, f in enumerate(frames):
        fap = fap_upper(f, enc.fapu)
        for n, v in fap.items():
            vals[i, n - 1] = v
            mask[n - 1] = True
    assert vals[2, 18] == 1024 and vals[0, 18] == 0  # close_t_l_eyelid: closed = IRISD0
    write_fap(tmp_path / "u.fap", vals, mask, 25.0, "upper")
    back = read_fap(tmp_path / "u.fap")
    for i, f in enumerate(frames):
        got = upper_from_faps({n + 1: int(back.values[i, n]) for n in np.flatnonzero(back.mask[i])},
                              enc.fapu)
        assert got["closure_left"] == pytest.approx(f.closure_left, abs=1e-3)
        assert got["closure_right"] == pytest.approx(f.closure_right, abs=1e-3)
        assert got["gaze_yaw_deg"] == pytest.approx(f.gaze_yaw_deg, abs=1e-3)
        assert got["gaze_pitch_deg"] == pytest.approx(f.gaze_pitch_deg, abs=1e-3)
        ens = enc.fapu.ENS0 / 1024
        assert got["raise_inner_left_mm"] == pytest.approx(f.raise_inner_left_mm, abs=ens)
        assert got["raise_outer_right_mm"] == pytest.approx(f.raise_outer_right_mm, abs=ens)
        # the lower lids (close_b, 21-22, up +) and the brows' squeeze (37-38, ES0 units)
        assert got["lower_lid_left"] == pytest.approx(f.lower_lid_left, abs=1e-3)
        assert got["lower_lid_right"] == pytest.approx(f.lower_lid_right, abs=1e-3)
        es = enc.fapu.ES0 / 1024
        assert got["squeeze_left_mm"] == pytest.approx(f.squeeze_left_mm, abs=es)
        assert got["squeeze_right_mm"] == pytest.approx(f.squeeze_right_mm, abs=es)
    assert vals[2, 36] == round(2.0 / (enc.fapu.ES0 / 1024))  # squeeze_l_eyebrow: 2 mm
    assert fap_upper(UpperFace.absent("x: y"), enc.fapu) == {}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def vmcp_osc():
    """One vmcp OSC system for the module: osc4py3 registers its dispatcher globally, and a
    second system in the same process is refused ("dispatcher name 'global' already used")."""
    vmcp_osc = pytest.importorskip("vmcp.osc")
    backend = pytest.importorskip("vmcp.osc.backend.osc4py3").as_comthreads
    with vmcp_osc.OSC(backend) as osc:
        yield osc


def test_vmcp_receives_blinks_and_eye_bones_from_our_bundles(vmcp_osc):
    from vmcp.events import BlendShapeEvent, BoneTransformEvent
    from vmcp.facades import on_receive

    port = free_udp_port()
    got: list = []
    osc = vmcp_osc
    receiver = osc.create_receiver("127.0.0.1", port, "articast-test").open()
    on_receive(receiver, BlendShapeEvent, got.append)
    on_receive(receiver, BoneTransformEvent, got.append)
    sent = face(cl=0.1, cr=0.8, yaw=15.0, pitch=5.0)
    r = TrackResult(0, 0.0, np.zeros(MODEL.n_params), Pose(FRONTAL), upper=sent)
    with VmcSender("127.0.0.1", port) as sender:
        assert sender.send(r, MODEL)
        end = time.monotonic() + TIMEOUT
        while time.monotonic() < end and not any(
                getattr(e, "key", "") == "Blink_R" for e in got):
            osc.run()
            time.sleep(0.01)
    blends = {e.key: e.value for e in got if isinstance(e, BlendShapeEvent)}
    bones = {str(e.joint.value): e for e in got if isinstance(e, BoneTransformEvent)}
    assert blends["Blink_L"] == pytest.approx(0.1, abs=1e-6)
    assert blends["Blink_R"] == pytest.approx(0.8, abs=1e-6)
    assert blends["EyeBlinkRight"] == pytest.approx(0.8, abs=1e-6)  # perfect sync
    assert blends["EyeLookOutLeft"] == pytest.approx(15.0 / GAZE_FULL_DEG, abs=1e-6)
    assert {"LeftEye", "RightEye", "Head"} <= set(bones)
    q = bones["LeftEye"].rotation
    # Unity is left-handed with x mirrored: a look to the speaker's left is a negative
    # rotation about Unity's +y, looking up a negative one about +x (a nod down is +x)
    half = math.radians(15.0) / 2
    assert q.y == pytest.approx(-math.sin(half) * math.cos(math.radians(5.0) / 2), abs=0.01)
    assert q.x < 0
    # an absent eye sends neither bones nor blinks
    none = VmcSender("127.0.0.1", port).bundles(
        TrackResult(0, 0.0, np.zeros(MODEL.n_params), Pose(FRONTAL),
                    upper=UpperFace.absent("not_seen: head rig")), MODEL)
    names = [m.params[0] for b in none for m in (c for c in b) if m.address in
             ("/VMC/Ext/Blend/Val", "/VMC/Ext/Bone/Pos")]
    assert "Blink_L" not in names and "LeftEye" not in names


def test_wire_frame_carries_eyes_and_brows_with_their_own_ok():
    from articast.client.protocol import Frame, parse_server_message
    from articast.service.outputs import Outputs
    from articast.service.wire import FrameEvent, FrameRecord

    outputs = Outputs(MODEL)
    names = list(MODEL.param_names)

    def record(upper: UpperFace | None, ok: bool = True) -> FrameRecord:
        return FrameRecord(
            seq=0, frame=0, t=0.0, t_capture=0.0, t_tracked=0.0,
            alpha=tuple(0.0 for _ in names), rotation=tuple(FRONTAL), translation=(0, 0, 400.0),
            quality={"ok": ok, "reason": "", "residual": 0.0, "evals": 0, "iterations": 0,
                     "ms": 1.0},
            eyes=None if upper is None else upper.eyes_dict(),
            brows=None if upper is None else upper.brows_dict())

    streams = (("arkit", "fap"), "json")
    seen = FrameEvent("s", 1, record(face(cl=0.7)), names, outputs=outputs)
    text = seen.for_subscriber(streams, dropped=3)
    msg = parse_server_message(text)
    assert isinstance(msg, Frame) and msg.dropped == 3
    assert msg.eyes is not None and msg.eyes.ok and msg.eyes.closure_left == pytest.approx(0.7)
    assert msg.brows is not None and msg.brows.raise_inner_left_mm == pytest.approx(4.0)
    assert msg.values.arkit["eyeBlinkLeft"] == pytest.approx(0.7)
    assert "jawOpen" in msg.values.arkit  # the mouth's still there
    assert msg.values.fap.values["19"] == round(0.7 * 1024)
    # eyes lost while the lips are fine: their own ok and reason, no eye values anywhere
    lost = FrameEvent("s", 1, record(UpperFace.absent("turned: the head is turned 50 deg")),
                      names, outputs=outputs)
    m2 = parse_server_message(lost.for_subscriber(streams, dropped=0))
    assert m2.quality.ok and not m2.eyes.ok and m2.eyes.reason.startswith("turned")
    assert m2.eyes.closure_left is None
    assert "eyeBlinkLeft" not in m2.values.arkit and "19" not in m2.values.fap.values
    # the binary encoding carries the same blocks
    binary = seen.for_subscriber((("arkit", "fap"), "binary"), dropped=2)
    assert isinstance(binary, bytes)
    mb = parse_server_message(binary, {1: "s"}, {1: names})
    assert isinstance(mb, Frame) and mb.dropped == 2 and mb.eyes is not None
    assert mb.eyes.model_dump() == pytest.approx(msg.eyes.model_dump(), abs=1e-5)
    assert mb.brows.model_dump() == pytest.approx(msg.brows.model_dump(), abs=1e-5)
    from articast.client.protocol import ProtocolError
    with pytest.raises(ProtocolError, match="truncated"):  # a cut block: one clear error
        parse_server_message(binary[:-7], {1: "s"}, {1: names})
    lost_b = parse_server_message(lost.for_subscriber((("arkit",), "binary"), dropped=0),
                                  {1: "s"}, {1: names})
    assert not lost_b.eyes.ok and lost_b.eyes.reason == m2.eyes.reason
    assert lost_b.eyes.closure_left is None
    # a processor without the upper face (e.g. ground truth): no blocks
    m3 = parse_server_message(FrameEvent("s", 1, record(None), names,
                                         outputs=outputs).for_subscriber(streams, dropped=0))
    assert m3.eyes is None and m3.brows is None
    m4 = parse_server_message(FrameEvent("s", 1, record(None), names, outputs=outputs)
                              .for_subscriber((("arkit",), "binary"), dropped=0),
                              {1: "s"}, {1: names})
    assert m4.eyes is None and m4.brows is None


def test_hostile_eye_blocks_in_a_recording_never_reach_an_output():
    from articast.core.outputs.fap import fapu_from_model

    d = TrackResult(0, 0.0, np.zeros(MODEL.n_params), Pose(FRONTAL),
                    upper=face()).to_dict(MODEL.param_names)
    d["eyes"].update(closure_left=7.0, gaze_yaw_deg=1e308)
    d["brows"].update(raise_inner_left_mm=float("nan"), raise_outer_left_mm="high")
    back = TrackResult.from_dict(d, MODEL.param_names).upper
    # a closure out of 0..1 is no closure: the eyes are not ok; the brows neither
    assert not back.eyes_ok and back.closure_left is None and back.gaze_yaw_deg is None
    assert not back.brows_ok and back.raise_inner_left_mm is None
    assert fap_upper(back, fapu_from_model(MODEL)) == {} and arkit_upper(back) == {}
    d["eyes"] = "not a block"
    assert TrackResult.from_dict(d, MODEL.param_names).upper is None


def test_a_served_session_sends_its_blinks_eyes_and_brows_over_vmc(speaker4_enrolled, tmp_path,
                                                                   vmcp_osc):
    """Issue 39: a served session's VMC carried the head bone and the mouth only (728 frames,
    no blink, eye or brow message, though its recording had the eyes on 727): the session
    rebuilt each frame for VMC without its eyes and brows. Now a real session (the enrolled
    synthetic speaker, blinking, tracked live, as ``serve --speaker --vmc`` does) sends them,
    received by ``vmcp``, each value the one the session recorded."""
    import json

    from vmcp.events import BlendShapeEvent, BoneTransformEvent
    from vmcp.facades import on_receive

    from articast.service.app import ServiceConfig
    from articast.service.cli import main
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from tests.service_helpers import TIMEOUT as SERVICE_TIMEOUT
    from tests.service_helpers import ServerThread

    clip = tmp_path / "clip"
    assert main(["synth", "sequence", "-o", str(clip), "--seed", "4", "--sentence", "43",
                 "--rig", "desk", "--frames", "60", "--fps", "15", "--upper"]) == 0
    port = free_udp_port()
    got: list = []
    osc = vmcp_osc
    receiver = osc.create_receiver("127.0.0.1", port, "articast-session").open()
    on_receive(receiver, BlendShapeEvent, got.append)
    on_receive(receiver, BoneTransformEvent, got.append)
    config = ServiceConfig(
        server=ServerSettings(log_level="critical", vmc=f"127.0.0.1:{port}",
                              record=str(tmp_path / "rec")),
        sessions=(SessionSpec("me", f"file:{clip / 'video.mp4'}?pace=fast",  # every frame
                              speaker=str(speaker4_enrolled / "speaker")),))
    with ServerThread(config) as srv:
        session = srv.service.manager.sessions["me"]
        end = time.monotonic() + 30 * SERVICE_TIMEOUT
        while session.state not in ("ended", "failed"):
            assert time.monotonic() < end, (session.state, session.detail)
            osc.run()
            time.sleep(0.01)
        assert session.state == "ended", session.detail
    end = time.monotonic() + TIMEOUT  # what is still on its way
    while time.monotonic() < end and not any(
            isinstance(e, BoneTransformEvent) and e.joint.value == "LeftEye" for e in got):
        osc.run()
        time.sleep(0.01)
    for _ in range(20):
        osc.run()
        time.sleep(0.01)
    lines = [json.loads(x) for x in next((tmp_path / "rec").glob("me-*.jsonl")).read_text()
             .splitlines()[1:]]
    eyes = [r["eyes"] for r in lines if r.get("eyes") and r["eyes"]["ok"]]
    brows = [r["brows"] for r in lines if r.get("brows") and r["brows"]["ok"]]
    assert len(eyes) >= 0.8 * len(lines) and len(brows) >= 0.8 * len(lines), len(lines)
    blends: dict[str, list[float]] = {}
    for e in got:
        if isinstance(e, BlendShapeEvent):
            blends.setdefault(e.key, []).append(e.value)
    bones = {str(e.joint.value) for e in got if isinstance(e, BoneTransformEvent)}
    assert {"Head", "LeftEye", "RightEye"} <= bones, bones
    for name in ("Blink_L", "Blink_R", "EyeBlinkLeft", "EyeBlinkRight", "BrowInnerUp",
                 "BrowOuterUpLeft", "BrowOuterUpRight", "JawOpen"):
        assert blends.get(name), (name, sorted(blends))
    # each blink sent is one the session tracked (OSC floats are 32-bit)
    closures = np.array([e["closure_left"] for e in eyes])
    assert all(np.min(np.abs(closures - v)) < 1e-5 for v in blends["Blink_L"])
    assert blends["Blink_L"] == blends["EyeBlinkLeft"]
    # the clip blinks: a closed eye reached the receiver
    assert max(blends["Blink_L"]) > 0.5, max(blends["Blink_L"])

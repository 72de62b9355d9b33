"""Protocol v1: validation, errors with reasons, binary round trip, schema, no heavy imports."""

import json
import subprocess
import sys

import pytest

from articast.client import protocol as P


def test_subscribe_defaults_and_round_trip():
    m = P.parse_client_message('{"type": "subscribe", "session": "alice"}')
    assert isinstance(m, P.Subscribe)
    assert m.streams == ["articulatory", "pose"] and m.encoding == "json" and m.rate is None
    again = P.parse_client_message(m.model_dump_json())
    assert again == m


@pytest.mark.parametrize("text, code", [
    ("{not json", "bad_json"),
    ("[1, 2]", "bad_message"),
    ('{"session": "a"}', "bad_message"),
    ('{"type": "dance"}', "bad_message"),
    ('{"type": "subscribe"}', "bad_message"),
    ('{"type": "subscribe", "session": "a b"}', "bad_message"),
    ('{"type": "subscribe", "session": "a", "streams": ["pose", "smell"]}', "unknown_stream"),
    ('{"type": "subscribe", "session": "a", "streams": []}', "bad_message"),
    ('{"type": "subscribe", "session": "a", "rate": -1}', "bad_message"),
    ('{"type": "subscribe", "session": "a", "encoding": "xml"}', "bad_message"),
    ('{"type": "subscribe", "session": "a", "protocol": 2}', "unsupported_protocol"),
    ('{"type": "subscribe", "session": "a", "extra": 1}', "bad_message"),
    (b"\xff\xfe\x00garbage", "bad_json"),
])
def test_bad_client_messages_have_a_code_and_a_reason(text, code):
    with pytest.raises(P.ProtocolError) as e:
        P.parse_client_message(text)
    assert e.value.code == code
    assert e.value.reason and len(e.value.reason) < 1000
    P.Error(code=e.value.code, reason=e.value.reason)  # it fits an error message


def _frame_dict(**values):
    return {"type": "frame", "session": "alice", "seq": 7, "frame": 9, "t": 0.3,
            "t_capture": 1.5e9, "t_tracked": 1.5e9 + 0.004, "t_sent": 1.5e9 + 0.005,
            "values": values, "dropped": 3,
            "quality": {"ok": True, "reason": "", "residual": 0.25, "evals": 40,
                        "iterations": 5, "ms": 3.5}}


def test_binary_frame_round_trip():
    names = ["jaw1", "lips1", "lips2"]
    d = _frame_dict(articulatory={"jaw1": 0.5, "lips1": -1.25, "lips2": 2.0},
                    pose={"rotation": [3.0, 0.1, -0.2], "translation": [1.0, 2.0, 400.0]},
                    mesh=[0.5, 1.5, 2.5, 3.5, 4.5, 5.5],
                    fap={"values": {"3": 120, "17": -40}, "mask": [3, 17]})
    data = P.encode_frame_binary(d, sid=2, param_names=names)
    assert data[:2] == b"AC"
    f = P.parse_server_message(data, {2: "alice"}, {2: names})
    assert isinstance(f, P.Frame)
    assert f.session == "alice" and f.seq == 7 and f.frame == 9 and f.dropped == 3
    assert f.t_tracked == d["t_tracked"]  # times stay float64
    assert f.values.articulatory == pytest.approx(d["values"]["articulatory"])
    assert f.values.pose.translation == pytest.approx([1.0, 2.0, 400.0])
    assert f.values.mesh == pytest.approx(d["values"]["mesh"])
    assert f.values.fap.values == {"3": 120, "17": -40}
    assert f.quality.residual == pytest.approx(0.25) and f.quality.evals == 40
    assert f.lips is None  # a frame without lip measures decodes without them


def test_binary_frame_carries_lip_measures():
    d = _frame_dict(articulatory={"jaw1": 0.5})
    d["lips"] = {"aperture_mm": 12.5, "width_mm": 41.25}
    f = P.parse_server_message(P.encode_frame_binary(d, 1, ["jaw1"]), {1: "a"}, {1: ["jaw1"]})
    assert f.lips.aperture_mm == pytest.approx(12.5) and f.lips.width_mm == pytest.approx(41.25)
    # and the JSON form validates to the same
    j = P.parse_server_message(json.dumps(d))
    assert j.lips == P.Lips(aperture_mm=12.5, width_mm=41.25)


def test_binary_is_compact_and_dropped_is_patchable():
    names = [f"p{i}" for i in range(7)]
    d = _frame_dict(articulatory={n: 0.1 for n in names},
                    pose={"rotation": [0, 0, 0], "translation": [0, 0, 400]})
    data = P.encode_frame_binary(d, 1, names)
    assert len(data) == P.BINARY_HEADER.size + 7 * 4 + 6 * 4
    assert len(data) < len(json.dumps(d)) / 3
    import struct
    patched = data[:P.DROPPED_OFFSET] + struct.pack("<I", 99) + data[P.DROPPED_OFFSET + 4:]
    assert P.parse_server_message(patched, {}, {1: names}).dropped == 99


def test_truncated_binary_frame_is_a_protocol_error():
    names = ["a", "b"]
    data = P.encode_frame_binary(_frame_dict(articulatory={"a": 1.0, "b": 2.0}), 1, names)
    with pytest.raises(P.ProtocolError):
        P.parse_server_message(data[:-3], {}, {1: names})


def test_server_messages_validate():
    P.parse_server_message(json.dumps(_frame_dict(articulatory={"jaw1": 0.1})))
    P.parse_server_message(P.Status(session="a", state="unavailable", detail="x").model_dump_json())
    with pytest.raises(ValueError):  # pydantic's ValidationError is a ValueError
        P.parse_server_message('{"type": "frame"}')


def test_schema_covers_both_directions():
    s = P.protocol_schema()
    text = json.dumps(s)
    for name in ("Subscribe", "Hello", "Frame", "Status", "Error", "Geometry", "FapValue"):
        assert name in text
    assert s["binary_frame"]["header_size"] == P.BINARY_HEADER.size


def test_protocol_imports_without_numpy_opencv_fastapi():
    code = ("import sys; import articast.client.protocol; import articast.client; "
            "bad = [m for m in ('numpy', 'cv2', 'fastapi', 'core', 'articast.service', "
            "'articast.core') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_frame_header_names_every_field():
    d = _frame_dict(articulatory={"jaw1": 0.5})
    d["lips"] = {"aperture_mm": 3.0, "width_mm": 48.0}
    h = P.frame_header(P.encode_frame_binary(d, 4, ["jaw1"]))
    assert (h.magic, h.sid, h.seq, h.frame, h.dropped, h.evals) == (b"AC", 4, 7, 9, 3, 40)
    assert h.t_tracked == d["t_tracked"] and h.lip_width_mm == 48.0 and h.ok == 1
    assert len(P.FrameHeader._fields) == len(P.BINARY_HEADER.unpack_from(b"\0" * 80))

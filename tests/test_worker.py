"""The worker without a server: source -> processor -> messages, recording, NaN guard."""

import json
import threading

import numpy as np

from articast.core.model.camera import Pose
from articast.core.tracking.result import TrackResult
from articast.service.settings import CaptureSettings
from articast.service.worker import SessionSpec, _record, run_worker
from tests.service_helpers import write_recording


def run(spec, record_dir=""):
    msgs = []
    stop, go = threading.Event(), threading.Event()
    go.set()
    run_worker(spec, CaptureSettings(), record_dir, msgs.append, stop, go)
    return msgs


def test_a_fast_replay_emits_ready_every_frame_then_ended(tmp_path):
    rec = tmp_path / "r.jsonl"
    truth = write_recording(rec, frames=25)
    msgs = run(SessionSpec("s", f"replay-record:{rec}?pace=fast"), str(tmp_path / "out"))
    kinds = [m[0] for m in msgs]
    assert kinds[kinds.index("ready")] == "ready" and kinds[-1] == "done"
    assert msgs[-1][1] == "ended"
    frames = [m[1] for m in msgs if m[0] == "frame"]
    assert [f.seq for f in frames] == list(range(25))
    for f, t in zip(frames, truth, strict=True):
        np.testing.assert_allclose(f.alpha, t.alpha)
        assert f.t_capture <= f.t_tracked
    desc = next(m for m in msgs if m[0] == "ready")[1]
    assert desc["geometry"]["n_points"] == 12
    lines = next((tmp_path / "out").glob("s-*.jsonl")).read_text().splitlines()
    assert len(lines) == 26 and json.loads(lines[0])["type"] == "header"


def test_input_errors_fail_and_crashes_are_crashes(tmp_path):
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"junk" * 100)
    done = run(SessionSpec("s", f"file:{bad}", processor="truth"))[-1]
    assert done[:2] == ("done", "failed") and "bad.avi" in done[2]
    rec = tmp_path / "r.jsonl"
    write_recording(rec, frames=10)
    done = run(SessionSpec("s", f"replay-record:{rec}?pace=fast",
                           processor="tests.service_helpers:Crashy"))[-1]
    assert done[:2] == ("done", "crashed") and "boom" in done[2]
    done = run(SessionSpec("s", f"replay-record:{rec}", processor="nope"))[-1]
    assert done[:2] == ("done", "failed") and "unknown processor" in done[2]


def test_stop_before_go_is_a_clean_stop():
    stop, go = threading.Event(), threading.Event()
    stop.set()
    msgs = []
    run_worker(SessionSpec("s", "v4l2:/dev/video97"), CaptureSettings(), "", msgs.append,
               stop, go)
    assert msgs == [("done", "stopped", "")]


def test_non_finite_results_never_reach_the_wire():
    r = TrackResult(0, 0.0, np.array([np.nan, 1.0, np.inf]), Pose(), residual=float("nan"))
    rec = _record(0, 0, 0.0, 1.0, 2.0, r, 1.0, 0)
    json.dumps(rec.quality, allow_nan=False)
    assert rec.alpha == (0.0, 1.0, 0.0) and rec.quality["ok"] is False
    assert rec.quality["residual"] == -1.0


def test_a_gap_in_a_recording_is_said_alive_at_the_interval_asked(tmp_path):
    """A recording's gap is waited out saying ``alive``; once a second was as often as the
    stall bound of a session held to 1 s, and a sign of life handed over late restarted it
    (tests/test_hardening.py). The worker says it at the interval the session asks: a
    quarter of the shortest bound."""
    from articast.service.worker import alive_interval

    assert alive_interval(1.0, 120.0) == 0.25 and alive_interval(10.0, 120.0) == 1.0
    assert alive_interval(0.0, 0.0) == 1.0  # no watchdog: the default
    rec = tmp_path / "gap.jsonl"
    write_recording(rec, frames=4, fps=20)
    lines = rec.read_text().splitlines()
    shifted = [json.dumps({**json.loads(x), "t": json.loads(x)["t"] + 2.5}) for x in lines[3:]]
    rec.write_text("\n".join([*lines[:3], *shifted]) + "\n")  # 2.5 s of nothing after frame 1
    msgs = []
    stop, go = threading.Event(), threading.Event()
    go.set()
    run_worker(SessionSpec("s", f"replay-record:{rec}"), CaptureSettings(), "", msgs.append,
               stop, go, alive_s=0.25)
    kinds = [m[0] for m in msgs]
    assert kinds.count("frame") == 4 and msgs[-1][:2] == ("done", "ended")
    frames = [i for i, k in enumerate(kinds) if k == "frame"]
    gap = kinds[frames[1]:frames[2]]
    assert gap.count("alive") >= 6, gap  # ~10 in 2.5 s; once a second gave 3

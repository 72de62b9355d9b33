"""The synthetic speaker's eyes and brows (core/synthetic/upper.py): a person's blink timing,
and what is painted follows the truth."""

from __future__ import annotations

import numpy as np
import pytest

from articast.core.errors import InputError
from articast.core.synthetic.texture import SKIN_PPM, SKIN_X0, SKIN_Y1, make_atlas
from articast.core.synthetic.upper import BROW_Y, EYE_X, EYE_Y, paint_upper, upper_sequence


def test_blinks_like_a_person():
    fps = 30.0
    u = upper_sequence(3, int(300 * fps), fps)  # five minutes
    per_minute = len(u.blinks) / 5.0
    assert 10.0 <= per_minute <= 20.0
    starts = np.array([s for s, _ in u.blinks])
    assert (np.diff(starts) < 0.45 * fps).any()  # some double blinks
    lengths = np.array([e - s for s, e in u.blinks])
    assert lengths.min() >= 3 and lengths.max() <= 9  # 100-300 ms at 30 fps
    assert np.all((u.closure >= 0) & (u.closure <= 1))
    assert np.abs(u.gaze[:, 0]).max() <= 15 and np.abs(u.gaze[:, 1]).max() <= 10
    assert u.gaze[:, 0].std() > 3 and u.brows.max() > 2 and u.brows.min() >= 0
    with pytest.raises(InputError):
        upper_sequence(0, 0, 30.0)


def px(x_mm: float, y_mm: float) -> tuple[int, int]:
    """Atlas (row, col) of a neutral head-frame point."""
    return int((SKIN_Y1 - y_mm) * SKIN_PPM), int((x_mm - SKIN_X0) * SKIN_PPM)


def test_painted_eyes_follow_the_truth():
    open_ = paint_upper(0, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0)).astype(float)
    shut = paint_upper(0, (1.0, 0.0), (0.0, 0.0), (0.0, 0.0)).astype(float)
    for side, x in ((0, EYE_X), (1, -EYE_X)):
        r, c = px(x + 9.0, EYE_Y)  # the sclera, beside the iris
        if side == 0:
            assert open_[r, c].mean() > 200 and shut[r, c].mean() < 190  # the lid covers it
        else:
            assert shut[r, c].mean() > 200  # the other eye stays open
    looking = paint_upper(0, (0.0, 0.0), (15.0, 0.0), (0.0, 0.0)).astype(float)
    r, c = px(EYE_X, EYE_Y)  # the eye's centre: the pupil looking ahead, the iris looking left
    assert open_[r, c].mean() < 20 and 50 < looking[r, c].mean() < 100
    r, c = px(EYE_X + 11.5 * np.sin(np.radians(15.0)), EYE_Y)  # where the pupil went
    assert looking[r, c].mean() < 20 and open_[r, c].mean() > 50
    raised = paint_upper(0, (0.0, 0.0), (0.0, 0.0), (5.0, 0.0)).astype(float)
    r0, c0 = px(EYE_X, BROW_Y)
    r1, _ = px(EYE_X, BROW_Y + 5.0)
    assert raised[r0, c0].mean() > open_[r0, c0].mean() + 20  # the brow has left its place
    assert raised[r1, c0].mean() < open_[r1, c0].mean() - 20  # and is 5 mm higher
    # everything outside the eyes' region is the speaker's own atlas
    base = make_atlas(0).image.astype(float)
    rl, cl = px(0.0, 0.0)
    assert np.array_equal(open_[rl - 40:rl + 40, cl - 40:cl + 40],
                          base[rl - 40:rl + 40, cl - 40:cl + 40])


def test_cli_synth_sequence_with_upper_writes_its_truth(tmp_path):
    import json

    import cv2

    from articast.service.cli import main

    out = tmp_path / "s"
    assert main(["synth", "sequence", "-o", str(out), "--rig", "desk", "--frames", "60",
                 "--fps", "10", "--size", "320x240", "--upper"]) == 0
    lines = [json.loads(x) for x in (out / "truth.jsonl").read_text().splitlines()]
    assert len(lines) == 60 and all("upper" in r for r in lines)
    closure = np.array([r["upper"]["closure_left"] for r in lines])
    want = upper_sequence(0, 60, 10.0).closure[:, 0]  # --sentence defaults to --seed 0
    assert np.allclose(closure, want) and closure.max() > 0.5  # a blink in 6 s
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 60


def test_upper_scores_against_the_truth():
    from articast.core.evaluation.upper import score_upper
    from articast.core.faces.upper import UpperFace

    truth = upper_sequence(5, 900, 30.0)

    def faces(shift: int = 0, absent: bool = False):
        out = []
        for i in range(900):
            j = min(max(i - shift, 0), 899)
            if absent:
                out.append(UpperFace.absent("not_seen: head rig"))
                continue
            c, g, b = truth.closure[j], truth.gaze[j], truth.brows[j]
            out.append(UpperFace(True, "", c[0], c[1], g[0], g[1], "reader", True, "",
                                 b[0], b[0], b[1], b[1], 0.0))
        return out

    exact = score_upper(faces(), truth, 30.0)
    assert exact["blink_f1"] == 1.0 and exact["true_blinks"] == exact["tracked_blinks"] > 5
    assert exact["onset_within_1"] == 1.0 and exact["gaze_median_error_deg"] == 0.0
    assert exact["closure_r"] == [1.0, 1.0] and exact["brow_r"] == [1.0, 1.0]
    late = score_upper(faces(shift=3), truth, 30.0)  # three frames late: found, but late
    assert late["blink_f1"] == 1.0 and late["onset_within_1"] == 0.0
    assert set(late["onset_frames"]) == {3}
    gone = score_upper(faces(absent=True), truth, 30.0)
    assert gone["eyes_ok"] == 0.0 and gone["blink_recall"] == 0.0 and gone["blink_f1"] == 0.0


def test_evaluate_refuses_a_bad_upper_length(capsys):
    from articast.service.cli import main

    assert main(["evaluate", "--quick", "--upper", "--upper-seconds", "0.5"]) == 2
    assert "--upper-seconds" in capsys.readouterr().err


def test_a_blink_is_not_split_by_a_gap_shorter_than_a_reopening():
    """Runs of blink frames apart by <= 50 ms (one frame at 30 fps, three at 60) are one
    blink, in the synthetic scorer and benchmarks/blinks.py alike; a longer gap (the eye
    seen open for two frames at 30 fps: 67 ms) parts two blinks."""
    from articast.core.evaluation.upper import blink_events

    flags = np.zeros(40, bool)
    flags[[5, 6, 8, 9, 20, 21, 24, 25]] = True  # a one-frame gap, then a two-frame one
    assert blink_events(flags, 30.0) == [(5, 10), (20, 22), (24, 26)]
    assert blink_events(flags, 24.0) == [(5, 10), (20, 22), (24, 26)]
    assert blink_events(flags, 60.0) == [(5, 10), (20, 26)]  # 2 frames at 60 fps: 33 ms
    assert blink_events(flags, 12.0) == [(5, 7), (8, 10), (20, 22), (24, 26)]  # 83 ms
    with pytest.raises(InputError, match="frame rate"):
        blink_events(flags, 0.0)


def test_a_flickering_blink_matches_once():
    from articast.core.evaluation.upper import match_events

    ref = [(10, 18), (40, 44)]
    # the first blink read as three short events, the second missed, one false event
    ours = [(10, 12), (13, 15), (16, 18), (70, 72)]
    prec, rec, onsets = match_events(ours, ref)
    assert rec == 0.5 and onsets == [0]
    assert prec == 0.25  # the flicker's two extra pieces are false events
    prec, rec, onsets = match_events([(11, 17), (39, 45)], ref)
    assert prec == rec == 1.0 and onsets == [1, -1]
    # within a tolerance: a tracked event just after the true one still matches
    assert match_events([(19, 21)], [(10, 18)], tol=2)[1] == 1.0
    assert match_events([(19, 21)], [(10, 18)], tol=0)[1] == 0.0
    # by overlap alone (against another detector whose events fragment too): each piece of
    # the flicker is a true event, and one event over two reference pieces finds both
    assert match_events(ours, ref, one_to_one=False)[:2] == (0.75, 0.5)
    assert match_events([(10, 30)], [(10, 12), (20, 25)], one_to_one=False)[:2] == (1.0, 1.0)
    assert match_events([(10, 30)], [(10, 12), (20, 25)])[:2] == (1.0, 0.5)

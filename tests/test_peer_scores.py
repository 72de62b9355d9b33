"""The peer benchmark's scoring (benchmarks/peers.py) on series whose answer is known."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
peers = pytest.importorskip("peers")


def test_consensus_leaves_the_scored_method_out_and_needs_two_others():
    a = np.array([9.0, 9.0, 9.0, 9.0])
    b = np.array([1.0, 1.0, np.nan, np.nan])
    c = np.array([2.0, 3.0, 5.0, np.nan])
    d = np.array([4.0, np.nan, 7.0, np.nan])
    series = {"a": a, "b": b, "c": c, "d": d}
    got = peers.consensus(series, leave_out="a")
    np.testing.assert_allclose(got[:3], [2.0, 2.0, 6.0])  # median of b, c, d only: a left out
    assert np.isnan(got[3])  # no other method has a value
    without_c = peers.consensus(series, leave_out="c")  # a is an "other" now
    np.testing.assert_allclose(without_c[:3], [4.0, 5.0, 8.0])
    assert np.isnan(without_c[3])  # only a has a value: fewer than 2 others
    with_a = peers.consensus(series, leave_out="b")
    np.testing.assert_allclose(with_a[:3], [4.0, 6.0, 7.0])


def test_a_method_alone_has_no_consensus_and_is_still_scored():
    """--methods articast facemesh_v1 on a clip articast cannot enrol (no face) leaves one
    method: no consensus, no lag, its jitter still (it crashed the run before)."""
    rng = np.random.default_rng(0)
    ap = rng.normal(0.2, 0.05, 60)
    assert np.isnan(peers.consensus({"v1": ap}, leave_out="v1")).all()
    got = peers.score({"v1": ap}, [slice(0, 10), slice(30, 40)])["v1"]
    assert got["consensus_r"] is None and got["consensus_n"] == 0 and got["lag_frames"] is None
    assert got["jitter_pct_width"] is not None and got["jitter_pct_width"] > 0


def test_lag_is_positive_when_the_method_is_late():
    rng = np.random.default_rng(0)
    ref = np.convolve(rng.normal(size=300), np.ones(4) / 4, mode="same")
    late = np.concatenate([np.full(2, np.nan), ref[:-2]])  # x[t] = ref[t - 2]
    early = np.concatenate([ref[3:], np.full(3, np.nan)])  # x[t] = ref[t + 3]
    assert peers.lag(late, ref) == 2
    assert peers.lag(early, ref) == -3
    assert peers.lag(ref, ref) == 0


def test_jitter_is_the_rms_about_the_linear_trend_in_percent():
    t = np.arange(8.0)
    trend = 0.2 + 0.01 * t
    noise = 0.001 * np.array([1, -1, -1, 1, 1, -1, -1, 1])  # orthogonal to 1 and t per window
    windows = [slice(0, 4), slice(4, 8)]
    assert peers.jitter(trend, windows) == pytest.approx(0.0, abs=1e-9)
    assert peers.jitter(trend + noise, windows) == pytest.approx(0.1, rel=1e-6)
    # a window with a frame missing is left out, not filled
    gappy = trend + noise
    gappy[5] = np.nan
    assert peers.jitter(gappy, windows) == pytest.approx(0.1, rel=1e-6)


@pytest.mark.parametrize("scheme", ["mediapipe", "ibug68", "openseeface"])
def test_aperture_ratio_is_the_gap_normal_to_the_corners_over_the_width(scheme):
    up, low, right, left, top, bottom = peers.SCHEMES[scheme]
    pts = np.zeros((2, max(peers.SCHEMES[scheme]) + 1, 2))
    pts[0, [right, left, up, low, top, bottom]] = [[0, 0], [10, 0], [4, -1], [6, 2], [5, -3],
                                                   [5, 4]]
    turn = np.deg2rad(30)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    pts[1] = pts[0] @ rot.T * 2 + [100, 50]  # the same mouth turned, scaled and moved
    np.testing.assert_allclose(peers.aperture_ratio(pts, scheme), [0.3, 0.3])
    np.testing.assert_allclose(peers.lip_box(pts[:1], scheme), [[0, -3, 10, 4]])


def test_pearson_needs_enough_common_frames():
    x = np.arange(20.0)
    r, n = peers.pearson(x, 2 * x + 1)
    assert (round(r, 9), n) == (1.0, 20)
    y = np.where(x < 15, np.nan, x)
    assert np.isnan(peers.pearson(x, y)[0]) and peers.pearson(x, y)[1] == 5


def test_the_gap_to_the_best_peer_has_an_interval_that_excludes_zero_only_when_it_is_real():
    rng = np.random.default_rng(1)
    n, block = 600, 25
    truth = np.convolve(rng.normal(size=n), np.ones(8) / 8, mode="same")
    good = truth + 0.05 * rng.normal(size=n)
    bad = truth + 0.3 * rng.normal(size=n)
    gap, lo, hi = peers.gap_interval(good, bad, truth, truth, block)
    assert gap > 0 and 0 < lo <= gap <= hi  # the better method's lead is beyond the sampling
    same, lo, hi = peers.gap_interval(good, good.copy(), truth, truth, block)
    assert same == lo == hi == 0.0  # paired: the same frames for both, no spurious gap
    twin = truth + 0.05 * rng.normal(size=n)  # as good, other noise: the interval holds 0
    gap, lo, hi = peers.gap_interval(good, twin, truth, truth, block)
    assert lo < 0 < hi
    assert peers.gap_interval(good[:30], bad[:30], truth[:30], truth[:30], block) is None


def test_the_jitter_gap_resamples_the_still_windows():
    rng = np.random.default_rng(2)
    windows = [slice(s, s + 10) for s in range(0, 200, 20)]
    steady = 0.001 * rng.normal(size=200)
    shaky = 0.01 * rng.normal(size=200)
    gap, lo, hi = peers.window_gap_interval(shaky, steady, windows)
    assert gap > 0 and 0 < lo <= gap <= hi
    assert peers.window_gap_interval(shaky, steady, windows[:1]) is None


def test_against_best_names_the_best_peer_of_each_score():
    rng = np.random.default_rng(3)
    n = 400
    truth = np.convolve(rng.normal(size=n), np.ones(8) / 8, mode="same")
    aps = {"articast": truth + 0.2 * rng.normal(size=n),
           "a": truth + 0.02 * rng.normal(size=n),  # the closest to the others
           "b": truth + 0.1 * rng.normal(size=n),
           "c": truth + 0.1 * rng.normal(size=n)}
    windows = [slice(s, s + 10) for s in range(0, n - 10, 40)]
    scores = peers.score(aps, windows)
    got = peers.against_best(aps, scores, windows, fps=25.0)
    assert got["r"]["peer"] == "a" and got["r"]["ci95"][1] < 0  # articast clearly behind
    assert got["jitter"]["peer"] == min(("a", "b", "c"),
                                        key=lambda k: scores[k]["jitter_pct_width"])
    assert got["jitter"]["gap"] > 0


def test_consensus_validity_compares_the_two_rankings_where_the_truth_is_known():
    """The consensus that ranks the methods backwards against the truth scores -1; a method
    without one of the two figures is left out of both rankings."""
    rows = {"a": {"consensus_r": 0.90, "truth_r": 0.80},
            "b": {"consensus_r": 0.95, "truth_r": 0.70},
            "c": {"consensus_r": 0.80, "truth_r": 0.90},
            "d": {"consensus_r": None, "truth_r": 0.99},
            "e": {"skipped": "not set up"}}
    got = peers.consensus_validity(rows)
    assert got["spearman"] == -1.0
    assert got["by_consensus"] == ["b", "a", "c"] and got["by_truth"] == ["c", "a", "b"]
    rows["c"]["consensus_r"] = 0.99  # now c first by both, a and b swapped: 0.5
    assert peers.consensus_validity(rows)["spearman"] == 0.5
    assert peers.consensus_validity({"a": rows["a"], "b": rows["b"]}) is None

# ---------------------------------------------------------------------------- timing
class _Virtual:
    """A clock that moves only when a fake method works: its cost per frame, and per build."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _fake(clock: _Virtual, build_s: float, frame_s, seen: list):
    """A builder whose construction costs build_s and whose frame i costs frame_s(i); it
    records (pass, frame) as it works."""
    passes = []

    def build():
        clock.now += build_s
        passes.append(len(passes))
        p = passes[-1]

        def step(i):
            seen.append((p, i))
            clock.now += frame_s(i)
            return i * 10
        return step
    return build


def test_chunk_schedule_gives_every_frame_once_in_order_and_alternates_who_goes_first():
    sched = peers.chunk_schedule(7, 3, 2)
    assert [(a, b) for a, b, _ in sched] == [(0, 3), (3, 6), (6, 7)]
    assert [o for _, _, o in sched] == [(0, 1), (1, 0), (0, 1)]
    assert peers.chunk_schedule(0, 3, 2) == []
    with pytest.raises(ValueError):
        peers.chunk_schedule(5, 0, 2)


def test_timed_pass_keeps_construction_out_of_the_per_frame_cost():
    clock, seen = _Virtual(), []
    got = peers.timed_pass(_fake(clock, 0.5, lambda i: 0.002, seen), 4, clock, clock)
    assert got["outputs"] == [0, 10, 20, 30]
    assert got["build_ms"] == pytest.approx(500.0) and got["build_cpu_ms"] == pytest.approx(500.0)
    assert got["ms"] == pytest.approx(2.0) and got["cpu_ms"] == pytest.approx(2.0)


def test_interleaved_cost_times_each_method_on_its_own_turns_fresh_every_pass():
    clock, seen_a, seen_b = _Virtual(), [], []
    # a costs 3 ms a frame plus 30 ms on its first frame (a start); b 2 ms; builds 1 s / 2 s
    a = _fake(clock, 1.0, lambda i: 0.003 + (0.030 if i == 0 else 0.0), seen_a)
    b = _fake(clock, 2.0, lambda i: 0.002, seen_b)
    costs = peers.interleaved_cost({"a": a, "b": b}, 10, repeats=2, chunk=4, wall=clock,
                                   cpu=clock)
    # every pass builds afresh and runs every frame once, in order
    assert seen_a == [(p, i) for p in range(2) for i in range(10)]
    assert seen_b == [(p, i) for p in range(2) for i in range(10)]
    assert costs["a"]["ms"] == pytest.approx([6.0, 6.0])  # (10 * 3 + 30) / 10
    assert costs["b"]["cpu_ms"] == pytest.approx([2.0, 2.0])
    assert costs["a"]["build_ms"] == pytest.approx([1000.0, 1000.0])
    assert costs["b"]["build_cpu_ms"] == pytest.approx([2000.0, 2000.0])
    got = peers.interleaved_ratios(costs, "a", base="b")
    assert got["passes"] == 2
    assert got["cpu_x_v1"]["median"] == pytest.approx(3.0)
    assert got["x_v1"]["runs"] == [3.0, 3.0]


def test_ratio_spread_pairs_the_passes():
    got = peers.ratio_spread([6.0, 4.0, 9.0], [3.0, 4.0, 3.0])
    assert got["runs"] == [2.0, 1.0, 3.0]  # pass by pass, not the ratio of the means
    assert (got["median"], got["min"], got["max"]) == (2.0, 1.0, 3.0)
    assert peers.ratio_spread([1.0], [0.0])["median"] is None
    with pytest.raises(ValueError):
        peers.ratio_spread([1.0, 2.0], [1.0])


def test_set_changes_one_field_of_the_live_policy_and_refuses_what_is_not_one():
    """``--set FIELD=VALUE`` (peers.py, enrolment_spread.py): a FusionPolicy field or the
    streamed filter's, on top of the variant; anything else is a one-line error."""
    from articast.core.faces.live import FusionPolicy, LivePolicy
    from articast.core.tracking.filters import OneEuroPolicy

    assert peers.policy_with(None, []) is None  # nothing set: the variant as it is
    got = peers.policy_with(None, ["appearance_weight=2", "cadence=none", "regression=false",
                                   "read_every=2", "one_euro.beta=3"])
    assert got.fusion == FusionPolicy(appearance_weight=2.0, cadence=None, regression=False,
                                      read_every=2)
    assert got.smoothing == OneEuroPolicy(beta=3.0)
    base = peers.VARIANTS["no_one_euro"]  # a variant's own changes are kept
    kept = peers.policy_with(base, ["points_weight=0.1"])
    assert kept.fusion.points_weight == 0.1 and kept.smoothing is None
    for bad, says in (("appearnce_weight=2", "no policy field"), ("beta", "FIELD=VALUE"),
                      ("one_euro.gamma=1", "one_euro has no field"),
                      ("one_euro.beta=none", "takes a number"),
                      ("read_every=often", "not a number")):
        with pytest.raises(ValueError, match=says):
            peers.policy_with(None, [bad])
    with pytest.raises(ValueError, match="without fusion"):
        peers.policy_with(LivePolicy(fusion=None), ["read_every=2"])


def _z(v):
    return (v - np.nanmean(v)) / np.nanstd(v)


def test_the_judge_gives_each_family_outside_facemesh_one_vote():
    """articast and every FaceMesh-family method are scored against the same series, made of
    the other families only (one vote each, however many members, each vote z-scored over its
    frames); a method of another family is not its own judge."""
    n = 5
    osf = np.array([1.0, 2.0, 3.0, np.nan, np.nan])
    dl = np.array([3.0, 4.0, 5.0, 7.0, np.nan])
    fm = {k: np.full(n, 100.0) for k in ("articast", "facemesh_v1", "facelandmarker_v2",
                                         "mediapipe")}
    aps = {**fm, "openseeface": osf, "dlib": dl}
    both = (_z(osf) + _z(dl)) / 2
    for k in fm:  # the FaceMesh family never votes, for any of its members
        np.testing.assert_allclose(peers.judge(aps, k)[:4], [*both[:3], _z(dl)[3]])
        assert np.isnan(peers.judge(aps, k)[4])
    np.testing.assert_allclose(peers.judge(aps, "openseeface")[:4], _z(dl)[:4])  # dlib alone
    np.testing.assert_allclose(peers.judge(aps, "dlib")[:3], _z(osf)[:3])
    # a second member of a family does not give the family a second vote
    two = {**aps, "dlib_2": np.array([3.0, 4.0, 5.0, 7.0, np.nan])}
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(peers.FAMILIES, "dlib_2", "dlib")
        np.testing.assert_allclose(peers.judge(two, "articast")[:3], both[:3])


def test_the_judge_is_the_median_of_three_families_whatever_their_scales():
    """With three families each frame's judge is the middle vote, and a family's scale and
    offset (the schemes' ratios differ in both) neither decide which vote is the middle one
    nor weigh its vote: one family's error on a frame is outvoted by the other two."""
    rng = np.random.default_rng(3)
    n = 200
    truth = np.convolve(rng.normal(size=n), np.ones(6) / 6, mode="same")
    votes = {"openseeface": truth + 0.01 * rng.normal(size=n),
             "dlib": truth + 0.01 * rng.normal(size=n),
             "faceapi": truth + 0.01 * rng.normal(size=n)}
    votes["faceapi"][50] += 3.0  # one family's blunder on one frame
    aps = {"articast": truth, **votes}
    j = peers.judge(aps, "articast")
    assert abs(j[50] - _z(truth)[50]) < 0.1  # outvoted
    # the same judge when one family's series is scaled and shifted (z-scores are unchanged)
    scaled = {**aps, "dlib": 10.0 * votes["dlib"] + 5.0}
    np.testing.assert_allclose(peers.judge(scaled, "articast"), j)
    # unscaled, the middle of the three would mostly be one family: the judge would follow
    # it, blunder included; z-scored, r with the truth stays near 1
    assert peers.pearson(j, truth)[0] > 0.99


def test_against_reader_scores_articast_and_its_reader_on_the_same_judge():
    rng = np.random.default_rng(4)
    n = 500
    truth = np.convolve(rng.normal(size=n), np.ones(8) / 8, mode="same")
    aps = {"articast": truth + 0.02 * rng.normal(size=n),
           "facemesh_v1": truth + 0.2 * rng.normal(size=n),  # the reader, noisier
           "facelandmarker_v2": truth + 0.1 * rng.normal(size=n),
           "openseeface": truth + 0.05 * rng.normal(size=n),
           "dlib": truth + 0.05 * rng.normal(size=n)}
    windows = [slice(s, s + 10) for s in range(0, n - 10, 40)]
    scores = peers.score(aps, windows)
    got = peers.against_reader(aps, scores, windows, fps=25.0)
    assert got["r_vs_reader"]["peer"] == "facemesh_v1"
    assert got["r_vs_reader"]["ci95"][0] > 0  # better than its reader, beyond the sampling
    assert got["r_vs_best_facemesh"]["peer"] == "facelandmarker_v2"
    assert got["jitter_vs_reader"]["gap"] < 0
    assert got["lag_velocity_vs_reader"] == 0
    late = {**aps, "articast": np.roll(aps["facemesh_v1"], 2)}  # the reader two frames late
    assert peers.against_reader(late, peers.score(late, windows), windows, 25.0)[
        "lag_velocity_vs_reader"] == 2
    assert got["judge"] == "other families"
    # where the truth is known it judges: the peers all err alike here (they share a bias
    # that articast does not), so the other families' judge calls articast worse than its
    # reader, the truth better
    bias = np.sin(np.arange(n) / 7.0)
    biased = {k: (v if k == "articast" else v + bias) for k, v in aps.items()}
    biased["facemesh_v1"] = truth + bias + 0.3 * rng.normal(size=n)
    s = peers.score(biased, windows)
    assert peers.against_reader(biased, s, windows, 25.0)["r_vs_reader"]["ci95"][1] < 0
    by_truth = peers.against_reader(biased, s, windows, 25.0, truth=truth)
    assert by_truth["judge"] == "truth" and by_truth["r_vs_reader"]["ci95"][0] > 0


def test_a_clips_folder_is_read_as_it_is(tmp_path):
    """--clips takes ../shared/clips as it is: every video file by its stem, no list."""
    import common

    for name in ("b.mp4", "a.MOV", "notes.md", "c.txt", "d.y4m"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.mp4").mkdir()
    got = common.clip_paths(tmp_path)
    assert list(got) == ["a", "b", "d"] and got["a"] == tmp_path / "a.MOV"
    assert common.clip_paths(tmp_path / "missing") == {}
    (tmp_path / "clips.json").write_text('[{"name": "x", "path": "/somewhere/x.mp4"}]')
    assert common.clip_paths(tmp_path) == {"x": Path("/somewhere/x.mp4")}  # a fetched cache


def test_the_still_windows_are_placed_without_the_scored_methods_box():
    """articast's own lip box does not place the still windows (a variant that moved its box
    would move the windows, and its reader's jitter with them); the others' boxes do, and all
    of them where articast is alone."""
    a, v1, dl = (np.full((4, 4), x) for x in (1.0, 2.0, 3.0))
    got = peers.window_boxes({"articast": a, "facemesh_v1": v1, "dlib": dl})
    assert len(got) == 2 and all(g is not a for g in got)
    assert peers.window_boxes({"articast": a})[0] is a

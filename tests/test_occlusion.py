"""The occlusion test (``occluded``) on the synthetic speaker, against ground truth: a hand
sliding over the chin and mouth is flagged before it spoils the articulation, and clean
sequences have no occluded frame."""

from dataclasses import replace

import numpy as np
import pytest

from articast.core.evaluation.experiments import HAND_SLIDE, HAND_SLIDE_FROM, HAND_SLIDE_IN
from articast.core.evaluation.measures import rms_3d
from articast.core.model.build import invert
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence
from articast.core.synthetic.enrol import enrolment_appearance, enrolment_frames
from articast.core.tracking.tracker import Tracker, TrackingPolicy


@pytest.fixture(scope="module")
def speaker():
    return default_speaker(0)


@pytest.fixture(scope="module")
def head_app(speaker):
    return enrolment_appearance(speaker, "head", "la_lin",
                                enrolment_frames(speaker, "head", 1, 75, 6.0))


def track(speaker, app, rig, seq_seed, n, options_for_frame, policy=None):
    seq = make_sequence(seq_seed, n, 50.0, rig)
    model = speaker.model()
    truth = invert(model, seq.points)
    tracker = Tracker(model, app, seq.camera, policy or TrackingPolicy.for_rig(rig),
                      initial_pose=seq.pose(0))
    tracker.reset(seq.pose(0), truth[0])
    res = [tracker.track(speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                                        options_for_frame(i)), float(seq.times[i]))
           for i in range(n)]
    rms = rms_3d(model, np.array([r.alpha for r in res]), truth)
    return res, rms


def sliding_hand(i):
    """The hand_slide condition's first sequence: from below the chin onto the mouth."""
    a, b = HAND_SLIDE
    if not a <= i < b:
        return RenderOptions(seed=1000 + i)
    left = max(0.0, 1.0 - (i - a) / HAND_SLIDE_IN)
    dx, dy = HAND_SLIDE_FROM[0]
    return RenderOptions(seed=1000 + i, occluder="hand", occluder_shift=(dx * left, dy * left))


def test_a_hand_sliding_over_the_chin_is_flagged_occluded_not_streamed_wrong(speaker, head_app):
    a, b = HAND_SLIDE
    # without the occlusion test the robust fit tracks the first frames of the hand through,
    # and streams some more than 1 mm wrong as ok
    off, rms_off = track(speaker, head_app, "head", 2, b + 10, sliding_hand,
                         replace(TrackingPolicy.for_rig("head"), occlusion_q=None))
    ok_off = np.array([r.ok for r in off])
    assert not any(r.reason.startswith("occluded") for r in off)
    assert rms_off[a:b][ok_off[a:b]].max() > 1.0

    res, rms = track(speaker, head_app, "head", 2, b + 10, sliding_hand)
    ok = np.array([r.ok for r in res])
    occluded = [i for i in range(a, b) if res[i].reason.startswith("occluded")]
    assert occluded, [r.reason for r in res[a:b]]
    # nothing the hand spoils is streamed as ok
    assert rms[a:b][ok[a:b]].max(initial=0.0) < 1.0
    # an occluded frame streams the last good state, and the fit carries on underneath
    for i in occluded:
        last_ok = max(j for j in range(i) if ok[j])
        np.testing.assert_array_equal(res[i].alpha, res[last_ok].alpha)
        assert "alpha_fit" in res[i].extra
    # clean frames before the hand are untouched; after it, ok and accurate at once
    assert ok[:a].all()
    assert ok[b:b + 3].all() and rms[b:b + 3].max() < 1.0


@pytest.mark.parametrize("rig,seq_seed", [("head", 2), ("head", 3), ("desk", 2)])
def test_clean_sequences_have_no_occluded_frame_where_the_fit_is_right(speaker, head_app, rig,
                                                                       seq_seed):
    """No hand, no occluded frame -- except where the fit itself went wrong on the lips (on an
    earlier main, desk sequence 2 frame 41 was 4.3 mm off, streamed ok without the test, and
    flagged): such a frame should not be ok either way; an accurate one must not be flagged."""
    app = head_app if rig == "head" else enrolment_appearance(
        speaker, "desk", "la_lin", enrolment_frames(speaker, "desk", 1, 75, 6.0))
    res, _ = track(speaker, app, rig, seq_seed, 150, lambda i: RenderOptions(seed=1000 + i))
    seq = make_sequence(seq_seed, 150, 50.0, rig)
    model = speaker.model()
    truth = invert(model, seq.points)
    flagged = [r.frame for r in res if r.reason.startswith("occluded")]
    if rig == "head":
        assert flagged == []
    fit_err = rms_3d(model, np.array([res[i].extra["alpha_fit"] for i in flagged]).reshape(
        -1, model.n_params), truth[flagged])
    assert np.all(fit_err > 2.0), dict(zip(flagged, fit_err))
    assert len(flagged) <= 3
    assert np.mean([r.ok for r in res]) >= 0.97


def test_a_second_opinion_can_overrule_the_appearance_occlusion_verdict(speaker, head_app):
    """``Evidence.confirm``: the fused tracker's landmarks confirm fits the appearance calls
    occluded where the appearance was never trained (an opening wider than the enrolment's).
    The hook is asked about the fit the appearance flagged, and its yes streams that fit."""
    from articast.core.tracking.tracker import Evidence

    a, b = HAND_SLIDE
    seq = make_sequence(2, b + 2, 50.0, "head")
    model = speaker.model()
    truth = invert(model, seq.points)
    asked = []

    def confirm(alpha, pose):
        asked.append(np.array(alpha))
        return True

    for answer in (False, True):
        tracker = Tracker(model, head_app, seq.camera, TrackingPolicy.for_rig("head"),
                          initial_pose=seq.pose(0))
        tracker.reset(seq.pose(0), truth[0])
        ev = Evidence(confirm=confirm if answer else (lambda alpha, pose: False))
        res = [tracker.track(speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                                            sliding_hand(i)), float(seq.times[i]), evidence=ev)
               for i in range(b + 2)]
        occluded = [r for r in res if r.reason.startswith("occluded")]
        if not answer:
            assert occluded  # the hook's no leaves the verdict
        else:
            assert not occluded and asked
            assert any(np.allclose(r.alpha, x) for r in res for x in asked)


def test_points_seen_edge_on_do_not_vote_for_an_occlusion(speaker, head_app):
    """``occlusion_facing``: outliers only where the face is seen edge-on (a jaw line against
    the background) flag nothing; the same outliers flag the frame when every point votes,
    and outliers on points facing the camera still do."""
    model = speaker.model()
    seq = make_sequence(2, 30, 50.0, "desk")
    policy = TrackingPolicy.for_rig("desk")
    tracker = Tracker(model, head_app, seq.camera, policy, initial_pose=seq.pose(0))
    assert tracker.policy.occlusion_facing is not None
    truth = invert(model, seq.points)
    tracker.reset(seq.pose(0), truth[0])
    for i in range(20):  # (the per-point running levels)
        tracker.track(speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                                     RenderOptions(seed=1000 + i)), float(seq.times[i]))
    frontal = seq.pose(20)
    mouth = np.argmin(np.abs(tracker.problem.s_mean[:, 0]))
    assert tracker.facing(frontal)[mouth] > 0.8  # the front of the face faces the camera
    # the head turned 35 deg further: one side's jaw line is seen edge-on
    from articast.core.model.camera import Pose, axis_angle

    c, s_ = np.cos(0.6), np.sin(0.6)
    yaw = np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
    pose = Pose(axis_angle(yaw @ frontal.matrix), frontal.translation)
    facing = tracker.facing(pose)
    assert facing[mouth] < tracker.facing(frontal)[mouth]
    judged = np.flatnonzero(tracker._judged)
    # a pair of judged points seen most edge-on, next to each other (within the span)
    order = judged[np.argsort(facing[judged])]
    edge = [int(order[0])] + [int(j) for j in order[1:]
                              if tracker._span[order[0], j]][:1]
    top = order[::-1]
    front = [int(top[0])] + [int(j) for j in top[1:] if tracker._span[top[0], j]][:1]
    assert facing[edge].max() < policy.occlusion_facing < facing[front].min(), (
        facing[edge], facing[front])
    level = tracker._qlevel.copy()

    def verdict(points, facing_limit):
        tracker.policy = replace(policy, occlusion_facing=facing_limit)
        tracker._qlevel = level.copy()
        q = np.full(len(facing), 8.0)
        q[points] = 1e4
        return tracker.occlusion(q, 1.0, pose=pose)

    assert verdict(edge, None) is not None  # every point votes: flagged
    assert verdict(edge, policy.occlusion_facing) is None
    assert verdict(front, policy.occlusion_facing) is not None

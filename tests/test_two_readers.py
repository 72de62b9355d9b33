"""Two readers live (core/faces/two_readers.py): the opt-in stream that averages a FaceMesh v1
reader's tracker and a FaceLandmarker v2 reader's, on the rendered speaker whose truth is
known; the command line and the service ask for it with ``--readers 2``."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from articast.core.faces.speaker import Speaker
from articast.core.model.face import FaceModel
from articast.core.outputs.lips import lip_measures, lips_dict
from articast.core.tracking.result import TrackResult
from articast.service.cli import main


@pytest.fixture(scope="module")
def clip(tmp_path_factory, speaker4_enrolled):
    """Speaker 4's folder (enrolled once per session, conftest.py) and a 2 s test clip of
    theirs at 25 fps, another sentence than the enrolment's."""
    d = tmp_path_factory.mktemp("two_readers")
    shutil.copytree(speaker4_enrolled / "speaker", d / "speaker")
    assert main(["synth", "sequence", "-o", str(d / "test"), "--seed", "4", "--sentence", "42",
                 "--rig", "desk", "--frames", "50", "--fps", "25"]) == 0
    return d


def _frames(d):
    from articast.service.video import iter_video

    return [(t, img) for _, t, img in iter_video(d / "test" / "video.mp4")]


def _truth(d):
    truth = [json.loads(line) for line in (d / "test" / "truth.jsonl").read_text().splitlines()]
    model = FaceModel.load(d / "test" / "model.npz")
    alpha = np.array([[r["alpha"][n] for n in model.param_names] for r in truth])
    return lip_measures(model, alpha)[0]


def _result(alpha, ok=True, **extra) -> TrackResult:
    from articast.core.model.camera import Pose

    return TrackResult(frame=0, t=0.0, alpha=np.asarray(alpha, float),
                       pose=Pose(np.zeros(3), np.zeros(3)), ok=ok, extra=extra)


def test_paired_is_the_mean_where_both_are_ok_else_the_first():
    from articast.core.faces.two_readers import paired

    a, b = _result([1.0, 2.0, 0.0], tag="first"), _result([3.0, -2.0, 1.0])
    got = paired(a, b)
    assert np.array_equal(got.alpha, [2.0, 0.0, 0.5])
    assert got.extra["tag"] == "first"  # the first's verdicts and extras stand
    assert np.array_equal(got.extra["alpha_second"], b.alpha)
    assert got.pose is a.pose
    for first, second in ((a, _result([3.0, -2.0, 1.0], ok=False)),
                          (_result([1.0, 2.0, 0.0], ok=False), b)):
        assert paired(first, second) is first
    with pytest.raises(ValueError, match="parameters"):
        paired(a, _result([1.0, 2.0]))


def test_two_readers_stream_the_mean_of_two_live_trackers_and_follow_the_truth(clip):
    """The pair's frame is the mean of what the product's tracker and a v2 reader's tracker,
    each built alone with its own networks, stream on the same frames: sharing the finder
    changes neither. Verdicts, head pose and the upper face are the first's; the lips are the
    mean's; the frame's time is both trackers'. On the rendered speaker the stream follows
    the true lip aperture."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LivePolicy, LiveTracker
    from articast.core.faces.offline import second_reader
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.two_readers import TwoReaderTracker

    sp = Speaker.load(clip / "speaker")
    frames = _frames(clip)
    scheme = mediapipe_scheme(sp.rig)
    pair = TwoReaderTracker.of(LiveTracker(sp, FaceFinder.load(), scheme))
    sp2 = second_reader(sp)
    assert sp2 is not None and sp2.upper is None
    fusion = LivePolicy().fusion
    assert fusion is not None
    alone = (LiveTracker(sp, FaceFinder.load(), scheme),
             LiveTracker(sp2, FaceFinder.load(), scheme,
                         LivePolicy(fusion=replace(fusion, reader="v2"))))
    both = differ = 0
    for t, img in frames:
        got = pair.track(img, t)
        a, b = (tr.track(img, t) for tr in alone)
        assert got.ok == a.ok and got.reason == a.reason
        assert np.array_equal(got.pose.rotation, a.pose.rotation)
        assert (got.upper is None) == (a.upper is None)
        if a.upper is not None:
            assert got.upper.eyes_dict() == a.upper.eyes_dict()
        assert got.ms >= a.ms  # (both trackers' time: never less than the first's)
        if a.ok and b.ok:
            both += 1
            assert np.allclose(got.alpha, 0.5 * (a.alpha + b.alpha), atol=1e-9)
            differ += not np.allclose(a.alpha, b.alpha, atol=1e-3)
        else:
            assert np.allclose(got.alpha, a.alpha, atol=1e-9)
        assert got.lips == pytest.approx(lips_dict(sp.model, got.alpha))
    assert both >= 0.9 * len(frames) and differ >= 0.5 * both  # the second reader counts
    # the stream on its own: the true lip aperture followed
    pair = TwoReaderTracker.of(LiveTracker(sp, FaceFinder.load(), scheme))
    out = [pair.track(img, t) for t, img in frames]
    ok = np.array([r.ok for r in out])
    ap = np.array([r.lips["aperture_mm"] for r in out])
    assert ok.mean() >= 0.9 and np.corrcoef(ap[ok], _truth(clip)[ok])[0, 1] > 0.95


def test_a_speaker_without_the_v2_readers_model_is_refused_in_one_line(clip, tmp_path,
                                                                      capsys):
    """A speaker folder without the v2 observation model (enrolled before it was learned)
    cannot be tracked with two readers: the class, the track command and the serving
    commands each say why in one line and what to do; --readers 2 asks for a speaker, and
    for --causal in track (offline tracking reads two readers already)."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.two_readers import TwoReaderTracker, readers_problem

    old = tmp_path / "old"
    shutil.copytree(clip / "speaker", old)
    (old / "points_v2.npz").unlink()
    sp = Speaker.load(old)
    assert sp.finder_points is None
    with pytest.raises(ValueError, match="enrol again"):
        TwoReaderTracker.of(LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig)))
    assert "enrol again" in readers_problem(sp, 2) and readers_problem(sp, 1) == ""
    assert "1 or 2" in readers_problem(Speaker.load(clip / "speaker"), 3)
    video, out = str(clip / "test" / "video.mp4"), str(tmp_path / "t.jsonl")
    for argv, says in (
            (["track", video, "--speaker", str(old), "--causal", "--readers", "2", "-o", out],
             "enrol again"),
            (["track", video, "--speaker", str(clip / "speaker"), "--readers", "2", "-o", out],
             "--causal"),
            (["serve", "--source", f"a=file:{video}", "--speaker", str(old), "--readers", "2"],
             "enrol again"),
            (["serve", "--source", f"a=file:{video}", "--readers", "2"], "needs --speaker")):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err and "Traceback" not in err, (argv, err)


def test_track_causal_with_two_readers_writes_the_pairs_stream(clip, tmp_path):
    """``articast track --causal --readers 2`` writes, frame by frame, what the live service
    streams with ``--readers 2``: the pair's (against the class run on the same frames),
    with the one reader's verdicts, and other lips than the one reader's on most frames."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.two_readers import TwoReaderTracker

    lines = {}
    for readers in (1, 2):
        out = tmp_path / f"r{readers}.jsonl"
        assert main(["track", str(clip / "test" / "video.mp4"), "--speaker",
                     str(clip / "speaker"), "--causal", "--readers", str(readers), "-o",
                     str(out), "--quiet"]) == 0
        lines[readers] = [json.loads(x) for x in out.read_text().splitlines()]
    sp = Speaker.load(clip / "speaker")
    names = sp.model.param_names
    pair = TwoReaderTracker.of(LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig)))
    moved = 0
    for (t, img), two, one in zip(_frames(clip), lines[2], lines[1], strict=True):
        want = pair.track(img, t)
        assert two["quality"]["ok"] == want.ok == one["quality"]["ok"]
        if want.ok:
            a2, a1 = (np.array([x["alpha"][n] for n in names]) for x in (two, one))
            assert np.allclose(a2, want.alpha, atol=1e-6)
            moved += not np.allclose(a2, a1, atol=1e-3)
    assert moved >= 0.5 * len(lines[2])


def test_a_serve_session_with_readers_2_streams_the_pairs_frames(clip, tmp_path):
    """The session option ``readers`` (``serve --readers``, ``"readers"`` in POST) reaches
    the live processor: 2 streams the pair's frames, 1 (the default) the one reader's; a bad
    count or a speaker without the v2 model fails the session with one line."""
    from articast.core.errors import InputError
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.two_readers import TwoReaderTracker
    from articast.service.processors import LiveProcessor, ProcessorContext
    from articast.service.source_types import Frame, SourceInfo

    sp = Speaker.load(clip / "speaker")
    info = SourceInfo("file:video.mp4", "file", False, sp.camera.width, sp.camera.height)

    def context(options, speaker=sp):
        return ProcessorContext("s", info, speaker.model, speaker.camera, speaker.appearance,
                                options, speaker, None)

    frames = _frames(clip)[:20]
    streams = {}
    for readers in (1, 2):
        proc = LiveProcessor(context({"readers": readers} if readers == 2 else {}))
        streams[readers] = [proc.process(Frame(i, t, 0.0, img))
                            for i, (t, img) in enumerate(frames)]
    pair = TwoReaderTracker.of(LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig)))
    moved = 0
    for (t, img), two, one in zip(frames, streams[2], streams[1], strict=True):
        want = pair.track(img, t)
        assert two.ok == want.ok == one.ok
        if want.ok:
            assert np.allclose(two.alpha, want.alpha, atol=1e-9)
            moved += not np.allclose(two.alpha, one.alpha, atol=1e-3)
    assert moved >= 0.5 * len(frames)
    old = replace(sp, finder_points=None)
    for options, speaker, says in (({"readers": 3}, sp, "1 or 2"),
                                   ({"readers": 2}, old, "enrol again")):
        with pytest.raises(InputError) as err:
            LiveProcessor(context(options, speaker))
        assert says in str(err.value) and "\n" not in str(err.value)

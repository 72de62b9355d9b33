"""A real-speaker workflow with nothing but videos: enroll, then track; ok must mean ok.

The synthetic speaker stands in for a person: its videos are rendered, the enrolment sees only
the video (landmarks from the bundled face models, no ground truth), and the truth is used
only to check the result.
"""

import json
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest

from articast.core.errors import ModelFileError
from articast.core.faces.speaker import Speaker
from articast.core.model.face import FaceModel
from articast.core.outputs.lips import lip_measures
from articast.service.cli import main


def _write_video(path, frames, fps=25.0):
    h, w = frames[0].shape[:2]
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for f in frames:
        wr.write(f)
    wr.release()


def _track_lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def enrolled(tmp_path_factory, speaker4_enrolled):
    """Speaker 4 enrolled from a 20 s desk clip (6 fps) with the README's commands."""
    d = tmp_path_factory.mktemp("enrol")
    for part in ("clip", "speaker"):  # enrolled once per session (conftest.py)
        shutil.copytree(speaker4_enrolled / part, d / part)
    assert main(["synth", "sequence", "-o", str(d / "test"), "--seed", "4", "--sentence", "41",
                 "--rig", "desk", "--frames", "75", "--fps", "25"]) == 0
    return d


def test_enroll_writes_a_speaker_folder_with_the_seven_parameters(enrolled, capsys):
    sp = Speaker.load(enrolled / "speaker")
    assert sp.model.param_names == ("jaw1", "lips1", "lips2", "lips3", "lips4", "jaw2", "lar1")
    assert np.all(sp.model.basis[6] == 0)  # the throat is not observable: lar1 stays 0
    var = sp.report["variance_pct"]
    assert var["lar1"] == 0 and sum(var.values()) > 85
    assert var["jaw1"] > 10 and var["lips1"] > 10  # the two big speech modes are found
    assert sp.residual.p99 >= sp.residual.median > 0
    # the scale assumption is stated, and the model is in mm: a plausible mouth
    assert "63 mm" in sp.report["scale"]
    # a desk camera enrols from the landmarks' own pixels (the optical flow did not help the
    # real webcam clips: docs/history/REAL_SPEAKERS_LOG.md)
    assert sp.report["pixels"] == "landmarks"
    ap, wd = lip_measures(sp.model, np.zeros(7))
    assert 30 < wd < 70 and 0 <= ap < 15
    # a contact sheet of what it learned: enrolment frames with the fitted model drawn
    sheet = cv2.imread(str(enrolled / "speaker" / "contact.png"))
    assert sheet is not None and sheet.shape[0] >= 240 and sheet.shape[1] == 3 * 240
    assert "contact sheet" not in capsys.readouterr().out  # --json: the report only
    # the upper face's references, from the same clip; its static eyes never blink: said
    assert sp.upper is not None and sp.upper.open_mm[0] > sp.upper.closed_mm[0] > 0
    assert sp.report["upper"]["eyes_visible"] and sp.report["upper"]["blinks"] == 0
    assert any("no blink" in w for w in sp.report["warnings"])


def test_track_with_only_the_speaker_folder_follows_the_true_articulation(enrolled, capsys):
    out = enrolled / "track.jsonl"
    assert main(["track", str(enrolled / "test" / "video.mp4"), "--speaker",
                 str(enrolled / "speaker"), "-o", str(out), "--quiet"]) == 0
    lines = _track_lines(out)
    assert len(lines) == 75
    ok = np.array([r["quality"]["ok"] for r in lines])
    assert ok.mean() >= 0.95
    truth = _track_lines(enrolled / "test" / "truth.jsonl")
    true_model = FaceModel.load(enrolled / "test" / "model.npz")
    at = np.array([[r["alpha"][n] for n in true_model.param_names] for r in truth])
    a = np.array([[r["alpha"][n] for n in true_model.param_names] for r in lines])
    # the enrolled model's parameters mean what the paper's do: jaw opening is jaw opening
    assert np.corrcoef(a[ok, 0], at[ok, 0])[0, 1] > 0.85
    # lip aperture in mm follows the true aperture
    ap = np.array([r["lips"]["aperture_mm"] for r in lines])
    ap_true, _ = lip_measures(true_model, at)
    assert np.corrcoef(ap[ok], ap_true[ok])[0, 1] > 0.9
    # every line has the eyes and brows; the rendered eyes stay open and look ahead
    eyes = [r["eyes"] for r in lines]
    assert all(e["ok"] for e, k in zip(eyes, ok, strict=True) if k)
    closure = np.array([e["closure_left"] for e in eyes if e["ok"]])
    assert np.all((closure >= 0) & (closure <= 1)) and np.median(closure) < 0.3
    assert all("raise_left_mm" in r["brows"] for r in lines)


def test_offline_track_is_the_live_estimate_smoothed_with_the_frames_after(enrolled):
    """``articast track --speaker --single-reader`` writes each frame smoothed with the frames
    after it (core/faces/offline.py: the motion model's fixed-lag smoother, the One Euro
    filter both ways); ``--causal`` writes what the live service streams. Same frames and
    verdicts; the smoothed lip aperture is nearer the truth and steadier, and its lips are
    its own articulation's."""
    got = {}
    for causal in (False, True):
        out = enrolled / f"track-{'causal' if causal else 'offline'}.jsonl"
        assert main(["track", str(enrolled / "test" / "video.mp4"), "--speaker",
                     str(enrolled / "speaker"), "-o", str(out), "--quiet",
                     *(["--causal"] if causal else ["--single-reader"])]) == 0
        got[causal] = _track_lines(out)
    off, live = got[False], got[True]
    assert [r["frame"] for r in off] == [r["frame"] for r in live]
    verdict = [{k: v for k, v in r["quality"].items() if k != "ms"} for r in off]
    assert verdict == [{k: v for k, v in r["quality"].items() if k != "ms"} for r in live]
    ok = np.array([r["quality"]["ok"] for r in off])
    assert ok.mean() >= 0.95
    truth = _track_lines(enrolled / "test" / "truth.jsonl")
    true_model = FaceModel.load(enrolled / "test" / "model.npz")
    ap_true, _ = lip_measures(true_model, np.array(
        [[r["alpha"][n] for n in true_model.param_names] for r in truth]))
    sp = Speaker.load(enrolled / "speaker")
    err, rough = {}, {}
    for causal, lines in got.items():
        ap = np.array([r["lips"]["aperture_mm"] for r in lines])
        alpha = np.array([[r["alpha"][n] for n in sp.model.param_names] for r in lines])
        assert np.allclose(ap, lip_measures(sp.model, alpha)[0], atol=0.01)
        # (the enrolled model's mm are its own: the error once its mean offset is taken off)
        d = ap[ok] - ap_true[ok]
        err[causal] = float(np.mean(np.abs(d - np.median(d))))
        rough[causal] = float(np.std(np.diff(ap[ok], 2)))
    assert err[False] < err[True]
    assert rough[False] < 0.8 * rough[True]
    assert any(r["pose"] != q["pose"] for r, q in zip(off, live, strict=True))  # pose too


def test_offline_track_averages_the_two_readers_trackers(enrolled):
    """``articast track --speaker`` (offline, by default) also tracks the clip with the
    finding landmarks read on every frame through the speaker's model
    (core/faces/offline.py, ``second_reader``), smooths it alike, and writes the mean of the
    two articulations, its opening then moved half way to the two readers' own lip gap
    (``with_reader_gap``); ``--single-reader`` writes the first tracker's alone, with its
    reader's gap. The verdicts and head pose are the first tracker's either way, and the
    lips still follow the truth."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.offline import (
        SECOND_READER,
        OfflineSmoother,
        averaged,
        reader_ratios,
        second_reader,
        with_reader_gap,
    )
    from articast.core.faces.scheme import mediapipe_scheme

    got = {}
    for mode in ("both", "single"):
        out = enrolled / f"track-{mode}.jsonl"
        assert main(["track", str(enrolled / "test" / "video.mp4"), "--speaker",
                     str(enrolled / "speaker"), "-o", str(out), "--quiet",
                     *(["--single-reader"] if mode == "single" else [])]) == 0
        got[mode] = _track_lines(out)
    sp, frames, ap_true = _test_clip(enrolled)
    second = second_reader(sp)
    assert second is not None
    runs = {}
    # one reader: the One Euro filter forward and back; two: not (ONE_EURO_READERS)
    for key, speaker, policy, readers in (("single", sp, None, 1), ("first", sp, None, 2),
                                          ("second", second, SECOND_READER, 2)):
        live = LiveTracker(speaker, FaceFinder.load(), mediapipe_scheme(sp.rig), policy)
        smoother = OfflineSmoother.for_live(live, readers)
        results = [live.track(f, got["single"][i]["t"]) for i, f in enumerate(frames)]
        for r in results:
            smoother.add(r)
        runs[key] = (smoother.finish(), reader_ratios(results))
    (alone, r1), (first, _), (other, r2) = runs["single"], runs["first"], runs["second"]
    m, cam = sp.model, sp.camera
    want = {"single": with_reader_gap(alone, [r1], m, cam),
            "both": with_reader_gap(averaged(first, other), [r1, r2], m, cam)}
    names = sp.model.param_names
    both, single = got["both"], got["single"]
    assert [r["quality"]["ok"] for r in both] == [r["quality"]["ok"] for r in single]
    assert all(r["pose"] == q["pose"] for r, q in zip(both, single, strict=True))
    mixed = 0
    for mode in ("single", "both"):
        for line, w in zip(got[mode], want[mode], strict=True):
            if w is not None and line["quality"]["ok"]:
                a = np.array([line["alpha"][n] for n in names])
                assert np.allclose(a, w.alpha, atol=1e-6)
    for r, q in zip(both, single, strict=True):
        a, b = (np.array([x["alpha"][n] for n in names]) for x in (r, q))
        mixed += not np.allclose(a, b, atol=1e-3)
    assert mixed >= 0.9 * len(both)
    ok = np.array([r["quality"]["ok"] for r in both])
    ap = np.array([r["lips"]["aperture_mm"] for r in both])
    assert ok.mean() >= 0.95 and np.corrcoef(ap[ok], ap_true[ok])[0, 1] > 0.95


def test_the_readers_crop_is_the_policys_wherever_the_reader_reads(enrolled, monkeypatch):
    """``FusionPolicy.reader_keep_roi`` crops every reading of the live reader: the live
    tracker's own reader, the enrolment's readings of its frames (which the speaker records)
    and ``articast track``'s second tracker's reader (the finder's sessions, shared, cropping
    as ``SECOND_READER`` says: what a live tracker built with that policy reads)."""
    import argparse

    import articast.core.faces.offline as offline
    from articast.core.faces.finder import FaceFinder, read_every_frame
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker, reader_finder
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.service.commands.enroll import find_faces
    from articast.service.commands.track import _second_tracker

    default = FusionPolicy().reader_keep_roi
    sp = Speaker.load(enrolled / "speaker")
    assert sp.report["reader"]["keep_roi"] == default
    finder = FaceFinder.load()
    scheme = mediapipe_scheme(sp.rig)
    for crop in (0.0, 0.05):
        live = LiveTracker(sp, finder, scheme, LivePolicy(fusion=FusionPolicy(
            reader_keep_roi=crop)))
        assert live.reader.policy.keep_roi == crop
    # the enrolment reads its frames as the default live reader does (the rendered face is
    # still enough for the kept crop to be kept: another crop reads other landmarks)
    images, _, _, _, _, _, readings, _ = find_faces(enrolled / "test" / "video.mp4", 600,
                                                    quiet=True, read=True)
    faces = []
    for img in images:  # the enrolment's finding landmarks, as find_faces tracks them
        face = finder.track(img, faces[-1]) if faces and faces[-1] is not None else None
        faces.append(face or finder.find(img))
    assert np.array_equal(readings, read_every_frame(reader_finder(), images, faces),
                          equal_nan=True)
    other = read_every_frame(reader_finder(FusionPolicy(reader_keep_roi=0.0)), images, faces)
    assert not np.allclose(readings, other, equal_nan=True)
    # offline: the second tracker's reader crops as SECOND_READER's policy, whatever it is
    first = LiveTracker(sp, finder, scheme)
    args = argparse.Namespace(rig=None, optimiser="gauss-newton", quiet=True)
    for crop in (default, 0.0):
        policy = replace(offline.SECOND_READER, fusion=replace(
            offline.SECOND_READER.fusion, reader_keep_roi=crop))
        monkeypatch.setattr(offline, "SECOND_READER", policy)
        second = _second_tracker(args, first)
        assert second.reader.policy.keep_roi == crop
        assert second.reader.landmarks_session is finder.landmarks_session  # not loaded again
        own = LiveTracker(second.speaker, FaceFinder.load(), scheme, policy)
        assert own.reader.policy == second.reader.policy


def test_a_readers_crop_outside_its_range_is_refused_in_one_line():
    from articast.core.faces.live import FusionPolicy

    for bad in (-0.01, 1.0):
        with pytest.raises(ValueError, match="reader_keep_roi must be in"):
            FusionPolicy(reader_keep_roi=bad)


def test_a_speakers_track_file_is_served_as_a_recording(enrolled):
    """``articast serve --source rec=replay-record:track.jsonl --speaker DIR`` (the processor
    left to choose) streams the file's states with the speaker's model, as a ``--record``
    recording: a track file has no images to track (it failed with "this source has no
    images to track" before)."""
    import asyncio

    import websockets

    from articast.service.app import ServiceConfig
    from articast.service.security import AccessPolicy
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from tests.service_helpers import TIMEOUT, ServerThread

    track = enrolled / "track-served.jsonl"
    assert main(["track", str(enrolled / "test" / "video.mp4"), "--speaker",
                 str(enrolled / "speaker"), "-o", str(track), "--quiet"]) == 0
    lines = _track_lines(track)
    names = Speaker.load(enrolled / "speaker").model.param_names
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(
        SessionSpec("rec", f"replay-record:{track}?loop=yes", speaker=str(enrolled / "speaker")),),
        access=AccessPolicy(token="replay-token-0123456789"))

    async def frames(url):
        async with websockets.connect(url, open_timeout=TIMEOUT, max_size=2**24,
                                      close_timeout=1) as ws:
            await ws.send(json.dumps({"type": "subscribe", "session": "rec",
                                      "streams": ["articulatory"]}))
            got, hello = [], None
            while len(got) < 5:
                m = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))
                hello = m if m["type"] == "hello" else hello
                if m["type"] == "frame":
                    got.append(m)
            return hello, got

    with ServerThread(config) as srv:
        hello, got = asyncio.run(frames(srv.url))
    assert hello is not None and hello["param_names"] == list(names)
    for f in got:
        want = lines[f["frame"] % len(lines)]["alpha"]
        assert f["values"]["articulatory"] == pytest.approx(want, abs=1e-6)


@pytest.mark.parametrize("kind", ["noise", "blank"])
def test_noise_and_blank_videos_are_never_ok(enrolled, tmp_path, kind, capsys):
    import re

    rng = np.random.default_rng(0)
    frames = [(rng.integers(0, 256, (480, 640, 3)) if kind == "noise"
               else np.full((480, 640, 3), 127)).astype(np.uint8) for _ in range(20)]
    video = tmp_path / f"{kind}.mp4"
    _write_video(video, frames)
    out = tmp_path / "track.jsonl"
    # nothing tracked is an error for the command (exit 2, one line that says why), and -o
    # is not written (it is written only when tracking succeeds: issue 39)
    assert main(["track", str(video), "--speaker", str(enrolled / "speaker"), "-o", str(out),
                 "--quiet"]) == 2
    assert not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none of its 20 frames could be tracked" in err[0]
    counts = dict((k, int(v)) for k, v in re.findall(r"(no_face|blank|diverged|occluded|"
                                                      r"left_image|not_started) (\d+)", err[0]))
    assert sum(counts.values()) == 20 and set(counts) <= {"no_face", "blank", "diverged"}
    if kind == "blank":
        assert counts == {"blank": 20}


def test_enroll_on_a_video_without_a_face_is_one_clear_error(tmp_path, capsys):
    rng = np.random.default_rng(1)
    video = tmp_path / "noise.mp4"
    _write_video(video, [rng.integers(0, 256, (240, 320, 3), dtype=np.uint8) for _ in range(10)])
    assert main(["enroll", str(video), "-o", str(tmp_path / "sp"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a face was found in 0 of 10" in err[0]
    assert not (tmp_path / "sp").exists()


def test_a_broken_speaker_folder_is_one_clear_error(enrolled, tmp_path, capsys):
    with pytest.raises(ModelFileError, match="missing appearance.npz"):
        d = tmp_path / "partial"
        d.mkdir()
        (d / "speaker.json").write_text("{}")
        (d / "model.npz").write_bytes(b"")
        (d / "camera.json").write_text("{}")
        Speaker.load(d)
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in ("model.npz", "appearance.npz", "camera.json"):
        (bad / f).write_bytes((enrolled / "speaker" / f).read_bytes())
    (bad / "speaker.json").write_text('{"kind": "articast-speaker", "version": 9}')
    out = tmp_path / "t.jsonl"
    assert main(["track", str(enrolled / "test" / "video.mp4"), "--speaker", str(bad),
                 "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "version 9 is not supported" in err[0]


def test_serve_streams_an_enrolled_speaker_with_lips_and_honest_ok(enrolled, tmp_path):
    """serve --speaker: the live processor starts from landmarks; every frame carries lips;
    the same frames as the offline track (fast pace, nothing dropped)."""
    import asyncio

    from articast.service.app import ServiceConfig
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from tests.service_helpers import ServerThread, collect

    video = enrolled / "test" / "video.mp4"
    spec = SessionSpec("me", f"file:{video}?pace=fast", wait_for_subscriber=True,
                       speaker=str(enrolled / "speaker"), preview=True)
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,))
    with ServerThread(config) as srv:
        hello, frames = asyncio.run(collect(srv.url, "me",
                                            ["articulatory", "pose", "fap", "arkit"]))
        with srv.client() as c:
            jpeg = c.get("/api/sessions/me/preview.jpg").content
    # the preview draws the lip contours over the translucent mesh (an opaque wireframe hid
    # them): the inner contour's magenta is there, and not without the contours
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker, live_policy
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.speaker import Speaker
    from articast.service.overlay import lip_contours
    from articast.service.preview import render_preview
    from articast.service.video import iter_video

    def magenta(data):
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).astype(int)
        b, g, r = img[..., 0], img[..., 1], img[..., 2]
        return int(((b - g > 30) & (r - g > 30)).sum())

    assert magenta(jpeg) >= 20
    sp = Speaker.load(enrolled / "speaker")
    image = next(img for i, _, img in iter_video(video) if i == 30)
    res = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig),
                      tracking=live_policy(sp.rig)).track(image, 0.0)
    drawn = render_preview(image, sp.model, sp.camera, res, contours=lip_contours(sp))
    plain = render_preview(image, sp.model, sp.camera, res)
    assert magenta(drawn) >= magenta(plain) + 20, (magenta(drawn), magenta(plain))
    assert hello["param_names"][6] == "lar1" and len(frames) == 75
    ok = np.array([f["quality"]["ok"] for f in frames])
    assert ok.mean() >= 0.95
    ap = np.array([f["lips"]["aperture_mm"] for f in frames])
    truth = _track_lines(enrolled / "test" / "truth.jsonl")
    true_model = FaceModel.load(enrolled / "test" / "model.npz")
    at = np.array([[r["alpha"][n] for n in true_model.param_names] for r in truth])
    ap_true, _ = lip_measures(true_model, at)
    assert np.corrcoef(ap[ok], ap_true[ok])[0, 1] > 0.9
    assert all(f["lips"]["width_mm"] > 20 for f in frames)
    # FAPs and blendshapes from an enrolled model (ES0/ENS0 from the stated eye distance)
    assert hello["fapu"]["ES0"] == 63.0
    jaw = np.array([f["values"]["arkit"]["jawOpen"] for f in frames])
    assert np.corrcoef(jaw[ok], ap_true[ok])[0, 1] > 0.8
    assert any(f["values"]["fap"]["values"] for f in frames)


def test_a_face_that_leaves_is_reported_within_a_few_frames_and_picked_up_again(enrolled):
    """The face finder checks on the tracker every 10 frames: a scene without the face (the
    speaker's background, textured, not blank) is no longer ok within 10 frames, and tracking
    is ok again soon after the face returns."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig))
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    h, w = frames[0].shape[:2]
    # the background without the face: the frame's left margin, stretched over the frame
    empty = cv2.resize(frames[0][:, : w // 6], (w, h), interpolation=cv2.INTER_LINEAR)
    seq = frames[:30] + [empty] * 20 + frames[30:60]
    ok = np.array([live.track(img, i / 25).ok for i, img in enumerate(seq)])
    assert ok[:30].all()
    gone = np.flatnonzero(~ok[30:50])
    assert gone.size and gone[0] <= 10 and not ok[40:50].any()
    back = np.flatnonzero(ok[50:])
    assert back.size and back[0] <= 10 and ok[50 + back[0]:].mean() > 0.9


@pytest.fixture(scope="module")
def head_rig(tmp_path_factory):
    """A rendered head-rig clip (seed 8, sentence 50) enrolled with ``--rig head`` (its default,
    pixels refined by the flow), then another sentence (51) tracked: (speaker, track lines, ok
    mask, truth lines, the truth's model), shared by the two head-rig tests (one enrolment:
    ~30 s of CI)."""
    tmp_path = tmp_path_factory.mktemp("head_rig")
    seed = 8
    assert main(["synth", "sequence", "-o", str(tmp_path / "clip"), "--seed", str(seed),
                 "--sentence", "50", "--rig", "head", "--frames", "200", "--fps", "10"]) == 0
    assert main(["enroll", str(tmp_path / "clip" / "video.mp4"), "-o", str(tmp_path / "sp"),
                 "--rig", "head", "--quiet", "--json"]) == 0
    sp = Speaker.load(tmp_path / "sp")
    assert main(["synth", "sequence", "-o", str(tmp_path / "test"), "--seed", str(seed),
                 "--sentence", "51", "--rig", "head", "--frames", "60", "--fps", "25"]) == 0
    out = tmp_path / "t.jsonl"
    assert main(["track", str(tmp_path / "test" / "video.mp4"), "--speaker",
                 str(tmp_path / "sp"), "-o", str(out), "--quiet"]) == 0
    lines = _track_lines(out)
    ok = np.array([r["quality"]["ok"] for r in lines])
    return (sp, lines, ok, _track_lines(tmp_path / "test" / "truth.jsonl"),
            FaceModel.load(tmp_path / "test" / "model.npz"))


def test_a_head_mounted_camera_enrols_and_tracks_the_lower_face(head_rig):
    """The head rig sees the face from the nose down (no eyes): scale from the assumed mouth
    width, one head pose for the clip; the lips are still followed."""
    sp, lines, ok, truth, true_model = head_rig
    assert sp.rig == "head" and "mouth width 50 mm" in sp.report["scale"]
    assert ok.mean() >= 0.95
    # no eyes in view: absent with their reason, never open eyes at 0
    assert sp.upper is None
    assert all(not r["eyes"]["ok"] and r["eyes"]["reason"].startswith("not_seen")
               and r["eyes"]["closure_left"] is None and not r["brows"]["ok"] for r in lines)
    at = np.array([[r["alpha"][n] for n in true_model.param_names] for r in truth])
    ap_true, _ = lip_measures(true_model, at)
    ap = np.array([r["lips"]["aperture_mm"] for r in lines])
    assert np.corrcoef(ap[ok], ap_true[ok])[0, 1] > 0.85


def test_a_head_mounted_camera_enrols_from_pixels_refined_by_the_flow(head_rig):
    """Seen from 22 cm below the mouth, the landmarker's pixels under-read the lips' own small
    motions; a head-mounted enrolment refines them by optical flow by default, and the tracked
    lips2 and lips3 follow the truth (this clip: 0.96 and 0.96 with the flow, 0.82 and 0.95
    with the landmarks' pixels, ``--no-flow``)."""
    sp, lines, ok, truth, _ = head_rig
    assert sp.report["pixels"] == "landmarks refined by optical flow"
    assert ok.mean() >= 0.95
    names = ("jaw1", "lips1", "lips2", "lips3")
    at = np.array([[r["alpha"][n] for n in names] for r in truth])[ok]
    a = np.array([[r["alpha"][n] for n in names] for r in lines])[ok]
    r = [float(np.corrcoef(a[:, k], at[:, k])[0, 1]) for k in range(4)]
    assert min(r) > 0.9, dict(zip(names, r, strict=True))


def test_enrolled_geometry_follows_the_pixels_not_the_landmarkers_depth(enrolled):
    """The landmarker's depth is a guess (a camera sees pixels): enrolment takes each frame's
    depth from the rigid head posed on the stable points' pixels. Garbage added to the
    landmarks' depth must leave the enrolled articulation unchanged (with the landmarks' own
    depth it moved lips2 to r 0.85), and on the rendered speaker the enrolment's parameters
    follow the true ones better than with the landmarks' depth (jaw1 0.92, lips1 0.94 then)."""
    from articast.core.faces.enrol import EnrolOptions, enrol_geometry
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.model.camera import Camera
    from articast.service.video import iter_video

    frames = [img for _, _, img in iter_video(enrolled / "clip" / "video.mp4")]
    finder = FaceFinder.load()
    faces = [finder.find(f) for f in frames]
    marks = np.array([f.landmarks if f is not None else np.full((478, 3), np.nan)
                      for f in faces])
    found = np.array([f is not None for f in faces])
    assert found.mean() > 0.95
    camera = Camera.default(frames[0].shape[1], frames[0].shape[0], 60.0)
    scheme = mediapipe_scheme("desk")
    assert EnrolOptions().depth == "rigid"  # the product's default
    geo = enrol_geometry(marks, found, scheme, camera)
    noisy = marks.copy()
    noisy[..., 2] += np.random.default_rng(0).normal(0.0, 3.0, noisy.shape[:2])
    geo_noisy = enrol_geometry(noisy, found, scheme, camera)
    assert np.array_equal(geo.frames, geo_noisy.frames)
    for k in range(5):  # jaw1 .. lips4
        assert np.corrcoef(geo.alpha[:, k], geo_noisy.alpha[:, k])[0, 1] > 0.99
    truth = _track_lines(enrolled / "clip" / "truth.jsonl")
    true_model = FaceModel.load(enrolled / "clip" / "model.npz")
    at = np.array([[r["alpha"][n] for n in true_model.param_names] for r in truth])[geo.frames]
    r = [np.corrcoef(geo.alpha[:, k], at[:, k])[0, 1] for k in range(4)]
    assert r[0] > 0.93 and r[1] > 0.95 and min(r) > 0.8, r
    # the option that keeps the upper lip off jaw1 (off by default) reaches the guided PCA
    upper = geo.model.group("upper_lip")
    assert np.abs(geo.model.basis[0, upper]).max() > 0
    kept = enrol_geometry(marks, found, scheme, camera, EnrolOptions(jaw_moves_upper_lip=False))
    assert np.all(kept.model.basis[0, upper] == 0) and np.abs(kept.model.basis[3, upper]).max() > 0


def test_optical_flow_refines_landmark_pixels_that_under_read_the_motion():
    """A textured face moves; the 'landmarks' read 70 % of its motion plus noise (the kind of
    slope a landmark model's prior gives). The refined pixels follow the image."""
    import cv2

    from articast.core.faces.flow import refine_pixels

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (240, 240)).astype(np.float32), (0, 0), 2.0)
    # three points inside, two marking the face's extent (its size bounds the flow's deviation)
    pts = np.array([[100.0, 100.0], [140.0, 110.0], [120.0, 140.0], [40.0, 40.0], [200, 200]])
    n_frames = 60
    t = np.arange(n_frames)  # a syllable-like motion: a period of ~12 frames (1 s at 12 fps)
    shift = np.stack([8 * np.sin(t / 2), 5 * np.sin(t / 2.6)], 1)
    frames = [cv2.warpAffine(texture, np.float32([[1, 0, dx], [0, 1, dy]]), (240, 240))
              .clip(0, 255).astype(np.uint8) for dx, dy in shift]
    true = pts[None, :3] + shift[:, None]
    marks = np.zeros((n_frames, 7, 3))
    marks[:, 1:6, :2] = pts[None] + 0.7 * shift[:, None] + rng.normal(0, 0.5, (n_frames, 5, 2))
    found = np.ones(n_frames, bool)
    found[30] = False  # a frame without a face: the flow restarts from the landmarks after it
    out = refine_pixels(frames, marks, found, np.arange(1, 6))
    assert np.array_equal(out[:, [0, 6]], marks[:, [0, 6]])  # other landmarks untouched
    assert np.array_equal(out[..., 2], marks[..., 2])  # depth untouched
    assert np.array_equal(out[30], marks[30])

    def error(p):
        return float(np.sqrt(((p[:, 1:4, :2] - true) ** 2).sum(-1).mean()))

    assert error(marks) > 1.5
    assert error(out) < 0.5 * error(marks)
    slope = np.polyfit(shift[:, 0], out[:, 1:4, 0].mean(1) - pts[:3, 0].mean(), 1)[0]
    assert slope > 0.9
    # a flow that lands far from its landmark (here: the image does not move at all while
    # the landmarks jump by a fifth of the face) is not trusted
    still = refine_pixels([frames[0]] * 3, np.stack([marks[0], marks[0] + [[32, 0, 0]],
                                                     marks[0] + [[32, 0, 0]]]),
                          np.ones(3, bool), np.arange(1, 6))
    assert np.allclose(still[1:, 1:6, :2], marks[0, 1:6, :2] + [32, 0])


def test_a_desk_enrolment_learns_how_the_live_reader_sees_the_face(enrolled):
    """Fused live tracking reads FaceMesh v1 every frame: the enrolment learns, from the same
    clip, where that network puts this face's points (a linear observation model), how far
    its readings stray (each point's own s.d. and the errors they share) and the motion
    model's process noise (its defaults here: the 6 fps clip is too sparse to learn it)."""
    from articast.core.tracking.kalman import MotionNoise

    sp = Speaker.load(enrolled / "speaker")
    assert (enrolled / "speaker" / "points_v1.npz").is_file()
    pm = sp.points
    assert pm is not None and pm.network == "v1"
    assert pm.mean.shape == sp.model.mean.shape and len(pm.modes) > 0
    assert 0.1 < float(np.median(pm.sigma_mm)) < 3.0
    assert sp.motion_noise is not None
    assert np.allclose(sp.motion_noise.q, MotionNoise.default(7).q)
    assert sp.report["reader"]["network"] == "v1"
    # and the articulation read straight off a reading, with the error it expects
    reg = pm.regression
    assert reg is not None and reg.weights.shape == (2 * len(pm.mean), sp.model.n_params)
    assert np.allclose(reg.information, reg.information.T)
    assert np.linalg.eigvalsh(reg.information).min() >= -1e-9
    # and how the finding landmarks (read on every enrolment frame) see it: offline track's
    # second reader, a model of its own (the enrolled states are theirs: it strays less)
    assert (enrolled / "speaker" / "points_v2.npz").is_file()
    fp = sp.finder_points
    assert fp is not None and fp.network == "v2" and fp.mean.shape == pm.mean.shape
    assert not np.allclose(fp.mean, pm.mean)
    assert fp.offset_p99 < pm.offset_p99
    assert sp.report["second_reader"]["network"] == "v2"


def test_a_speaker_whose_second_readers_model_is_of_another_network_is_refused(enrolled,
                                                                                tmp_path):
    import shutil

    d = tmp_path / "speaker"
    shutil.copytree(enrolled / "speaker", d)
    shutil.copy(d / "points_v1.npz", d / "points_v2.npz")
    with pytest.raises(ModelFileError, match="points_v2.npz: an observation model of the 'v1'"):
        Speaker.load(d)


def _test_clip(enrolled):
    """The enrolled speaker, its test clip's frames and their true lip aperture (mm)."""
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    truth = _track_lines(enrolled / "test" / "truth.jsonl")
    true_model = FaceModel.load(enrolled / "test" / "model.npz")
    at = np.array([[r["alpha"][n] for n in true_model.param_names] for r in truth])
    ap_true, _ = lip_measures(true_model, at)
    return sp, frames, ap_true


def _fused(sp, fusion=None):
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    policy = None if fusion is None else LivePolicy(fusion=fusion)
    return LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig), policy)


def _cadenced(**changes):
    """The fused policy reading every third frame, as the default did before issue 38 (the
    reader's cadence, the frames between, the eyes' and the lag's own readings: the
    mechanisms these tests check, still there for that policy)."""
    from articast.core.faces.live import FusionPolicy

    return FusionPolicy(**{"read_every": 3, "cadence": 0.1, "reader_gap": None,
                           "eyes_every": 1, **changes})


def test_the_articulation_read_off_a_reading_pulls_the_fit_to_it(enrolled):
    """On a frame with a reading, the enrolment's regression reads the articulation off the
    reader's points (``FusionPolicy.regression``), a measurement beside the landmark term:
    the fused fit lands nearer what it read than without it, the motion model is surer after
    it, and the lips still follow the truth."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    sp, frames, ap_true = _test_clip(enrolled)
    pm = sp.points
    assert pm is not None and pm.regression is not None
    reg = pm.regression
    runs = {}
    for on in (True, False):
        live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig),
                           LivePolicy(fusion=FusionPolicy(regression=on)))
        near, sure, ap = [], [], []
        for i, img in enumerate(frames[:40]):
            r = live.track(img, i / 25)
            ap.append(r.lips["aperture_mm"] if r.ok else np.nan)
            if r.ok and live._since_read == 0 and i > 0:  # a frame with a reading
                seen = live._reading.landmarks[pm.landmarks, :2]
                read = reg.alpha(reg.features(pm.mean, sp.camera, seen, r.pose.matrix,
                                              r.pose.translation))
                near.append(float(np.linalg.norm(np.asarray(r.extra["alpha_raw"]) - read)))
                # (lar1, which no reading sees, grows without bound in both)
                sure.append(float(np.trace(live.kalman.p[:6, :6])))
        runs[on] = (np.array(near), np.array(sure), np.array(ap))
    (near_on, sure_on, ap_on), (near_off, sure_off, _) = runs[True], runs[False]
    assert len(near_on) >= 8 and len(near_on) == len(near_off)
    assert np.mean(near_on < near_off) >= 0.8
    assert np.median(sure_on) < np.median(sure_off)
    ok = np.isfinite(ap_on)
    assert ok.mean() > 0.95 and np.corrcoef(ap_on[ok], ap_true[:40][ok])[0, 1] > 0.9


def test_fused_tracking_reads_every_frame_and_recovers_a_lost_state(enrolled):
    """A state knocked off the face (as a missed fast turn would leave it): the reading is
    far from the motion model's prediction, the motion model restarts there and every
    landmark pulls, and the lips are followed again within two frames."""
    sp, frames, ap_true = _test_clip(enrolled)
    live = _fused(sp, _cadenced())
    assert live.fusion is not None
    res = [live.track(img, i / 25) for i, img in enumerate(frames[:30])]
    # the reader, every third frame (FusionPolicy.read_every; a frame or two more for the
    # eyes, FusionPolicy.eye_reads), and the finder once
    assert 30 // 3 <= live.finder_calls <= 30 // 3 + 4
    while live._since_read < live.fusion.read_every - 1:  # the knock just before a reading
        res.append(live.track(frames[len(res)], len(res) / 25))
    knock = len(res)
    kf = live.kalman
    kf.t = kf.t + np.array([60.0, 0.0, 120.0])  # 6 cm aside, 12 cm further
    kf.alpha = kf.alpha + 3.0
    regated = live.regated
    res += [live.track(img, (knock + i) / 25) for i, img in enumerate(frames[knock:])]
    assert live.regated >= regated + 1
    assert live.rereads >= 1  # (the next frame was read too)
    ok = np.array([r.ok for r in res])
    assert ok[knock + 2:].all()
    ap = np.array([r.lips["aperture_mm"] for r in res])
    assert np.corrcoef(ap[knock + 2:], ap_true[knock + 2:])[0, 1] > 0.9


def test_a_gated_reading_restarts_the_motion_model_at_the_head_pose_it_shows(enrolled):
    """``FusionPolicy.realign``: a motion model knocked off the face just before a reading (as
    a hand-held camera's jump leaves its prediction) is gated; realigned, it restarts at the
    head's pose the reading shows and the regression is read there, so the frame's lips are
    the undisturbed run's whatever the knock; restarted at the predicted pose (realign off),
    the same frame's lips depend on how far off the prediction was."""
    from articast.core.faces.live import FusionPolicy

    sp, frames, _ = _test_clip(enrolled)
    knock = 20

    def aperture(realign, shift):
        live = _fused(sp, FusionPolicy(realign=realign))
        for i, img in enumerate(frames[:knock + 1]):
            if i == knock and shift is not None:
                live.kalman.t = live.kalman.t + np.array(shift)
            r = live.track(img, i / 25)
        assert r.ok
        return r.lips["aperture_mm"], live

    undisturbed, live = aperture(False, None)
    assert live.regated == 0
    aside = [30.0, 20.0, 0.0]  # mm
    for shift in (aside, [40.0, 0.0, 0.0]):
        ap, live = aperture(True, shift)
        assert live.regated == live.realigned == 1
        assert abs(ap - undisturbed) < 0.5, (shift, ap, undisturbed)
    off = [aperture(False, shift)[0] for shift in (aside, [40.0, 0.0, 0.0])]
    assert abs(off[1] - off[0]) > 1.5, off  # (at the predicted pose: 15.4 and 18.4 mm)


def _counting_finders():
    """The finding landmarks and the reader (sharing one detector session), each counting
    its detector's runs and its own ``find`` / ``track`` calls."""
    from articast.core.faces.finder import FaceFinder

    class Counting(FaceFinder):
        def detect(self, image_bgr):
            self.detections = getattr(self, "detections", 0) + 1
            return super().detect(image_bgr)

        def find(self, image_bgr, **kw):
            self.finds = getattr(self, "finds", 0) + 1
            return super().find(image_bgr, **kw)

        def track(self, image_bgr, previous):
            self.tracks = getattr(self, "tracks", 0) + 1
            return super().track(image_bgr, previous)

    finder = Counting.load()
    return finder, Counting.load(landmarks="v1", detector=finder.detector_session)


def test_a_start_policy_it_does_not_know_is_refused_in_one_line():
    from articast.core.faces.live import FusionPolicy

    with pytest.raises(ValueError, match="start must be 'reader' or 'finder', got 'v2'"):
        FusionPolicy(start="v2")


def _shut_eyes(image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """``image`` with both eyes (their contours in ``landmarks``, grown by 2 px) painted over
    with the skin's colour below them: the eyes shut."""
    from articast.core.faces.upper import EYE_CONTOUR, SIDES

    out = image.copy()
    for side in SIDES:
        poly = np.round(landmarks[list(EYE_CONTOUR[side]), :2]).astype(np.int32)
        mask = np.zeros(image.shape[:2], np.uint8)
        cv2.fillPoly(mask, [poly], 1)
        mask = cv2.dilate(mask, np.ones((5, 5), np.uint8))
        x, y, w, h = cv2.boundingRect(poly)
        below = image[y + 2 * h:y + 3 * h, x:x + w].reshape(-1, 3)
        out[mask > 0] = np.median(below, axis=0).astype(np.uint8)
    return out


def _on_to_a_reading(live, frames, first: int = 20) -> int:
    """Track ``frames`` from 0 on to a frame read on the cadence (at or after ``first``) whose
    next frame is not to be read for the lips; its index."""
    i = 0
    while True:
        res = live.track(frames[i], i / 25)
        if i >= first and res.upper.source == "reader" and live._since_read == 0:
            return i
        i += 1


def _inverted_eyes(image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """``image`` with both eyes' grey levels inverted inside their contours: eyes that change
    and stay open (the reader reads their lids where they were)."""
    from articast.core.faces.upper import EYE_CONTOUR, SIDES

    out = image.copy()
    for side in SIDES:
        mask = np.zeros(image.shape[:2], np.uint8)
        cv2.fillPoly(mask, [np.round(landmarks[list(EYE_CONTOUR[side]), :2]).astype(np.int32)],
                     1)
        out[mask > 0] = 255 - out[mask > 0]
    return out


def test_frames_read_for_the_eyes_do_not_follow_each_other(enrolled):
    """An eye that changes on every frame (a glint on glasses) is not read on every frame:
    after a frame read for the eyes, the next one is not (at most every other reading is one),
    though its eyes changed again."""
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    live = _fused(sp, _cadenced())
    i = _on_to_a_reading(live, frames)
    marks = np.asarray(live._fresh.landmarks)
    changed = live.track(_inverted_eyes(frames[i + 1], marks), (i + 1) / 25)
    assert changed.upper.source == "reader" and live.eye_reads == 1
    assert max(changed.upper.closure_left, changed.upper.closure_right) < 0.5  # (read open)
    back = live.track(frames[i + 2], (i + 2) / 25)  # changed again, back as they were
    assert back.upper.source == "photo" and live.eye_reads == 1


def test_an_eye_the_pixels_cannot_follow_is_read_the_frame_it_shuts(enrolled):
    """Speaker 4 enrolled with eyes that never moved: no photometric measure follows its
    lids, so between readings the closure is held and a blink of two frames could fall
    between them. Its eyes are watched instead (``FusionPolicy.eye_reads``): the frame after
    a reading, painted with the eyes shut, is read itself;
    without the policy it is not read."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    assert sp.upper is not None and max(abs(r) for r in sp.upper.photo_r) < 0.5
    assert min(sp.upper.change_limit) > 0
    assert sp.report["upper"]["watched"] == [True, True]  # (enroll reports it)
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    for eye_reads in (True, False):
        live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig),
                           LivePolicy(fusion=_cadenced(eye_reads=eye_reads)))
        assert live.upper.watched() == [0, 1]
        i = _on_to_a_reading(live, frames)
        marks = np.asarray(live._fresh.landmarks)
        before = live.eye_reads
        res = live.track(_shut_eyes(frames[i + 1], marks), (i + 1) / 25)
        assert res.ok
        if eye_reads:
            assert res.upper.source == "reader" and live.eye_reads == before + 1
        else:
            assert res.upper.source == "photo" and live.eye_reads == before == 0


def _knocked(sp, frames, fusion, knock=True):
    """A live tracker (fused by ``fusion``, counting finders) run over the first 50 frames,
    then its motion model knocked 6 cm aside, 12 cm further and 3 s.d. of articulation off
    (``knock``); returns it and its finder and reader."""
    from articast.core.faces.live import LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    finder, reader = _counting_finders()
    live = LiveTracker(sp, finder, mediapipe_scheme(sp.rig), LivePolicy(fusion=fusion),
                       reader=reader)
    for i, img in enumerate(frames[:50]):
        live.track(img, i / 25)
    if knock:
        kf = live.kalman
        kf.t = kf.t + np.array([60.0, 0.0, 120.0])
        kf.alpha = kf.alpha + 3.0
    return live, finder, reader


def test_a_diverged_fit_restarts_from_the_last_reading_without_the_detector(enrolled):
    """A fit the frame's landmarks disown (``diverged``: the state knocked off the face, the
    face still read) restarts on the next frame from the landmarks read in the crop grown from
    that reading: one reader call, no detector, no finding landmarks; with
    ``FusionPolicy(resume=False)`` the same frame runs the detector, and so does a resumed
    start whose reading finds no face (the face gone: a frame of noise). (``recover`` off:
    it starts the fit again within the frame, the next test.)"""
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    runs = {}
    noise = np.random.default_rng(0).integers(0, 256, frames[0].shape, np.uint8)
    for resume, gone in ((True, False), (False, False), (True, True)):
        # (realign off: on a read frame it restarts the knocked state at the reading's pose,
        # so nothing diverges; the frames between readings are what these tests knock)
        live, finder, reader = _knocked(sp, frames, _cadenced(resume=resume, recover=False,
                                                              realign=False))
        i = 50
        res = live.track(frames[i], i / 25)
        while not res.reason.startswith("diverged") and i < 53:
            i += 1
            res = live.track(frames[i], i / 25)
        assert res.reason.startswith("diverged"), res.reason
        before = (reader.detections, getattr(finder, "finds", 0), getattr(finder, "tracks", 0),
                  live.finder_calls, live.restarts)
        nxt = live.track(noise if gone else frames[i + 1], (i + 1) / 25)
        runs[resume, gone] = (nxt, before, (reader.detections, getattr(finder, "finds", 0),
                                            getattr(finder, "tracks", 0), live.finder_calls,
                                            live.restarts))
    nxt, before, after = runs[True, False]
    assert nxt.ok and after[4] == before[4] + 1  # restarted, and fits
    assert after[0] == before[0] and after[1:3] == before[1:3]  # no detector, no v2
    assert after[3] == before[3] + 1  # one reader call: the frame's reading
    _, before, after = runs[False, False]
    assert after[0] == before[0] + 1 and after[4] == before[4] + 1
    nxt, before, after = runs[True, True]  # the resumed reading finds nothing: the detector
    assert not nxt.ok and nxt.reason.startswith("no_face"), nxt.reason
    assert after[0] == before[0] + 1 and after[4] == before[4]  # ran, found none: no start
    assert after[3] == before[3] + 2  # the resumed reading, then the detector's search


def test_a_diverged_fit_starts_again_from_the_frames_reading_and_the_frame_is_kept(enrolled):
    """``FusionPolicy.recover``: the state knocked 6 cm off the face, the frame whose fit the
    landmarks disown is started again from its own reading (read then, in the crop grown from
    the last one, if the frame had none) and fitted again within the frame: every frame after
    the knock is ok, and from the frame started again on near what a tracker never knocked
    reads (lip aperture within 1 mm: the output filter forgets the lost fit's frames), with
    no detector run, and the frame after it is read (the motion model restarted at rest);
    without it the knocked track loses a frame as ``diverged``."""

    sp, frames, _ = _test_clip(enrolled)
    runs = {}
    for recover, knock in ((True, True), (False, True), (True, False)):
        # (reread off: the frame after a recovery is read for the recovery's sake)
        live, finder, reader = _knocked(sp, frames, _cadenced(recover=recover, reread=None,
                                                              realign=False), knock)
        detections = reader.detections
        after, calls = [], []
        for i in range(50, 56):
            before = live.finder_calls
            after.append(live.track(frames[i], i / 25))
            calls.append(live.finder_calls - before)
        runs[recover, knock] = (after, reader.detections - detections, live.recovered, calls)
    kept, detections, recovered, calls = runs[True, True]
    assert all(r.ok for r in kept), [r.reason for r in kept]
    assert recovered >= 1 and detections == 0
    first = next(n for n, r in enumerate(kept) if r.extra.get("recovered"))
    assert calls[first + 1] == 1  # the motion model restarted at rest: the next frame is read
    calm = runs[True, False][0]
    gap = [abs(a.lips["aperture_mm"] - b.lips["aperture_mm"])
           for a, b in zip(kept[first:], calm[first:])]
    assert max(gap) < 1.0, gap
    lost, _, recovered, _ = runs[False, True]
    assert recovered == 0 and any(r.reason.startswith("diverged") for r in lost)


def test_a_start_from_the_readers_landmarks_is_as_close_to_the_truth_as_the_finders(enrolled):
    """``FusionPolicy.start``: a tracker started on frames 0, 6, ..., 72 of the rendered
    speaker from the reader's own landmarks (FaceMesh v1 found as the finder finds, no
    FaceLandmarker v2 call) reads the first frame's lip aperture as well as one started from
    the finding landmarks (r with the truth across the starts), and no further from what a
    tracker running through the clip reads there."""
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    sp, frames, ap_true = _test_clip(enrolled)
    starts = np.arange(0, len(frames), 6)
    finder, reader = _counting_finders()

    def tracker(start):
        return LiveTracker(sp, finder, mediapipe_scheme(sp.rig),
                           LivePolicy(fusion=FusionPolicy(start=start)), reader=reader)

    through = tracker("finder")
    ref = np.array([through.track(img, i / 25).lips["aperture_mm"]
                    for i, img in enumerate(frames)])[starts]
    got = {}
    for start in ("finder", "reader"):
        finds = getattr(finder, "finds", 0)
        got[start] = []
        for k in starts:
            res = tracker(start).track(frames[k], k / 25)
            assert res.ok, (start, k, res.reason)
            got[start].append(res.lips["aperture_mm"])
        assert (getattr(finder, "finds", 0) - finds == 0) == (start == "reader")
    r = {k: np.corrcoef(v, ap_true[starts])[0, 1] for k, v in got.items()}
    mae = {k: np.abs(np.array(v) - ref).mean() for k, v in got.items()}
    assert r["reader"] >= r["finder"] - 0.003, r
    assert mae["reader"] <= 1.1 * mae["finder"], mae


def test_live_lips_are_measured_on_the_state_streamed_every_frame(enrolled):
    """The lips of every live frame (ok, filtered, lost on a blank frame, restarted) are those
    of the alpha it streams, measured once (the tracker inside measures none)."""
    from articast.core.outputs.lips import lips_dict
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    frames = [img for _, _, img in iter_video(enrolled / "test" / "video.mp4")]
    live = _fused(sp)
    assert not live.tracker.measure_lips
    # the reader runs no detector: it shares the finder's session instead of loading one
    assert live.reader.detector_session is live.finder.detector_session
    seq = frames[:12] + [np.zeros_like(frames[0])] + frames[12:20]
    res = [live.track(img, i / 25) for i, img in enumerate(seq)]
    assert not res[12].ok  # the blank frame is lost, then tracked again
    assert sum(r.ok for r in res[13:]) >= 6
    for r in res:
        assert r.lips is not None and r.lips == lips_dict(sp.model, r.alpha)
    # the streamed alpha is the filtered one: its lips, not the raw fit's
    raw = [r for r in res if r.ok and "alpha_raw" in r.extra]
    assert raw and any(r.lips != lips_dict(sp.model, r.extra["alpha_raw"]) for r in raw)


def test_warm_up_compiles_every_kernel_fused_live_tracking_calls(enrolled, monkeypatch):
    """kernels.warm_up() (run before a session's first frame) calls every compiled kernel a
    fused live frame calls with the same argument types: nothing is compiled while tracking
    (a new type -- a read-only or Fortran-ordered array -- would cost a first frame seconds).
    The types are recorded at the calls (the process may have compiled others before)."""
    from articast.core.tracking import kernels
    from articast.service.video import iter_video
    from tests.kernel_spies import KernelSpies

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    sp = Speaker.load(enrolled / "speaker")
    live = _fused(sp)
    assert live.fusion is not None
    spies = KernelSpies()
    for name in ("la_residuals", "cauchy", "point_residuals", "gn_terms", "lm_step",
                 "fit_information", "sample_uv", "roi_box", "state_measured", "pixels_sd3", "pixels_sd2",
                 "facing_cos", "occlusion_votes",
                 "point_offset", "cv_predict", "cv_update", "lip_gap",
                 "reading_features", "iris_chords", "iris_former_rows",
                 "iris_circle_height", "opening_centres", "dark_height", "brow_half"):
        monkeypatch.setattr(kernels, name, spies.wrap(name, getattr(kernels, name)))
    kernels.warm_up()
    warmed = spies.take()
    ok = [live.track(img, i / 25).ok for i, (_, _, img) in
          enumerate(iter_video(enrolled / "test" / "video.mp4")) if i < 12]
    seen = spies.take()
    assert all(ok) and live.finder_calls >= 4  # fitted with readings and between them
    assert {"gn_terms", "lm_step", "sample_uv", "roi_box", "cv_predict", "cv_update", "point_offset", "lip_gap",
            "reading_features"} <= set(seen)
    for name, types in seen.items():
        assert types <= warmed.get(name, set()), (name, types - warmed.get(name, set()))


def test_a_speaker_enrolled_before_the_reader_is_tracked_as_before(enrolled, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(enrolled / "speaker", old)
    (old / "points_v1.npz").unlink()
    sp = Speaker.load(old)
    live = _fused(sp)
    assert sp.points is None and live.fusion is None
    from articast.service.video import iter_video

    ok = [live.track(img, i / 25).ok for i, (_, _, img) in
          enumerate(iter_video(enrolled / "test" / "video.mp4")) if i < 20]
    assert all(ok) and live.finder_calls <= 3


def test_fused_frames_are_judged_by_the_landmarks_not_the_appearance_residual(enrolled):
    """With the reader in the fit, ``ok`` is the landmarks' verdict: an appearance residual
    far beyond the enrolment's (an opening the enrolment never showed, other light) does not
    make a frame the landmarks confirm ``diverged``; a fit the landmarks disown is, with the
    distance in its reason. A speaker whose observation model predates that statistic is
    judged by the residual as before."""
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    assert sp.points is not None and 0.0 < sp.points.offset_p99 < 0.2
    frames = [img for i, (_, _, img) in enumerate(iter_video(enrolled / "test" / "video.mp4"))
              if i < 16]

    def run(speaker):
        live = _fused(speaker)
        return [live.track(img, i / 25) for i, img in enumerate(frames)]

    strict = replace(sp, residual=replace(sp.residual, p99=sp.residual.p99 / 1000))
    assert all(r.ok for r in run(strict))
    assert all(r.extra["landmark_offset"] <= 3 * sp.points.offset_p99
               for r in run(strict) if "landmark_offset" in r.extra)
    before = replace(strict, points=replace(sp.points, offset_p99=float("nan")))
    assert not any(r.ok for r in run(before))
    disowned = replace(sp, points=replace(sp.points, offset_p99=1e-6))
    res = run(disowned)
    assert not any(r.ok for r in res)
    assert any(r.reason.startswith("diverged: the landmarks are") for r in res)


def test_an_opening_beyond_the_enrolment_is_unfamiliar_to_the_appearance(enrolled):
    """Where the lips open or stretch beyond the enrolment's range the appearance is not
    trained, and the landmarks alone may confirm a fit it calls occluded."""
    sp = Speaker.load(enrolled / "speaker")
    cov = sp.report["coverage"]
    live = _fused(sp)
    inside = np.zeros(sp.model.n_params)
    ap, wd = (float(x[0]) for x in lip_measures(sp.model, inside[None]))
    assert cov["aperture_mm"][0] <= ap <= cov["aperture_mm"][1]
    assert not live._unfamiliar(inside)
    narrow = replace(sp, report={**sp.report, "coverage": {
        "aperture_mm": [ap + 1.0, ap + 2.0], "width_mm": cov["width_mm"]}})
    assert _fused(narrow)._unfamiliar(inside)


def test_a_head_turned_beyond_the_enrolment_is_unfamiliar_a_hand_within_it_stays_occluded(
        enrolled):
    """Issue 38: the enrolment keeps the head rotations its appearance was trained on
    (``coverage["rotation_deg"]``, around ``rotation_ref``). A head turned beyond them is as
    unfamiliar to the appearance as an opening beyond the enrolment's (wojtek bowed 8-13 deg
    further than his: 11 frames "occluded" with nothing in front of the mouth), and the
    landmarks may confirm a fit it calls occluded there. Within them a hand over the chin
    stays ``occluded`` on frames the reader reads, though it reads a face under the hand."""
    from articast.core.model.camera import Pose, axis_angle, rotation_matrix

    sp, frames, _ = _test_clip(enrolled)
    cov = sp.report["coverage"]
    turns = np.asarray(cov["rotation_deg"])
    assert turns.shape == (3, 2) and np.all(turns[:, 0] <= turns[:, 1])
    live = _fused(sp)
    neutral = np.zeros(sp.model.n_params)
    ref = rotation_matrix(np.asarray(cov["rotation_ref"]))
    at_ref = Pose(axis_angle(ref), np.array([0.0, 0.0, 500.0]))
    assert not live._unfamiliar(neutral) and not live._unfamiliar(neutral, at_ref)
    a = np.radians(turns[0, 1] + 5.0)  # bowed 5 deg further than any training frame
    bow = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    assert live._unfamiliar(neutral, Pose(axis_angle(bow @ ref), at_ref.translation))

    def hand(speaker):
        live = _fused(speaker)
        i = _on_to_a_reading(live, frames)
        marks = np.asarray(live._fresh.landmarks)
        return [live.track(_hand_over_the_chin(frames[i + k], marks), (i + k) / 25).reason
                .split(":")[0] for k in (1, 2, 3, 4)]

    # (within the enrolment's lips too: the fit under the painted hand stretches the lips to
    # the edge of the enrolment's 2nd-98th percentile width, 54.1-55.5 mm against 54.6 on
    # session 10's machine, where a last digit decides; the rule for lips beyond the range
    # is test_an_opening_beyond_the_enrolment_is_unfamiliar_to_the_appearance's)
    within = replace(sp, report={**sp.report, "coverage": {
        **cov, "aperture_mm": [0.0, 100.0], "width_mm": [0.0, 100.0]}})
    assert hand(within)[1:] == ["occluded"] * 3
    # the same frames, the head beyond every rotation the appearance was trained on: the
    # landmarks, which read the face where the fit is, overrule the appearance
    beyond = replace(sp, report={**sp.report, "coverage": {
        **cov, "rotation_deg": (turns + 360.0).tolist()}})
    assert "occluded" not in hand(beyond)


def test_an_appearance_unlike_the_enrolment_weighs_less_in_the_fit(enrolled):
    """``FusionPolicy.adapt``: the appearance term's weight follows its residual level
    relative to the enrolment's, so a face the appearance no longer predicts (here: the same
    frames against an enrolment level made 50x smaller) leans on the landmarks and the motion
    model, and is still tracked; a face like the enrolment's keeps the full weight."""
    from articast.service.video import iter_video

    sp = Speaker.load(enrolled / "speaker")
    frames = [img for i, (_, _, img) in enumerate(iter_video(enrolled / "test" / "video.mp4"))
              if i < 20]
    truth = _track_lines(enrolled / "test" / "truth.jsonl")[:20]
    true_model = FaceModel.load(enrolled / "test" / "model.npz")
    ap_true, _ = lip_measures(true_model, np.array(
        [[r["alpha"][n] for n in true_model.param_names] for r in truth]))
    weights = {}
    for name, speaker in (("own", sp), ("unlike", replace(sp, residual=replace(
            sp.residual, median=sp.residual.median / 50)))):
        live = _fused(speaker)
        res = [live.track(img, i / 25) for i, img in enumerate(frames)]
        assert all(r.ok for r in res)
        weights[name] = np.array([r.extra["appearance_weight"] for r in res])
        ap = np.array([r.lips["aperture_mm"] for r in res])
        assert np.corrcoef(ap, ap_true)[0, 1] > 0.9
    assert weights["own"][-5:].min() > 0.3
    assert weights["unlike"][-5:].max() < 0.1


def _hand_over_the_chin(image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """``image`` with the lower 30 % of the face (the chin, the lower lip), between 20 % and
    80 % of its width, painted the cheeks' colour: a hand from below."""
    x0, y0 = landmarks[:, :2].min(0)
    x1, y1 = landmarks[:, :2].max(0)
    w, h = x1 - x0, y1 - y0
    cheek = image[int(y0 + 0.5 * h):int(y0 + 0.6 * h), int(x0):int(x0 + 0.2 * w)]
    out = image.copy()
    out[int(y1 - 0.3 * h):int(y1) + 30, int(x0 + 0.2 * w):int(x1 - 0.2 * w)] = np.median(
        cheek.reshape(-1, 3), axis=0).astype(np.uint8)
    return out


def test_a_hand_between_readings_is_read_and_stays_occluded(enrolled):
    """A hand over the chin between two readings: the appearance suspects it, the frame is
    read (``FusionPolicy.lag_check``), the reader reads a face under the hand where the fit
    is, and the verdict stands: the same frames are ``occluded`` as without the check."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    sp, frames, _ = _test_clip(enrolled)
    got = {}
    for check in (True, False):
        live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig),
                           LivePolicy(fusion=_cadenced(lag_check=check)))
        i = _on_to_a_reading(live, frames)
        marks = np.asarray(live._fresh.landmarks)
        res = [live.track(_hand_over_the_chin(frames[i + k], marks), (i + k) / 25)
               for k in (1, 2, 3, 4)]
        got[check] = ([r.reason.split(":")[0] for r in res], live.lag_reads)
    reasons, reads = got[True]
    assert reasons[1:] == ["occluded"] * 3 and reads >= 1
    assert got[False] == (reasons, 0)


def test_a_reading_far_from_a_fit_between_readings_is_the_fits_lag(enrolled):
    """``LiveTracker._fit_lags``, the check of an appearance suspicion between readings, on
    a real reading of the frame: a fit where the reader reads the face is not lagging (the
    suspicion stands); one 4 cm aside is (not ``occluded``, and the next frame is read);
    inside an occlusion nothing is read."""
    from articast.core.model.camera import Pose

    sp, frames, _ = _test_clip(enrolled)
    live = _fused(sp, _cadenced())
    fu = live.fusion
    assert fu is not None and fu.lag_check
    i = _on_to_a_reading(live, frames)
    alpha, pose = live.tracker.state
    since = live._since_read
    assert not live._fit_lags(frames[i + 1], alpha, pose, fu)
    assert live.lag_reads == 1 and live._since_read == since
    aside = Pose(pose.rotation, pose.translation + np.array([40.0, 0.0, 0.0]))
    assert live._fit_lags(frames[i + 1], alpha, aside, fu)
    assert live.lag_reads == 2 and live._since_read == fu.read_every - 1
    marks = np.asarray(live._fresh.landmarks)
    for k in (1, 2, 3):
        live.track(_hand_over_the_chin(frames[i + k], marks), (i + k) / 25)
    assert live.tracker.occluding
    reads = live.lag_reads
    assert not live._fit_lags(frames[i + 3], alpha, aside, fu) and live.lag_reads == reads


def test_a_speaker_enrolled_for_the_finding_landmarks_is_read_by_them_on_every_frame(enrolled):
    """The benchmark's ``reader_v2`` ablation (benchmarks/peers.py): the observation model is
    learned from the finding landmarks' own readings (FaceLandmarker v2, already read on
    every enrolment frame), and the live tracker reads v2 on every frame through it. The
    speaker's model is refused by a tracker that reads another network, and the lips follow
    the rendered truth."""
    import sys
    from pathlib import Path

    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.service.video import iter_video

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from real_clips import enrol_speaker

    sp, frames, ap_true = _test_clip(enrolled)
    images = [img for _, _, img in iter_video(enrolled / "clip" / "video.mp4")]
    sp2 = enrol_speaker(images, 6.0, camera=sp.camera, max_frames=None, reader="v2")
    finder = FaceFinder.load()
    scheme = mediapipe_scheme("desk")
    assert sp2.points is not None and sp2.points.network == "v2"
    with pytest.raises(ValueError, match="'v2' landmarks, not 'v1'"):
        LiveTracker(sp2, finder, scheme)  # the product's default reads v1
    policy = LivePolicy(fusion=FusionPolicy(reader="v2", read_every=1, cadence=None))
    live = LiveTracker(sp2, finder, scheme, policy)
    res = [live.track(f, i / 25.0) for i, f in enumerate(frames)]
    ok = np.array([r.ok for r in res])
    assert ok.mean() >= 0.95
    assert live.finder_calls >= 0.95 * len(frames)  # a reading on every frame
    ap = np.array([r.lips["aperture_mm"] if r.ok else np.nan for r in res])
    assert np.corrcoef(ap[ok], ap_true[ok])[0, 1] > 0.9


@pytest.mark.parametrize("share", [1.0, 0.5])
def test_the_streamed_opening_is_the_readers_gap_mixed_with_the_fits(enrolled, share):
    """``FusionPolicy.reader_gap``: on every frame the reader read, the streamed
    articulation's projected opening (inner gap over mouth width, as the reader's points
    measure it) is the given mix of the reader's own and the raw fused fit's, and the lips
    still follow the truth; without it, the streamed opening is the filtered fit's."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.lipgap import model_ratios, reader_ratio
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    sp, frames, ap_true = _test_clip(enrolled)
    fu = FusionPolicy(read_every=1, cadence=None, reader_gap=share, still_mouth=None)
    live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig), LivePolicy(fusion=fu))
    gaps, ap = [], []
    for i, img in enumerate(frames[:40]):
        r = live.track(img, i / 25)
        ap.append(r.lips["aperture_mm"] if r.ok else np.nan)
        if not r.ok or live._fresh is None:
            continue
        read = reader_ratio(np.asarray(live._fresh.landmarks)[:, :2])
        raw = model_ratios(sp.model, sp.camera, np.asarray(r.extra["alpha_raw"])[None],
                           r.pose)[0]
        got = model_ratios(sp.model, sp.camera, r.alpha[None], r.pose)[0]
        gaps.append((got, share * read + (1 - share) * raw, read, raw))
    g = np.array(gaps)
    assert len(g) >= 35  # every frame read
    np.testing.assert_allclose(g[:, 0], g[:, 1], atol=5e-4)
    assert np.abs(g[:, 2] - g[:, 3]).max() > 5e-3  # the two sources differ: the mix is real
    ap = np.array(ap)
    ok = np.isfinite(ap)
    assert ok.mean() > 0.95 and np.corrcoef(ap[ok], ap_true[:40][ok])[0, 1] > 0.9


def test_the_fits_half_of_the_opening_moves_as_far_as_the_mouths_pixels_do(enrolled):
    """``FusionPolicy.still_mouth``: the raw fit's half of the streamed opening follows the
    fit by the share of its change that the mouth's pixels allow (their mean absolute change
    since the last frame, or the last frame's own where larger, over ``still_mouth`` grey
    levels, at least ``lipgap.STILL_MIN_GAIN``): where a frame comes again (a still mouth:
    its pixels did not change) the fit's half hardly moves from the second repeat on, though
    the raw fit does; where the mouth moves, the fit's change passes whole (no lag), and the
    lips still follow the truth."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.lipgap import STILL_MIN_GAIN, model_ratios, still_gain
    from articast.core.faces.live import FusionPolicy, LivePolicy, LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    sp, frames, ap_true = _test_clip(enrolled)
    scale, share = 2.0, 0.5
    fu = FusionPolicy(read_every=1, cadence=None, reader_gap=share, still_mouth=scale)
    live = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig), LivePolicy(fusion=fu))
    # the clip's first 30 frames, then its 30th nine times more (a mouth held still), then on
    order = list(range(30)) + [29] * 9 + list(range(30, len(frames)))
    rows, ap = [], []
    for n, i in enumerate(order):
        r = live.track(frames[i], n / 25)
        assert r.ok and live._fresh is not None
        ap.append(r.lips["aperture_mm"])
        got = model_ratios(sp.model, sp.camera, r.alpha[None], r.pose)[0]
        raw = model_ratios(sp.model, sp.camera, np.asarray(r.extra["alpha_raw"])[None],
                           r.pose)[0]
        rows.append((live._fit_gap, raw, r.extra.get("mouth_change", np.nan),
                     got - share * r.extra["reader_ratio"]))
    half, raw, change, rest = np.array(rows, np.float64).T
    # the streamed opening is the reader's share of its gap and the rest the fit's half
    assert np.median(np.abs(rest - (1 - share) * half)) < 5e-4
    np.testing.assert_allclose(rest, (1 - share) * half, atol=3e-3)
    assert np.isnan(change[0]) and np.all(np.isfinite(change[1:]))
    # the frame again: not a pixel of the mouth changed (the first repeat keeps the change
    # of the frame before: the fit may follow it a frame late)
    assert change[30] == change[29] > 0 and np.all(change[31:39] == 0)
    assert np.sum(change[1:30] >= scale) >= 5  # the speaker talks: those frames pass whole
    gain = np.array([still_gain(c, scale) for c in change[1:]])
    np.testing.assert_allclose(half[1:] - half[:-1], gain * (raw[1:] - half[:-1]), atol=1e-12)
    assert np.allclose(gain[30:38], STILL_MIN_GAIN)
    off = np.abs(raw[31:39] - half[30]).max()
    assert off > 3e-4  # the raw fit moves on the still frames (wanders, or settles away)...
    # ...its half hardly: at most 1 - (1 - STILL_MIN_GAIN)^8, a third, of the way in 8 frames
    # (ungated it would go all the way)
    assert np.abs(half[31:39] - half[30]).max() <= (1 - (1 - STILL_MIN_GAIN) ** 8) * off + 1e-12
    assert np.corrcoef(ap, ap_true[order])[0, 1] > 0.9


def _stretched(src, dst, sx: float) -> None:
    """The clip with the face ``sx`` times wider (the frame resized, its centre kept): a face
    of other proportions, the same size of frame."""
    from articast.service.video import iter_video

    frames = []
    for _, _, img in iter_video(src):
        h, w = img.shape[:2]
        big = cv2.resize(img, (int(w * sx), h))
        x0 = (big.shape[1] - w) // 2
        frames.append(np.ascontiguousarray(big[:, x0:x0 + w]))
    _write_video(dst, frames)


def test_a_face_that_is_not_the_speaker_folders_is_warned_about_once(enrolled, tmp_path,
                                                                      capsys):
    """Issue 39, row 5: the enrolment keeps the face's shape as each landmark network read it;
    ``track`` compares the first readings with it and warns in one line when the face is of
    other proportions (here the speaker's own clip, the face made 30 % wider), never on the
    speaker's own face, and never refuses. A folder enrolled before says once that it is not
    checked."""
    sp = Speaker.load(enrolled / "speaker")
    assert set(sp.identity) == {"v1", "v2"} and sp.report["identity"]["v1"] >= 100
    own = enrolled / "test" / "video.mp4"
    capsys.readouterr()
    assert main(["track", str(own), "--speaker", str(enrolled / "speaker"), "-o",
                 str(tmp_path / "own.jsonl"), "--quiet", "--causal"]) == 0
    assert "does not look like" not in capsys.readouterr().err
    _stretched(own, tmp_path / "wide.mp4", 1.3)
    assert main(["track", str(tmp_path / "wide.mp4"), "--speaker", str(enrolled / "speaker"),
                 "-o", str(tmp_path / "wide.jsonl"), "--quiet", "--causal"]) == 0
    err = capsys.readouterr().err
    warned = [x for x in err.splitlines() if "does not look like the person" in x]
    assert len(warned) == 1 and "wrong --speaker?" in warned[0], err
    assert len(_track_lines(tmp_path / "wide.jsonl")) == 75  # tracked all the same
    old = tmp_path / "old"
    shutil.copytree(enrolled / "speaker", old)
    meta = json.loads((old / "speaker.json").read_text())
    del meta["identity"]
    (old / "speaker.json").write_text(json.dumps(meta))
    assert Speaker.load(old).identity == {}
    assert main(["track", str(tmp_path / "wide.mp4"), "--speaker", str(old), "-o",
                 str(tmp_path / "old.jsonl"), "--quiet", "--causal"]) == 0
    err = capsys.readouterr().err
    assert err.count("enrolled before the identity check") == 1
    assert "does not look like" not in err


def test_a_serve_session_with_another_faces_folder_says_so_once(enrolled, tmp_path):
    """The same check in a serve or room session (service/processors.py's LiveProcessor):
    said through the session's progress line (its console and its clients), once; the frames
    are tracked all the same."""
    from articast.service.processors import LiveProcessor, ProcessorContext
    from articast.service.source_types import Frame, SourceInfo
    from articast.service.video import iter_video

    _stretched(enrolled / "test" / "video.mp4", tmp_path / "wide.mp4", 1.3)
    sp = Speaker.load(enrolled / "speaker")
    said: list[str] = []
    ctx = ProcessorContext("s", SourceInfo("file:wide.mp4", "file", False, 640, 480), sp.model,
                           sp.camera, sp.appearance, {}, sp, said.append)
    proc = LiveProcessor(ctx)
    said.clear()  # (what the warm-up said)
    for i, t, img in iter_video(tmp_path / "wide.mp4"):
        proc.process(Frame(i, t, 0.0, img))
    assert [x for x in said if "does not look like" in x] == said and len(said) == 1, said

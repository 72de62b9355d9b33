"""Offline pipeline through the CLI: synth -> train-appearance -> track, checked against truth."""

import json

import numpy as np
import pytest

from articast.service.cli import main


def test_train_and_track_a_synthetic_video(tmp_path, capsys):
    tr, te = tmp_path / "train", tmp_path / "test"
    assert main(["synth", "sequence", "-o", str(tr), "--seed", "1", "--frames", "40",
                 "--fps", "6"]) == 0
    assert main(["synth", "sequence", "-o", str(te), "--seed", "2", "--frames", "30"]) == 0
    app = tmp_path / "app.npz"
    assert main(["train-appearance", str(tr / "video.mp4"), "--truth", str(tr / "truth.jsonl"),
                 "--model", str(tr / "model.npz"), "--camera", str(tr / "camera.json"),
                 "--kind", "la_lin", "-o", str(app)]) == 0
    out = tmp_path / "track.jsonl"
    assert main(["track", str(te / "video.mp4"), "--model", str(tr / "model.npz"),
                 "--appearance", str(app), "--camera", str(te / "camera.json"),
                 "--init-truth", str(te / "truth.jsonl"), "-o", str(out), "--quiet"]) == 0
    track = [json.loads(x) for x in out.read_text().splitlines()]
    truth = [json.loads(x) for x in (te / "truth.jsonl").read_text().splitlines()]
    assert len(track) == len(truth) == 30
    assert [r["frame"] for r in track] == list(range(30))
    assert all(r["quality"]["ok"] for r in track)
    names = list(truth[0]["alpha"])
    a = np.array([[r["alpha"][n] for n in names] for r in track])
    b = np.array([[r["alpha"][n] for n in names] for r in truth])
    # jaw opening (the largest mode) follows the truth closely on a compressed video
    assert np.corrcoef(a[:, 0], b[:, 0])[0, 1] > 0.9
    assert np.abs(a[:, 0] - b[:, 0]).mean() < 0.3
    # every line carries the lip measures of its own alpha, and they follow the true lips
    from articast.core.model.face import FaceModel
    from articast.core.outputs.lips import lip_measures

    model = FaceModel.load(tr / "model.npz")
    ap, wd = lip_measures(model, a)
    assert np.allclose([r["lips"]["aperture_mm"] for r in track], ap, atol=1e-3)
    assert np.allclose([r["lips"]["width_mm"] for r in track], wd, atol=1e-3)
    ap_true, _ = lip_measures(model, b)
    assert np.corrcoef(ap, ap_true)[0, 1] > 0.9

    # a part of the clip (--start in seconds, --end in frames), with the fit drawn on it
    part, shown = tmp_path / "part.jsonl", tmp_path / "part.mp4"
    common = [str(te / "video.mp4"), "--model", str(tr / "model.npz"), "--appearance", str(app),
              "--init-truth", str(te / "truth.jsonl"), "--quiet"]
    t10 = truth[10]["t"]
    assert main(["track", *common, "--camera", str(te / "camera.json"), "--start", str(t10),
                 "--end", "20f", "-o", str(part), "--overlay", str(shown)]) == 0
    lines = [json.loads(x) for x in part.read_text().splitlines()]
    assert len(lines) == 10 and lines[0]["t"] == pytest.approx(t10)
    import cv2

    cap = cv2.VideoCapture(str(shown))
    drawn = [f for ok, f in iter(cap.read, (False, None)) if ok]
    cap.release()
    plain = cv2.VideoCapture(str(te / "video.mp4"))
    frames = [f for ok, f in iter(plain.read, (False, None)) if ok][10:20]
    plain.release()
    assert len(drawn) == 10 and drawn[0].shape == frames[0].shape
    # the mesh is drawn (green, translucent) where the face is, and the rest is the frame
    diff = np.abs(drawn[5].astype(int) - frames[5].astype(int)).sum(2)
    assert 0.005 < (diff > 40).mean() < 0.5

    # the same camera at half the resolution is scaled to the frames, and says so
    from articast.core.model.camera import Camera

    Camera.load(te / "camera.json").scaled(0.5).save(tmp_path / "half.json")
    capsys.readouterr()
    half = tmp_path / "half.jsonl"
    assert main(["track", *common[:-1], "--camera", str(tmp_path / "half.json"), "--end", "20f",
                 "-o", str(half)]) == 0
    assert "camera scaled from" in capsys.readouterr().err
    a_half = [json.loads(x)["alpha"] for x in half.read_text().splitlines()]
    a_full = [json.loads(x)["alpha"] for x in out.read_text().splitlines()][:20]
    for x, y in zip(a_half, a_full, strict=True):
        assert [x[n] for n in names] == pytest.approx([y[n] for n in names], abs=1e-6)

    # another aspect ratio: one line that says what to do, and no track file left behind
    cam = Camera.load(te / "camera.json")
    Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height * 2).save(tmp_path / "tall.json")
    gone = tmp_path / "gone.jsonl"
    assert main(["track", *common, "--camera", str(tmp_path / "tall.json"), "-o", str(gone),
                 "--overlay", str(tmp_path / "gone.mp4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another aspect ratio" in err[0] and "resize" in err[0], err
    assert not gone.exists() and not (tmp_path / "gone.mp4").exists()
    assert not list(tmp_path.glob(".gone*"))


def test_track_errors_are_one_line(tmp_path, capsys):
    assert main(["track", str(tmp_path / "none.mp4"), "--model", "m.npz", "--appearance",
                 "a.npz", "--camera", "c.json", "-o", str(tmp_path / "t.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "no such" in err and "Traceback" not in err


def test_single_reader_without_the_offline_speaker_track_is_refused(tmp_path, capsys):
    """--single-reader chooses offline track's readers: with --causal, or without --speaker,
    there is nothing to choose, and saying so beats ignoring it."""
    for extra in (["--speaker", str(tmp_path), "--causal"],
                  ["--model", "m.npz", "--appearance", "a.npz", "--camera", "c.json"]):
        assert main(["track", str(tmp_path / "none.mp4"), *extra, "--single-reader", "-o",
                     str(tmp_path / "t.jsonl")]) == 2
        err = capsys.readouterr().err
        assert "--single-reader is for offline tracking with --speaker" in err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_track_that_fails_midway_leaves_no_file(tmp_path, capsys):
    """A truncated video fails after some frames were tracked: no .jsonl (it used to be left
    behind, empty or half written)."""
    assert main(["synth", "sequence", "-o", str(tmp_path / "s"), "--seed", "1", "--frames",
                 "8"]) == 0
    s = tmp_path / "s"
    data = (s / "video.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "t.jsonl"
    code = main(["track", str(tmp_path / "cut.mp4"), "--model", str(s / "model.npz"),
                 "--appearance", str(s / "model.npz"), "--camera", str(s / "camera.json"),
                 "-o", str(out), "--quiet"])
    assert code == 2 and "Traceback" not in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".t.jsonl*"))


def test_start_and_end_are_checked_before_any_work(tmp_path, capsys):
    assert main(["synth", "sequence", "-o", str(tmp_path / "s"), "--seed", "1", "--frames",
                 "5"]) == 0
    video = str(tmp_path / "s" / "video.mp4")
    capsys.readouterr()
    for args, says in ((["--start", "ten"], "expected seconds"),
                       (["--start", "3f", "--end", "2f"], "is not after"),
                       (["--start", "100"], "no frame from 100 s")):
        assert main(["enroll", video, "-o", str(tmp_path / "sp"), "--quiet", *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not (tmp_path / "sp").exists()
    # enroll with a camera of another aspect ratio: what to do, in one line
    from articast.core.model.camera import Camera

    cam = Camera.load(tmp_path / "s" / "camera.json")
    Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height * 2).save(tmp_path / "t.json")
    assert main(["enroll", video, "-o", str(tmp_path / "sp"), "--quiet", "--camera",
                 str(tmp_path / "t.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another aspect ratio" in err[0] and "resize" in err[0], err


def test_a_clip_without_the_face_writes_no_track(speaker4_enrolled, tmp_path, capsys):
    """track --help says -o is written only if tracking succeeds; a clip without the face
    (no frame tracked) wrote it anyway, full of ok=false lines (issue 39). Now: one line,
    exit 2, no file."""
    from tests.service_helpers import write_video

    clip = tmp_path / "empty-room.avi"
    write_video(clip, frames=6, size=(160, 120))  # grey frames: nobody there
    out = tmp_path / "t.jsonl"
    code = main(["track", str(clip), "--speaker", str(speaker4_enrolled / "speaker"), "-o",
                 str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "none of its 6 frames could be tracked" in err and "not written" in err, err
    assert not out.exists() and not list(tmp_path.glob(".t.jsonl*"))

"""Offline pipeline through the CLI: synth -> train-appearance -> track, checked against truth."""

import json

import numpy as np

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


def test_track_errors_are_one_line(tmp_path, capsys):
    assert main(["track", str(tmp_path / "none.mp4"), "--model", "m.npz", "--appearance",
                 "a.npz", "--camera", "c.json", "-o", str(tmp_path / "t.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "Traceback" not in err

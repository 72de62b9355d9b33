"""The committed FAP example reads back and agrees with its committed source track."""

import json
from pathlib import Path

import numpy as np

from articast.core.model.face import FaceModel
from articast.core.outputs.fap import FapEncoder
from articast.core.outputs.fap_io import read_fap

EX = Path(__file__).resolve().parent.parent / "docs" / "examples"


def test_example_fap_matches_its_track():
    fap = read_fap(EX / "synthetic_sentence.fap")
    track = [json.loads(x) for x in (EX / "synthetic_sentence.track.jsonl").read_text().splitlines()]
    model = FaceModel.load(EX / "synthetic_speaker_model.npz")
    assert fap.fps == 25 and len(track) == fap.values.shape[0] == 100
    alpha = np.array([[t["alpha"][n] for n in model.param_names] for t in track])
    pose = np.array([t["pose"]["rotation"] + t["pose"]["translation"] for t in track])
    enc = FapEncoder(model, reference_rotation=pose[0, :3])
    values, mask = enc.values(alpha, pose)
    np.testing.assert_array_equal(fap.values[:, mask], values[:, mask])

"""The face-geometry identity signature (core/faces/identity.py, issue 39 row 5): the same face
under other poses, distances, expressions and noise reads near its signature; a face of other
proportions reads far from it. Faces here are MediaPipe's canonical face, posed and projected
as a landmark network reports them (image px, depth in the same scale)."""

from __future__ import annotations

import numpy as np
import pytest

from articast.core.faces.canonical import canonical_face
from articast.core.faces.identity import (
    CHECK_FRAMES,
    POINTS,
    WARN_DISTANCE,
    FaceSignature,
    IdentityWatch,
    distance,
    signature,
)
from articast.core.model.camera import rotation_matrix

LIPS_AND_JAW = np.array([0, 13, 14, 17, 61, 78, 291, 308, 152, 148, 377, 176, 400])


def _face(kind: str = "same") -> np.ndarray:
    """(478, 3) mm, head axes: the canonical face, or one of other proportions."""
    v = canonical_face().vertices_mm.copy()
    if kind == "longer_nose":  # a nose 6 mm longer and 3 mm more prominent
        nose = (v[:, 1] < v[6, 1]) & (v[:, 1] > v[2, 1] - 2) & (np.abs(v[:, 0]) < 20)
        v[nose, 1] -= 6.0 * (v[6, 1] - v[nose, 1]) / (v[6, 1] - v[2, 1])
        v[nose, 2] += 3.0 * (v[6, 1] - v[nose, 1]) / (v[6, 1] - v[2, 1])
    elif kind == "wider_eyes":  # the eyes 4 mm further apart each, the brows with them
        upper = v[:, 1] > v[6, 1] - 10
        v[upper, 0] += 4.0 * np.tanh(v[upper, 0] / 15.0)
    elif kind != "same":
        raise ValueError(kind)
    return np.concatenate([v, np.repeat(v[:1], 10, axis=0)])  # the 10 iris points


def _frames(face: np.ndarray, n: int, seed: int, noise_px: float = 0.4,
            yaw_deg: float = 15.0) -> np.ndarray:
    """(n, 478, 3) as a landmark network reports ``face``: turned (yaw, pitch, roll), at
    another distance and place in the image, the mouth moving, with pixel noise."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, len(face), 3))
    to_camera = np.diag([1.0, -1.0, -1.0])  # head axes -> image axes (y down, z away)
    for i in range(n):
        shape = face.copy()
        shape[LIPS_AND_JAW, 1] -= rng.uniform(0, 12)  # speech: not in the signature
        rot = rotation_matrix(np.radians([rng.uniform(-8, 8), rng.uniform(-yaw_deg, yaw_deg),
                                          rng.uniform(-6, 6)]))
        px_per_mm = rng.uniform(1.5, 3.0)
        xyz = (shape @ rot.T) @ to_camera * px_per_mm
        xyz[:, :2] += rng.uniform(150, 450, 2)
        out[i] = xyz + rng.normal(0, noise_px, xyz.shape)
    return out


@pytest.fixture(scope="module")
def enrolled() -> FaceSignature:
    sig = signature(_frames(_face(), 150, seed=1), "v2")
    assert sig is not None
    return sig


def test_the_same_face_at_other_poses_and_distances_reads_near_its_signature(enrolled):
    for seed in range(2, 6):
        d = distance(enrolled, _frames(_face(), CHECK_FRAMES, seed=seed))
        assert d is not None and d < 0.5 * WARN_DISTANCE
    # FaceMesh v1's 468 points alone read the same
    d = distance(enrolled, _frames(_face(), CHECK_FRAMES, seed=9)[:, :468])
    assert d is not None and d < 0.5 * WARN_DISTANCE


@pytest.mark.parametrize("kind", ["longer_nose", "wider_eyes"])
def test_a_face_of_other_proportions_reads_far_from_the_signature(enrolled, kind):
    d = distance(enrolled, _frames(_face(kind), CHECK_FRAMES, seed=7))
    assert d is not None and d > 2 * WARN_DISTANCE


def test_the_mouth_and_jaw_are_not_part_of_the_signature():
    assert not set(LIPS_AND_JAW) & set(POINTS.tolist())
    assert len(set(POINTS.tolist())) == len(POINTS) == 80


def test_too_few_frames_give_no_signature_and_no_distance(enrolled):
    assert signature(_frames(_face(), 5, seed=1), "v2") is None
    assert distance(enrolled, _frames(_face(), 5, seed=2)) is None
    with pytest.raises(ValueError):
        signature(np.zeros((30, 68, 3)), "v2")


def test_the_watch_answers_once_on_the_first_readings_of_a_network_it_has(enrolled):
    watch = IdentityWatch({"v2": enrolled})
    other = _frames(_face("wider_eyes"), CHECK_FRAMES + 10, seed=3)
    got = [watch.add(f[:468]) for f in other]  # the v1 reader's: no signature of that
    assert got == [None] * len(other) and not watch.done
    got = [watch.add(f) for f in other]
    assert [i for i, d in enumerate(got) if d is not None] == [CHECK_FRAMES - 1]
    assert watch.done and watch.network == "v2"
    assert watch.distance is not None and watch.distance > WARN_DISTANCE
    assert IdentityWatch({}).done  # a folder without signatures: nothing to watch


def test_a_signature_survives_its_json_and_a_broken_one_is_refused(enrolled):
    from articast.core.errors import ModelFileError

    back = FaceSignature.from_dict(enrolled.to_dict(), "x")
    assert back.network == "v2" and back.frames == enrolled.frames
    np.testing.assert_allclose(back.median, enrolled.median, atol=1e-6)
    d = enrolled.to_dict()
    for bad in ({**d, "spread": [0.0] * len(d["spread"])}, {**d, "median": d["median"][:9]},
                {**d, "median": [float("nan")] * len(d["median"])}, {"network": "v2"}):
        with pytest.raises(ModelFileError):
            FaceSignature.from_dict(bad, "x")

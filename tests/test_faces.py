"""Face detection and landmarks (articast.core.faces) on the synthetic speaker's renders.

Truth: the speaker's true geometry projected with the sequence's pose and camera; MPEG-4
feature points of the synthetic model correspond to MediaPipe landmark indices.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from articast.core.errors import InputError
from articast.core.faces.canonical import canonical_face
from articast.core.faces.detector import DetectorPolicy
from articast.core.faces.finder import (
    DETECTOR_FILE,
    LANDMARK_MODELS,
    Face,
    FaceFinder,
    FinderPolicy,
    models_dir,
)
from articast.core.synthetic import RenderOptions, default_speaker, make_sequence

REFERENCE = Path(__file__).parent / "data" / "face_models_reference.npz"
#: synthetic MPEG-4 feature point -> MediaPipe landmark (person's left = image right)
MIDPOINTS = {"2.2": 13, "2.3": 14, "8.1": 0, "8.2": 17}
CORNERS = {"8.3": 291, "8.4": 61, "2.4": 308, "2.5": 78}
FRAMES = (0, 30, 60, 90, 120)


@pytest.fixture(scope="module")
def finder():
    return FaceFinder.load()


def _render(rig, frames=FRAMES):
    speaker = default_speaker(0)
    seq = make_sequence(0, 150, 50.0, rig, size=(640, 480), geometry=speaker.geometry)
    fp = speaker.geometry.feature_points
    out = []
    for i in frames:
        image = speaker.render(seq.controls[i], seq.pose(i), seq.camera, RenderOptions(seed=i))
        truth = {k: seq.camera.project(seq.pose(i).transform(seq.points[i][fp[k]]))
                 for k in (*MIDPOINTS, *CORNERS)}
        out.append((image, truth))
    return out


@pytest.fixture(scope="module")
def desk():
    return _render("desk")


@pytest.fixture(scope="module")
def head():
    return _render("head", FRAMES[1:4])


def _errors(face, truth, pairs):
    return np.array([np.linalg.norm(face.landmarks[j, :2] - truth[k]) for k, j in pairs.items()])


def test_detector_finds_exactly_one_face_on_a_desk_render(finder, desk):
    for image, truth in desk:
        found = finder.detect(image)
        assert len(found) == 1
        x0, y0, x1, y1 = found[0].box
        mouth = (truth["8.3"] + truth["8.4"]) / 2
        assert x0 < mouth[0] < x1 and y0 < mouth[1] < y1
        # keypoint 3 is the mouth centre
        assert np.linalg.norm(found[0].keypoints[3] - mouth) < 0.15 * (x1 - x0)


def test_a_face_small_in_a_wide_frame_is_found_in_tiles(finder, desk):
    """A speaker at a lectern in a wide shot: the face a sixth of the frame's width, too small
    for the detector's 128 px view of the whole frame; the tiles find it, where it is."""
    image, truth = desk[0]
    small = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA)
    wide = np.full((720, 1280, 3), 90, np.uint8)
    x, y = 700, 300
    wide[y:y + 240, x:x + 320] = small
    mouth = (truth["8.3"] + truth["8.4"]) / 4 + [x, y]
    untiled = FaceFinder.load(policy=FinderPolicy(detector=DetectorPolicy(tiles=None)))
    assert untiled.detect(wide) == []  # the whole frame alone: too small
    found = finder.detect(wide)
    assert len(found) == 1
    x0, y0, x1, y1 = found[0].box
    assert x0 < mouth[0] < x1 and y0 < mouth[1] < y1
    face = finder.find(wide)
    assert face is not None
    assert np.linalg.norm(face.landmarks[61, :2] - truth["8.4"] / 2 - [x, y]) < 4


@pytest.mark.parametrize("kind", ["noise", "blank", "grey"])
def test_no_face_on_noise_or_blank_frames(finder, kind):
    rng = np.random.default_rng(3)
    image = {"noise": rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
             "blank": np.zeros((480, 640, 3), np.uint8),
             "grey": np.full((480, 640, 3), 128, np.uint8)}[kind]
    assert finder.detect(image) == []
    assert finder.find(image) is None


def test_lip_landmarks_land_on_the_true_lips_desk(finder, desk):
    apertures = []
    for image, truth in desk:
        face = finder.find(image)
        assert isinstance(face, Face) and face.landmarks.shape == (478, 3)
        assert not face.landmarks.flags.writeable  # a frozen record, as the tracker keeps it
        assert np.all(face.box[:2] <= face.landmarks[:, :2].min(axis=0))
        assert face.score > 0.9
        assert np.all(_errors(face, truth, MIDPOINTS) < 5.0)  # lips ~53 px wide here
        assert np.all(_errors(face, truth, CORNERS) < 14.0)
        apertures.append((np.linalg.norm(face.landmarks[14, :2] - face.landmarks[13, :2]),
                          np.linalg.norm(truth["2.3"] - truth["2.2"])))
    est, true = np.array(apertures).T
    assert np.ptp(true) > 5.0  # the frames do cover different apertures
    assert np.corrcoef(est, true)[0, 1] > 0.95


def test_head_rig_lower_face_found_with_and_without_a_box(finder, head):
    """A head-mounted camera sees only the lower face: the detector still fires, and the
    landmarks run on a fixed box (the camera moves with the head) follow the lips too."""
    fixed = FaceFinder(finder.detector_session, finder.landmarks_session, FinderPolicy(refine=0))
    box = np.array([-80.0, -280.0, 720.0, 520.0])  # 800 px square above the 640x480 frame
    for image, truth in head:
        for face in (finder.find(image), fixed.find(image, box=box)):
            assert face is not None
            assert np.median(_errors(face, truth, MIDPOINTS)) < 10.0  # lips ~160 px wide


def test_track_from_find_gives_the_same_landmarks_on_a_still_frame(finder, desk):
    """Re-cropping from the landmarks on every frame (keep_roi=0) lands where find did."""
    recrop = FaceFinder(finder.detector_session, finder.landmarks_session,
                        FinderPolicy(keep_roi=0.0))
    for image, _ in desk[:3]:
        face = recrop.find(image)
        again = recrop.track(image, face)
        assert again.roi is not face.roi
        assert again is not None
        lips = [13, 14, 0, 17, 61, 291, 78, 308]
        assert np.abs(again.landmarks[lips, :2] - face.landmarks[lips, :2]).max() < 1.0
        assert np.abs(again.landmarks[:, :2] - face.landmarks[:, :2]).max() < 1.5


def test_track_keeps_a_still_crop_and_follows_a_moving_face(finder, desk):
    image = desk[0][0]
    face = finder.find(image)
    still = finder.track(image, face)
    assert still.roi is face.roi and np.array_equal(still.landmarks, face.landmarks)
    shift = np.float32([[1, 0, 40], [0, 1, 12]])  # the face moves 40 px right, 12 px down
    moved_image = cv2.warpAffine(image, shift, (640, 480), borderMode=cv2.BORDER_REPLICATE)
    moved = finder.track(moved_image, still)  # found in the crop of the previous frame
    lips = [13, 14, 0, 17, 61, 291]
    assert np.abs(moved.landmarks[lips, :2] - face.landmarks[lips, :2] - [40, 12]).max() < 2.0
    followed = finder.track(moved_image, moved)  # the crop now follows the face
    assert followed.roi is not still.roi
    assert np.abs(followed.roi.centre - still.roi.centre - [40, 12]).max() < 6.0  # side 240
    assert np.abs(followed.landmarks[lips, :2] - face.landmarks[lips, :2] - [40, 12]).max() < 1.0


def test_track_loses_the_face_when_it_is_gone(finder, desk):
    face = finder.find(desk[0][0])
    assert finder.track(np.zeros((480, 640, 3), np.uint8), face) is None


def test_onnx_models_match_the_original_tflite_reference(finder):
    """Outputs of the ORIGINAL .tflite (stored by tools/convert_face_models.py) on real
    inputs; the bundled ONNX models must reproduce them within 1e-3."""
    ref = np.load(REFERENCE)
    det_in = (ref["detector_input"].astype(np.float32) * (2.0 / 255.0) - 1.0)[None]
    got = finder.detector_session.run(None, {finder.detector_session.get_inputs()[0].name: det_in})
    for i, out in enumerate(got):
        assert np.abs(out - ref[f"detector_outputs_{i}"]).max() < 1e-3
    half = ref["landmarks_input_half"]
    full = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)
    lm_in = (full.astype(np.float32) / 255.0)[None]
    got = finder.landmarks_session.run(None, {finder.landmarks_session.get_inputs()[0].name: lm_in})
    assert len(got) == 3
    for i, out in enumerate(got):
        want = ref[f"landmarks_outputs_{i}"]
        assert out.shape == want.shape
        assert np.abs(out - want).max() < 1e-3
    v1 = FaceFinder.load(landmarks="v1", detector=finder.detector_session).landmarks_session
    v1_in = (np.repeat(np.repeat(ref["v1_input_half"], 2, axis=0), 2, axis=1)
             .astype(np.float32) / 255.0)[None]
    got = v1.run(None, {v1.get_inputs()[0].name: v1_in})
    assert len(got) == 2
    for i, out in enumerate(got):
        want = ref[f"v1_outputs_{i}"]
        assert out.shape == want.shape
        assert np.abs(out - want).max() < 1e-3


def test_bundled_networks_carry_no_prelu():
    """tools/convert_face_models.py writes each PRelu as Relu + Sub + Mul + Add (the same
    floats; onnxruntime's CPU PRelu leaves its blocked layout and was half of each landmark
    network's time). A model converted again without that step would be slower and
    still pass the parity test above: this one fails on it. The op type is stored in the
    protobuf as a plain string."""
    folder = models_dir()
    for name in (DETECTOR_FILE, *LANDMARK_MODELS.values()):
        data = (folder / name).read_bytes()
        assert b"PRelu" not in data, name


def test_box_must_be_a_proper_box(finder, desk):
    with pytest.raises(InputError):
        finder.find(desk[0][0], box=np.array([10.0, 10.0, 5.0, 50.0]))
    with pytest.raises(InputError):
        FaceFinder.load(threads=0)


def test_canonical_face_is_metric_and_triangulated():
    canon = canonical_face()
    v, tri = canon.vertices_mm, canon.triangles
    assert v.shape == (468, 3) and tri.shape[1] == 3 and len(tri) > 800
    assert tri.min() == 0 and tri.max() == 467
    assert 80.0 < np.linalg.norm(v[33] - v[263]) < 100.0  # outer eye corners, mm
    assert 40.0 < np.linalg.norm(v[61] - v[291]) < 60.0  # mouth corners, mm
    # the articast head frame: x to the person's left, y up, z forward
    assert v[263, 0] > 0 > v[33, 0] and v[10, 1] > v[152, 1]
    assert v[1, 2] > np.percentile(v[:, 2], 99)  # the nose tip is in front
    # every vertex is used, and each edge is shared by at most two triangles (a manifold)
    assert len(np.unique(tri)) == 468
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() <= 2
    a = v[tri]
    facing = np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0])[:, 2] > 0
    assert facing.mean() > 0.95  # counter-clockwise seen from +z


def test_lip_contours_run_corner_to_corner_through_the_midpoints():
    canon = canonical_face()
    ends = {"outer": (61, 291), "inner": (78, 308)}
    for name, mid in (("lips_outer_upper", 0), ("lips_outer_lower", 17),
                      ("lips_inner_upper", 13), ("lips_inner_lower", 14)):
        c = canon.contours[name]
        assert (c[0], c[-1]) == ends[name.split("_")[1]] and mid in c
        pairs = {tuple(sorted(e)) for e in canon.edges["lips"].tolist()}
        assert all(tuple(sorted(p)) in pairs for p in zip(c[:-1], c[1:]))
        assert np.all(np.diff(canon.vertices_mm[c, 0]) > 0)  # right corner -> left corner


def test_crop_is_the_rgb_patch_scaled_to_unit_range_in_float32():
    """The network input: the warped patch, channels reversed to RGB, x 1/255 in float32
    (written with cv2.cvtColor and an in-place scale: the same floats as the plain formula)."""
    from articast.core.faces.landmarks import Roi, crop

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)
    roi = Roi(np.array([61.0, 44.0]), 70.0, 0.3)
    got = crop(img, roi, 64)
    patch = cv2.warpAffine(img, roi.crop_to_image(64), (64, 64),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    want = (patch[:, :, ::-1].astype(np.float32) * (1.0 / 255.0))[None]
    assert got.dtype == np.float32 and got.shape == (1, 64, 64, 3)
    assert np.array_equal(got, want)
    # channel 0 is the image's red (BGR's last)
    np.testing.assert_allclose(got[0, :, :, 0], patch[:, :, 2] / 255.0, atol=1e-6)

"""The reader's lip gap as the streamed opening (core/faces/lipgap.py), on the synthetic
speaker's model, where the ratio of any articulation is known."""

from __future__ import annotations

import numpy as np
import pytest

from articast.core.faces.lipgap import (
    MODEL_POINTS,
    PATCH_SIZE,
    READER_POINTS,
    gap_ratio,
    matched,
    model_ratios,
    mouth_patch,
    reader_ratio,
)
from articast.core.model.camera import Camera, Pose
from articast.core.outputs.lips import lip_measures
from articast.core.synthetic import default_speaker


@pytest.fixture(scope="module")
def model():
    return default_speaker(1).model()


def test_the_ratio_is_the_gap_normal_to_the_corner_line_over_the_width():
    # corners 100 px apart on a line tilted 30 deg; the lower lip 12 px below the upper,
    # along the line's normal, and shifted along the line (which must not count)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    along, normal = np.array([c, s]), np.array([-s, c])
    right, left = np.array([50.0, 80.0]), np.array([50.0, 80.0]) + 100 * along
    up = (right + left) / 2 - 3 * normal
    low = up + 12 * normal + 7 * along
    assert gap_ratio(np.array([up, low, right, left])) == pytest.approx(0.12)
    assert gap_ratio(np.array([low, up, right, left])) == pytest.approx(-0.12)  # lips crossed
    marks = np.zeros((478, 2))
    marks[list(READER_POINTS)] = [up, low, right, left]
    assert reader_ratio(marks) == pytest.approx(0.12)
    assert np.isnan(reader_ratio(np.zeros((10, 2))))  # not the MediaPipe topology


def test_the_model_ratio_is_read_on_the_points_the_reader_reads(model):
    cam, pose = Camera.default(640, 480), Pose()
    a = np.zeros(model.n_params)
    idx = [model.point(x) for x in MODEL_POINTS]
    uv = cam.project_head(model.shape(a)[idx], pose)
    assert model_ratios(model, cam, a[None], pose)[0] == pytest.approx(gap_ratio(uv))
    # jaw1 opens the mouth: the ratio grows with it
    j = model.param_names.index("jaw1")
    ratios = model_ratios(model, cam, np.outer([0.0, 1.0, 2.0], np.eye(model.n_params)[j]),
                          pose)
    assert ratios[0] < ratios[1] < ratios[2]


@pytest.mark.parametrize("target_shift", [-0.03, 0.0, 0.02, 0.08])
def test_matching_reaches_the_target_by_the_smallest_step(model, target_shift):
    cam = Camera.default(640, 480)
    pose = Pose(rotation=[0.1, -0.2, 0.05], translation=[10.0, -5.0, 450.0])
    rng = np.random.default_rng(0)
    a0 = rng.normal(0, 0.5, model.n_params)
    r0 = model_ratios(model, cam, a0[None], pose)[0]
    target = r0 + target_shift
    a = matched(model, cam, a0, pose, target)
    assert model_ratios(model, cam, a[None], pose)[0] == pytest.approx(target, abs=2e-4)
    # the reading tells the opening, not the width: the streamed width stays the fit's
    _, w0 = lip_measures(model, a0)
    _, w1 = lip_measures(model, a)
    assert w1 == pytest.approx(w0, abs=0.02)
    if target_shift == 0.0:
        np.testing.assert_allclose(a, a0, atol=1e-6)
        return
    # the smallest such step lies in the span of the two measures' gradients: any component
    # outside it would lengthen the step and change neither
    step = a - a0

    def grad(f):
        return np.array([(f(a0 + e) - f(a0 - e)) / 2e-3
                         for e in np.eye(model.n_params) * 1e-3])

    span = np.stack([grad(lambda x: model_ratios(model, cam, x[None], pose)[0]),
                     grad(lambda x: float(lip_measures(model, x)[1]))]).T
    inside = span @ np.linalg.lstsq(span, step, rcond=None)[0]
    assert np.linalg.norm(step - inside) < 0.02 * np.linalg.norm(step)


def test_matching_leaves_the_articulation_when_the_reading_says_nothing(model):
    cam, pose = Camera.default(640, 480), Pose()
    a0 = np.full(model.n_params, 0.3)
    np.testing.assert_array_equal(matched(model, cam, a0, pose, float("nan")), a0)
    # a reading asking for far more than the articulation holds is followed max_change far
    far = matched(model, cam, a0, pose, 5.0, max_change=2.0)
    assert np.linalg.norm(far - a0) == pytest.approx(2.0)


def test_offline_the_opening_is_half_the_readers_gap_half_the_smoothed_fits(model):
    """``with_reader_gap``: each frame's projected ratio moves to the mean of the share of
    both readers' (smoothed over the frame's neighbours) and the rest its own; a frame no
    reader read, or no share, keeps the smoothed articulation."""
    from articast.core.faces.offline import Smoothed, with_reader_gap

    cam = Camera.default(640, 480)
    pose = Pose(rotation=[0.05, 0.1, 0.0], translation=[0.0, 0.0, 450.0])
    j = model.param_names.index("jaw1")
    frames = [Smoothed(np.eye(model.n_params)[j] * v, pose) for v in (0.5, 0.6, 0.7, 0.8)]
    own = model_ratios(model, cam, np.array([f.alpha for f in frames]), pose)
    v1 = own + 0.04  # a reader that reads the mouth more open
    v2 = np.array([own[0] + 0.02, own[1] + 0.02, np.nan, own[3] + 0.02])
    out = with_reader_gap(frames + [frames[0]], [np.append(v1, np.nan), np.append(v2, np.nan)],
                          model, cam, 0.5)
    got = model_ratios(model, cam, np.array([f.alpha for f in out[:4]]), pose)
    read = np.array([own[0] + 0.03, own[1] + 0.03, own[2] + 0.04, own[3] + 0.03])
    smooth = np.array([(2 * read[0] + read[1]) / 3, (read[0] + 2 * read[1] + read[2]) / 4,
                       (read[1] + 2 * read[2] + read[3]) / 4, (read[2] + 2 * read[3]) / 3])
    np.testing.assert_allclose(got, 0.5 * smooth + 0.5 * own, atol=2e-4)
    assert out[4] is frames[0]  # not read: as smoothed
    assert with_reader_gap(frames, [v1], model, cam, 0.0) is frames


@pytest.mark.skipif(not __import__("articast.core.tracking.kernels",
                                   fromlist=["AVAILABLE"]).AVAILABLE,
                    reason="numba is not installed: the live tracker uses the numpy path")
@pytest.mark.parametrize("share", [0.5, 1.0])
def test_the_compiled_lip_gap_is_the_numpy_one(model, share):
    """The live tracker's one compiled call (kernels.lip_gap) gives what model_ratios and one
    iteration of matched give, over random states, targets and poses, including a target out
    of reach (the step's length limit) and a reading of NaN (alpha unchanged)."""
    from articast.core.faces import lipgap
    from articast.core.tracking import kernels

    cam = Camera.default(640, 480)
    mean, basis = lipgap.lip_points(model)
    intr = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
    rng = np.random.default_rng(1)
    moved = 0
    for i in range(40):
        pose = Pose(rotation=np.array([np.pi, 0, 0]) + rng.normal(0, 0.15, 3),
                    translation=np.array([0, 0, 450.0]) + rng.normal(0, 20, 3))
        alpha, fitted = rng.normal(0, 1, model.n_params), rng.normal(0, 1, model.n_params)
        read = [float("nan"), 2.0][i] if i < 2 else float(rng.uniform(-0.05, 0.4))
        target = read
        if share < 1.0:
            f = float(model_ratios(model, cam, fitted[None], pose)[0])
            target = share * read + (1 - share) * f
        want = matched(model, cam, alpha, pose, target, iterations=1)
        got = kernels.lip_gap(mean, basis, pose.matrix, np.array(pose.translation), intr,
                              alpha, fitted, read, share, lipgap.PROBE_STEP,
                              lipgap.MAX_CHANGE, lipgap.TOLERANCE)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        moved += not np.allclose(got, alpha)
    assert moved >= 30  # (the comparison is not of alphas left where they were)


def test_the_mouth_patch_takes_a_box_as_an_array_or_a_sequence():
    img = np.random.default_rng(6).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    box = np.array([40.3, 50.7, 90.1, 75.2])
    got = mouth_patch(img, box)
    assert got.shape == PATCH_SIZE[::-1] and got.dtype == np.uint8
    assert np.array_equal(got, mouth_patch(img, list(box)))

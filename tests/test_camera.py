"""Camera projection against OpenCV, analytic Jacobians, poses, chessboard calibration."""

import cv2
import numpy as np
import pytest

from articast.core.errors import CalibrationError, InputError, ModelFileError
from articast.core.model.camera import (
    FRONTAL,
    Camera,
    Pose,
    axis_angle,
    calibrate_chessboard,
    rotation_matrix,
)

DISTORTED = Camera(610.0, 605.0, 322.0, 238.5, 640, 480, np.array([-0.21, 0.08, 1e-3, -2e-3, -0.01]))


def test_projection_matches_opencv(rng):
    pts = rng.uniform([-80, -60, 300], [80, 60, 500], size=(200, 3))
    ours = DISTORTED.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), DISTORTED.K, DISTORTED.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-9)


def test_projection_jacobian_matches_finite_differences(rng):
    pts = rng.uniform([-80, -60, 300], [80, 60, 500], size=(50, 3))
    _, jac = DISTORTED.project_jacobian(pts)
    eps = 1e-4
    for d in range(3):
        step = np.zeros(3)
        step[d] = eps
        num = (DISTORTED.project(pts + step) - DISTORTED.project(pts - step)) / (2 * eps)
        np.testing.assert_allclose(jac[:, :, d], num, rtol=1e-5, atol=1e-6)


def test_points_behind_camera_are_nan():
    uv = Camera.default().project(np.array([[0.0, 0.0, -10.0], [0.0, 0.0, 100.0]]))
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


def test_rotation_round_trip(rng):
    for r in rng.normal(size=(20, 3)):
        r = r / np.linalg.norm(r) * rng.uniform(0, np.pi - 1e-3)
        rot = rotation_matrix(r)
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(rot, cv2.Rodrigues(r)[0], atol=1e-12)
        np.testing.assert_allclose(axis_angle(rot), r, atol=1e-7)
    np.testing.assert_allclose(rotation_matrix(FRONTAL), np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_frontal_pose_puts_face_left_on_image_right():
    cam, pose = Camera.default(), Pose()
    left_cheek, right_cheek, chin = [40.0, 0, 0], [-40.0, 0, 0], [0, -60.0, 0]
    uv = cam.project_head(np.array([left_cheek, right_cheek, chin]), pose)
    assert uv[0, 0] > cam.cx > uv[1, 0]  # speaker's left appears on the image's right
    assert uv[2, 1] > cam.cy  # chin below centre


def test_pose_inverse_and_dict(rng):
    pose = Pose(rng.normal(size=3), rng.normal(size=3) * 100)
    pts = rng.normal(size=(10, 3))
    np.testing.assert_allclose(pose.inverse_transform(pose.transform(pts)), pts, atol=1e-10)
    again = Pose.from_dict(pose.to_dict())
    assert np.array_equal(again.as_vector(), pose.as_vector())
    with pytest.raises(InputError):
        Pose([0, 0], [0, 0, 1])


def test_camera_file_round_trip_and_errors(tmp_path):
    DISTORTED.save(tmp_path / "c.json")
    cam = Camera.load(tmp_path / "c.json")
    np.testing.assert_array_equal(cam.K, DISTORTED.K)
    np.testing.assert_array_equal(cam.dist, DISTORTED.dist)
    (tmp_path / "bad.json").write_text('{"K": [[1, 0], [0, 1]], "width": 640, "height": 480}')
    with pytest.raises(ModelFileError, match="K must be 3x3"):
        Camera.load(tmp_path / "bad.json")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="not a JSON camera file"):
        Camera.load(tmp_path / "junk.json")


def _chessboard_views(cam, pattern=(9, 6), square=20.0, n=8, seed=0):
    """Render a flat chessboard seen by ``cam`` from n poses (warpPerspective of a board)."""
    rng = np.random.default_rng(seed)
    cols, rows = pattern[0] + 1, pattern[1] + 1
    px = 40
    board = np.kron((np.indices((rows, cols)).sum(0) % 2) * 255, np.ones((px, px))).astype(np.uint8)
    board = cv2.copyMakeBorder(board, px, px, px, px, cv2.BORDER_CONSTANT, value=255)
    h, w = board.shape
    corners_px = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    corners_mm = (corners_px - px) / px * square - np.array([cols, rows]) * square / 2
    views = []
    for _ in range(n):
        r = rng.normal(size=3) * 0.25
        pose = Pose(r, [rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(350, 450)])
        obj = np.c_[corners_mm, np.zeros(4)]
        img_pts, _ = cv2.projectPoints(obj, pose.rotation, pose.translation, cam.K, None)
        hmat = cv2.getPerspectiveTransform(corners_px.astype(np.float32), img_pts.reshape(4, 2).astype(np.float32))
        views.append(cv2.warpPerspective(board, hmat, (cam.width, cam.height), borderValue=128))
    return views


def test_calibration_recovers_intrinsics():
    truth = Camera(560.0, 560.0, 330.0, 235.0, 640, 480)
    cal = calibrate_chessboard(_chessboard_views(truth), (9, 6), 20.0)
    assert cal.images_used >= 6
    assert cal.rms_px < 0.5
    assert abs(cal.camera.fx - truth.fx) / truth.fx < 0.03
    assert abs(cal.camera.cx - truth.cx) < 10


def test_calibration_without_pattern_fails_clearly():
    blank = [np.full((480, 640), 128, np.uint8)] * 4
    with pytest.raises(CalibrationError, match="found in 0 image"):
        calibrate_chessboard(blank, (9, 6), 20.0)

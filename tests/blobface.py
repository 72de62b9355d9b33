"""A tiny stand-in face for unit tests of the fitting machinery: the toy corpus model of
test_build rendered as coloured, blurred discs at its projected points. Not the product's
synthetic speaker (core/synthetic): just enough texture to check Jacobians and convergence."""

import cv2
import numpy as np

from articast.core.model.build import build_model
from articast.core.model.camera import Camera, Pose
from tests.test_build import grid_corpus


def blob_model(seed=0):
    rng = np.random.default_rng(seed)
    model, _ = build_model(grid_corpus(rng, v=60, noise=0.05))
    # a triangulation is needed for visibility tests: fan over the xy projection
    from scipy.spatial import Delaunay

    tri = Delaunay(model.mean[:, :2]).simplices.astype(np.int32)
    a, b, c = (model.mean[tri[:, i]] for i in range(3))
    flip = np.cross(b - a, c - a)[:, 2] < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    from articast.core.model.face import FaceModel

    return FaceModel(model.mean, model.basis, model.param_names, model.stats, model.point_names,
                     model.groups, tri, model.feature_points, {}, "blob")


def render_blobs(model, camera, alpha, pose, seed=0, shading=0.0):
    """shading > 0: each disc is a facet with its own normal, lit by a light fixed to the
    camera (Lambert), so its brightness changes as the head turns."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(30, 225, size=(model.n_points, 3))
    if shading:
        normals = rng.normal(size=(model.n_points, 3)) * [0.5, 0.5, 0.0] + [0.0, 0.0, 1.0]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        light = np.array([-0.4, -0.3, -0.87])  # towards the light, camera frame
        lit = np.clip((normals @ pose.matrix.T) @ light, 0.0, None)
        colours = np.clip(colours * (1.0 - shading + shading * 1.6 * lit[:, None]), 0, 255)
    img = np.full((camera.height, camera.width, 3), 90, np.uint8)
    # a smooth background gradient so derivatives are not all zero away from blobs
    img[:] += (np.linspace(0, 40, camera.width)[None, :, None]).astype(np.uint8)
    uv = camera.project_head(model.shape(alpha), pose)
    for (u, v), col in zip(uv, colours):
        cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 5 * 16,
                   tuple(int(x) for x in col), -1, cv2.LINE_AA, 4)
    return cv2.GaussianBlur(img, (0, 0), 1.2)


def blob_trained(seed=5, kind="la_lin", n=30):
    """The blob face with an appearance model trained on n frames of random states."""
    from articast.core.appearance.models import TrainingFrame, train_appearance

    model, camera, pose = blob_setup()
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        a = rng.normal(size=7) * 0.8
        p = Pose(pose.rotation + rng.normal(size=3) * 0.02,
                 pose.translation + rng.normal(size=3) * 3)
        frames.append(TrainingFrame(render_blobs(model, camera, a, p), a, p))
    app = train_appearance(model, camera, frames, kind, sigma=2.0, levels=(0, 1), per_param=6)
    return model, camera, pose, app


def blob_setup():
    model = blob_model()
    camera = Camera.default(480, 360, 36)
    # oblique view (yaw 25 deg, pitch 15 deg) so that depth-only modes (jaw2) are observable
    from articast.core.model.camera import FRONTAL, axis_angle, rotation_matrix

    rot = rotation_matrix(np.array([0.26, 0.0, 0.0])) @ rotation_matrix(np.array([0.0, 0.44, 0.0]))
    pose = Pose(rotation=axis_angle(rotation_matrix(FRONTAL) @ rot), translation=[0.0, -10.0, 300.0])
    return model, camera, pose

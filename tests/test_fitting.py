"""Appearance sampling, analytic Jacobians and single-frame fits on a stand-in blob face."""

import numpy as np
import pytest

from core.appearance import image_maps, roi_of, sample_la
from core.camera import rotation_matrix
from core.fitting import Problem, fit_gauss_newton, fit_nelder_mead
from tests.blobface import blob_trained, render_blobs


@pytest.fixture(scope="module")
def trained():
    return blob_trained(seed=5)


def test_la_derivatives_match_finite_differences():
    rng = np.random.default_rng(0)
    img = (rng.random((60, 80, 3)) * 255).astype(np.uint8)
    import cv2

    img = cv2.GaussianBlur(img, (0, 0), 2)
    maps = image_maps(img, (0, 0, 80, 60), 1.5, 0)
    uv = rng.uniform([10, 10], [70, 50], size=(40, 2))
    d, dd, valid = sample_la(maps, uv)
    assert valid.all()
    eps = 1e-4
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = eps
        num = (sample_la(maps, uv + step)[0] - sample_la(maps, uv - step)[0]) / (2 * eps)
        np.testing.assert_allclose(dd[:, :, axis], num, rtol=1e-3, atol=1e-3)


def test_samples_outside_the_map_are_invalid():
    img = np.zeros((40, 40, 3), np.uint8)
    maps = image_maps(img, (0, 0, 40, 40), 1.0, 0)
    _, _, valid = sample_la(maps, np.array([[20.0, 20.0], [-5.0, 3.0], [np.nan, 1.0], [39.5, 20]]))
    assert valid.tolist() == [True, False, False, False]


def test_residual_jacobian_matches_finite_differences(trained):
    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    alpha = np.full(7, 0.2)
    img = render_blobs(model, camera, alpha, pose)
    maps = image_maps(img, roi_of(prob.project(np.r_[alpha, pose.as_vector()]), 30), app.sigma, 0)
    rot = rotation_matrix(pose.rotation)
    r, jac, _ = prob.residuals(maps, 0, alpha, rot, pose.translation, True)
    eps = np.r_[np.full(7, 1e-4), np.full(3, 1e-6), np.full(3, 1e-4)]
    for j in range(13):
        d = np.zeros(13)
        d[j] = eps[j]
        def at(x):
            return prob.residuals(maps, 0, alpha + x[:7], rotation_matrix(x[7:10]) @ rot,
                                  pose.translation + x[10:], False)[0]
        num = (at(d) - at(-d)) / (2 * eps[j])
        scale = np.abs(num).max() + 1e-9
        assert np.abs(jac[:, j] - num).max() / scale < 0.05, j


@pytest.mark.parametrize("optimiser", ["gn", "nm"])
def test_fit_recovers_a_perturbed_state(trained, optimiser):
    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    truth = np.array([0.9, -0.6, 0.4, 0.3, -0.5, 0.2, 0.1])
    img = render_blobs(model, camera, truth, pose)
    start_t = pose.translation + [1.5, -1.0, 2.0]
    roi = roi_of(prob.project(np.r_[np.zeros(7), pose.rotation, start_t]), 40)
    maps = image_maps(img, roi, app.sigma, 0)
    if optimiser == "gn":  # coarse to fine: half resolution first
        from core.fitting import FitPolicy

        coarse = fit_gauss_newton(prob, image_maps(img, roi, app.sigma, 1), 1, np.zeros(7),
                                  pose.rotation, start_t, FitPolicy(max_iterations=30))
        res = fit_gauss_newton(prob, maps, 0, coarse.alpha, coarse.rotation, coarse.translation)
        assert coarse.evals + res.evals <= 40  # a cold start, far from the per-frame budget
    else:
        from core.fitting import FitPolicy

        res = fit_nelder_mead(prob, maps, 0, np.zeros(7), pose.rotation, start_t,
                              FitPolicy(nelder_mead_evals=3000))
    err = model.shape(res.alpha) - model.shape(truth)
    rms = np.sqrt((err**2).sum(1).mean())
    start_rms = np.sqrt(((model.shape(np.zeros(7)) - model.shape(truth)) ** 2).sum(1).mean())
    assert rms < 0.25 * start_rms, (rms, start_rms)
    assert np.abs(res.translation - pose.translation).max() < 1.5


def test_robust_loss_gradient_and_weights_are_those_of_its_cost():
    """The IRLS residuals/Jacobian give g = J_w^T r_w = half the gradient of the Cauchy cost
    (the least-squares convention of the optimiser), checked by finite differences on a
    random linear residual; None is plain least squares."""
    from core.fitting import _robust

    rng = np.random.default_rng(4)
    c, s, p = 8, 12, 5
    a, b = rng.normal(size=(s * c, p)), rng.normal(size=s * c) * 3
    x = rng.normal(size=p)

    def cost(v):
        return _robust(a @ v + b, None, c, 2.0)[0]

    _, rw, jw = _robust(a @ x + b, a, c, 2.0)
    num = np.array([(cost(x + e) - cost(x - e)) / 2e-6 for e in np.eye(p) * 1e-6])
    np.testing.assert_allclose(2 * jw.T @ rw, num, rtol=1e-5, atol=1e-6)
    r = a @ x + b
    assert _robust(r, a, c, None)[0] == pytest.approx(float(r @ r))
    # a point 10x off counts far less than in least squares: cost grows like log, not square
    big = np.zeros(s * c)
    big[:c] = 10.0
    assert _robust(big, None, c, 2.0)[0] < 0.1 * float(big @ big)


def test_robust_fit_is_not_dragged_by_points_the_model_gets_wrong(trained):
    """Patches of foreign colour over a few sample points (what the linear model cannot
    predict: a hand, lips beyond the enrolment's range) pull the least-squares fit away;
    the per-point Cauchy loss lets the other points decide."""
    import cv2

    from core.fitting import FitPolicy

    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    truth = np.array([0.5, -0.4, 0.3, 0.2, -0.3, 0.2, 0.1])
    img = render_blobs(model, camera, truth, pose).copy()
    uv = prob.project(np.r_[truth, pose.as_vector()])
    rng = np.random.default_rng(2)
    for i in rng.choice(len(uv), size=max(3, len(uv) // 6), replace=False):
        u, v = (int(round(z)) for z in uv[i])
        cv2.rectangle(img, (u - 6, v - 6), (u + 6, v + 6),
                      tuple(int(z) for z in rng.integers(0, 255, 3)), -1)
    maps = image_maps(img, roi_of(uv, 40), app.sigma, 0)
    errs = {}
    for scale in (None, 2.0):
        res = fit_gauss_newton(prob, maps, 0, np.zeros(7), pose.rotation, pose.translation,
                               FitPolicy(max_iterations=30, robust_scale=scale,
                                         pose_sigma_rad=0.001, pose_sigma_mm=0.1),
                               pose_ref=(pose.rotation, pose.translation))
        errs[scale] = float(np.sqrt(((model.shape(res.alpha) - model.shape(truth)) ** 2)
                                    .sum(1).mean()))
    assert errs[2.0] < 0.6 * errs[None], errs

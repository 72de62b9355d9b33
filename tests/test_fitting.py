"""Appearance sampling, analytic Jacobians and single-frame fits on a stand-in blob face."""

import numpy as np
import pytest

from articast.core.appearance.maps import image_maps, roi_of, sample_la
from articast.core.model.camera import Pose, rotation_matrix
from articast.core.tracking.fitting import FitPolicy, Problem, fit_gauss_newton, fit_nelder_mead
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


def shaded_frames(model, camera, pose, rng, n, turn=0.06):
    """Frames of the blob face lit by a camera-fixed light, the head turning by ~3 deg."""
    from articast.core.appearance.models import TrainingFrame
    from articast.core.model.camera import Pose

    out = []
    for _ in range(n):
        a = rng.normal(size=7) * 0.8
        p = Pose(pose.rotation + rng.normal(size=3) * turn,
                 pose.translation + rng.normal(size=3) * 2)
        out.append(TrainingFrame(render_blobs(model, camera, a, p, shading=0.5), a, p))
    return out


@pytest.fixture(scope="module")
def shaded():
    from articast.core.appearance.models import train_appearance
    from tests.blobface import blob_setup

    model, camera, pose = blob_setup()
    rng = np.random.default_rng(11)
    train = shaded_frames(model, camera, pose, rng, 40)
    kw = dict(sigma=2.0, levels=(0,), per_param=6)
    plain = train_appearance(model, camera, train, "la_lin", **kw)
    turned = train_appearance(model, camera, train, "la_lin", rotation_terms=True, **kw)
    return model, camera, pose, plain, turned, shaded_frames(model, camera, pose, rng, 12)


def test_rotation_terms_jacobian_matches_finite_differences(shaded):
    model, camera, pose, _, app, tests = shaded
    prob = Problem(model, app, camera)
    fr = tests[0]
    rot = fr.pose.matrix
    maps = image_maps(fr.image, roi_of(prob.project(np.r_[fr.alpha, fr.pose.as_vector()]), 30),
                      app.sigma, 0)
    r, jac, _ = prob.residuals(maps, 0, fr.alpha, rot, fr.pose.translation, True, 1.1, True)
    eps = np.r_[np.full(7, 1e-4), np.full(3, 1e-6), np.full(3, 1e-4), 1e-5]

    def at(x):
        return prob.residuals(maps, 0, fr.alpha + x[:7], rotation_matrix(x[7:10]) @ rot,
                              fr.pose.translation + x[10:13], False, 1.1 + x[13], True)[0]
    for j in range(14):
        d = np.zeros(14)
        d[j] = eps[j]
        num = (at(d) - at(-d)) / (2 * eps[j])
        scale = np.abs(num).max() + 1e-9
        assert np.abs(jac[:, j] - num).max() / scale < 0.05, j


def test_rotation_terms_follow_shading_as_the_head_turns(shaded):
    """Under a camera-fixed light, a model of the articulation alone reads the shading of a
    turning head as articulation; with rotation terms the fit from the true state stays
    closer to it."""
    from articast.core.tracking.fitting import FitPolicy

    model, camera, pose, plain, turned, tests = shaded
    errs = {}
    for name, app in (("plain", plain), ("turned", turned)):
        prob = Problem(model, app, camera)
        e = []
        for fr in tests:
            maps = image_maps(fr.image, roi_of(prob.project(np.r_[fr.alpha,
                                                                  fr.pose.as_vector()]), 30),
                              app.sigma, 0)
            res = fit_gauss_newton(prob, maps, 0, fr.alpha, fr.pose.rotation, fr.pose.translation,
                                   FitPolicy(max_iterations=15))
            e.append(np.sqrt(((model.shape(res.alpha) - model.shape(fr.alpha)) ** 2)
                             .sum(1).mean()))
        errs[name] = float(np.mean(e))
    assert errs["turned"] < 0.7 * errs["plain"], errs


def test_rotation_terms_round_trip_and_bad_files(shaded, tmp_path):
    from dataclasses import replace

    from articast.core.appearance.models import AppearanceModel
    from articast.core.errors import InputError, ModelFileError

    model, camera, _, _, app, tests = shaded
    path = tmp_path / "app.npz"
    app.save(path)
    back = AppearanceModel.load(path, model)
    np.testing.assert_array_equal(back.rotation_weights, app.rotation_weights)
    np.testing.assert_array_equal(back.rotation_ref, app.rotation_ref)
    bad = replace(app, rotation_weights=app.rotation_weights[:, :2])
    bad.save(tmp_path / "bad.npz")
    with pytest.raises(ModelFileError, match="rotation terms have shape"):
        AppearanceModel.load(tmp_path / "bad.npz", model)
    half = replace(app, rotation_ref=None)
    half.save(tmp_path / "half.npz")  # saved without rotation terms: a plain la model
    assert AppearanceModel.load(tmp_path / "half.npz", model).rotation_weights is None
    from articast.core.appearance.models import train_appearance
    with pytest.raises(InputError, match="rotation terms"):
        train_appearance(model, camera, tests, "tex_lin", rotation_terms=True)


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
        from articast.core.tracking.fitting import FitPolicy

        coarse = fit_gauss_newton(prob, image_maps(img, roi, app.sigma, 1), 1, np.zeros(7),
                                  pose.rotation, start_t, FitPolicy(max_iterations=30))
        res = fit_gauss_newton(prob, maps, 0, coarse.alpha, coarse.rotation, coarse.translation)
        assert coarse.evals + res.evals <= 40  # a cold start, far from the per-frame budget
    else:
        from articast.core.tracking.fitting import FitPolicy

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
    from articast.core.tracking.fitting import _robust

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

    from articast.core.tracking.fitting import FitPolicy

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


@pytest.mark.parametrize("kind", ["la_lin", "la_quad"])
@pytest.mark.parametrize("distorted", [False, True])
def test_compiled_kernel_gives_the_numpy_reference_numbers(trained, kind, distorted):
    """articast.core.tracking.kernels fuses the la cost into one compiled loop; Problem.residuals' numpy code is
    the definition. Same residuals, Jacobian (with gain) and valid set, samples off the map
    included, for la lin and la quad, with and without lens distortion."""
    from dataclasses import replace

    from articast.core.appearance.models import TrainingFrame, train_appearance
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0): only the numpy path")
    model, camera, pose, app = trained
    if kind == "la_quad":
        rng = np.random.default_rng(1)
        frames = []
        for _ in range(20):
            a = rng.normal(size=7) * 0.8
            frames.append(TrainingFrame(render_blobs(model, camera, a, pose), a, pose))
        app = train_appearance(model, camera, frames, kind, sigma=2.0, levels=(0, 1))
    if distorted:
        camera = replace(camera, dist=np.array([0.08, -0.03, 0.002, -0.001, 0.01]))
    fast, slow = Problem(model, app, camera), Problem(model, app, camera, jit=False)
    assert fast.jit and not slow.jit
    alpha = np.array([0.3, -0.2, 0.5, 0.1, -0.4, 0.2, 0.0])
    img = render_blobs(model, camera, alpha, pose)
    uv = fast.project(np.r_[alpha, pose.as_vector()])
    # a map that leaves a quarter of the points outside: they must be invalid on both paths
    x0, y0, x1, y1 = roi_of(uv, 12)
    maps = image_maps(img, (x0, y0, (x0 + x1) // 2 + 20, y1), app.sigma, 0)
    rot = rotation_matrix(pose.rotation + 0.01)
    for jacobian in (True, False):
        a = fast.residuals(maps, 0, alpha + 0.05, rot, pose.translation + 0.5, jacobian, 1.07,
                           True)
        b = slow.residuals(maps, 0, alpha + 0.05, rot, pose.translation + 0.5, jacobian, 1.07,
                           True)
        assert 0.3 < a[2] < 0.95 and a[2] == b[2]
        np.testing.assert_allclose(a[0], b[0], rtol=1e-9, atol=1e-9)
        if jacobian:
            assert a[1].shape == b[1].shape == (a[0].size, 7 + 6 + 1)
            np.testing.assert_allclose(a[1], b[1], rtol=1e-9, atol=1e-9 * np.abs(b[1]).max())


def test_compiled_cauchy_weights_match_their_numpy_definition(monkeypatch):
    from articast.core.tracking import fitting, kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(9)
    r, jac = rng.normal(size=80) * 3, rng.normal(size=(80, 6))
    fast = fitting._robust(r, jac, 8, 2.0)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    slow = fitting._robust(r, jac, 8, 2.0)
    assert fast[0] == pytest.approx(slow[0], rel=1e-12)
    np.testing.assert_allclose(fast[1], slow[1], rtol=1e-12)
    np.testing.assert_allclose(fast[2], slow[2], rtol=1e-12)


def test_lazy_maps_smooth_on_demand_what_the_full_blur_gives(trained):
    """Lazy level-0 maps: the kernel smooths only the pixels the samples read, with the same
    Gaussian and border rule as the full blur — same residuals and Jacobian to float32
    precision, a small fraction of the map touched, and dense() completes the rest."""
    from articast.core.appearance.maps import image_pyramid
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    alpha = np.array([0.2, 0.1, -0.3, 0.4, 0.0, -0.2, 0.1])
    img = render_blobs(model, camera, alpha, pose)
    roi = roi_of(prob.project(np.r_[alpha, pose.as_vector()]), 30)
    lazy = image_pyramid(img, roi, app.sigma, (0,), lazy=True)[0]
    full = image_maps(img, roi, app.sigma, 0)
    assert lazy.lazy and not full.lazy and lazy.done.sum() == 0
    rot = rotation_matrix(pose.rotation)
    a = prob.residuals(lazy, 0, alpha, rot, pose.translation, True, 1.0, True)
    b = prob.residuals(full, 0, alpha, rot, pose.translation, True, 1.0, True)
    np.testing.assert_allclose(a[0], b[0], atol=1e-4 * np.abs(b[0]).max())
    np.testing.assert_allclose(a[1], b[1], atol=1e-4 * np.abs(b[1]).max())
    touched = lazy.done.mean()
    assert 0 < touched < 0.2, touched
    np.testing.assert_allclose(lazy.smooth[lazy.done > 0], full.smooth[lazy.done > 0],
                               atol=1e-3)
    np.testing.assert_allclose(lazy.dense(), full.smooth, atol=1e-3)


def test_lazy_maps_in_reused_buffers_are_fresh_maps(trained):
    """image_pyramid(buffers=MapBuffers()) (a tracker's frames, one after the other): the maps
    a call makes in the memory the calls before used (a smaller ROI, a larger, with pixels
    smoothed there already) give the residuals and Jacobian of fresh maps to the last bit,
    and the YCrCb crop is OpenCV's."""
    from articast.core.appearance.maps import MapBuffers, image_pyramid
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    buffers = MapBuffers()
    rot = rotation_matrix(pose.rotation)
    rng = np.random.default_rng(4)
    for margin in (30, 12, 45, 30, 20):
        alpha = rng.normal(0, 0.3, 7)
        img = render_blobs(model, camera, alpha, pose)
        img = np.clip(img.astype(np.int16) + rng.integers(-20, 20, img.shape), 0, 255
                      ).astype(np.uint8)  # (colour noise: every channel's value matters)
        roi = roi_of(prob.project(np.r_[alpha, pose.as_vector()]), margin)
        reused = image_pyramid(img, roi, app.sigma, (0,), lazy=True, buffers=buffers)[0]
        fresh = image_pyramid(img, roi, app.sigma, (0,), lazy=True)[0]
        assert reused.lazy and reused.done.sum() == 0 and reused.rows_done.sum() == 0
        assert np.shares_memory(reused.smooth, buffers._f32)
        np.testing.assert_array_equal(reused.source, fresh.source)
        for a_fit in (alpha, alpha + 0.05):
            a = prob.residuals(reused, 0, a_fit, rot, pose.translation, True, 1.0, True)
            b = prob.residuals(fresh, 0, a_fit, rot, pose.translation, True, 1.0, True)
            np.testing.assert_array_equal(a[0], b[0])
            np.testing.assert_array_equal(a[1], b[1])
        assert reused.done.sum() > 0


def test_the_compiled_fit_information_is_the_numpy_one():
    """kernels.fit_information (a fused fit's epilogue: J^T J less the landmarks' shared
    errors, the image gain marginalised out) equals the numpy steps it replaced to the last
    bit, with the gain and without, and leaves its input as it was."""
    from articast.core.tracking import kernels
    from articast.core.tracking.fitting import _marginal_information

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(6)
    for i in range(200):
        p = 13
        jw = rng.normal(0, 10 ** rng.uniform(-2, 2), (300, p + (i % 2)))
        h = jw.T @ jw
        v = rng.normal(0, 1, (20, p))
        shared = v.T @ v
        wg = float(rng.uniform(100, 3000))
        kept = h.copy()
        got = kernels.fit_information(h, shared, p, wg)
        ref = h.copy()
        ref[:p, :p] -= shared
        ref = _marginal_information(ref, p, wg)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(h, kept)


def test_the_compiled_kernels_are_what_the_product_runs():
    """numba is a dependency: unless disabled on purpose, the kernels must import — or the
    parity tests above would skip silently and the tracker run 2-3x slower."""
    import os

    from articast.core.tracking import kernels

    if os.environ.get("ARTICAST_JIT") == "0":
        pytest.skip("disabled by ARTICAST_JIT=0")
    assert kernels.AVAILABLE


@pytest.fixture(scope="module")
def rotation_trained():
    """The blob face, la quad with rotation terms (a desk camera's model), trained on turned
    heads."""
    from articast.core.appearance.models import TrainingFrame, train_appearance
    from tests.blobface import blob_setup

    model, camera, pose = blob_setup()
    rng = np.random.default_rng(3)
    frames = []
    for _ in range(30):
        a = rng.normal(size=7) * 0.8
        p = Pose(pose.rotation + rng.normal(size=3) * 0.04, pose.translation + rng.normal(size=3) * 3)
        frames.append(TrainingFrame(render_blobs(model, camera, a, p), a, p))
    app = train_appearance(model, camera, frames, "la_quad", sigma=2.0, levels=(0, 1),
                           per_param=6, rotation_terms=True)
    assert app.rotation_weights is not None
    return model, camera, pose, app


@pytest.mark.parametrize("case", ["fused", "plain", "least_squares"])
def test_the_compiled_evaluation_fits_as_the_numpy_assembly(rotation_trained, monkeypatch,
                                                            case):
    """fit_gauss_newton evaluates each state in one compiled call (kernels.gn_terms: la cost
    with rotation terms, Cauchy weights, landmark term with its shared errors, priors) and
    runs each Levenberg-Marquardt iteration in another (kernels.lm_step) where it can; the
    numpy assembly and loop are the definition. Same fit to re-ordering precision: fused
    live tracking (the landmarks with shared error modes, a state prior, the gain, on lazy
    maps), the plain tracker's fit (pose and motion priors, full maps) and least squares."""
    from articast.core.appearance.maps import image_pyramid
    from articast.core.tracking import fitting, kernels
    from articast.core.tracking.fitting import StatePrior
    from articast.core.tracking.points import PointModel, PointTerm

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = rotation_trained
    rng = np.random.default_rng(11)
    truth = rng.normal(size=7) * 0.6
    turned = Pose(pose.rotation + [0.03, -0.02, 0.01], pose.translation + [2.0, -1.0, 4.0])
    img = render_blobs(model, camera, truth, turned)
    prob = Problem(model, app, camera)
    k = model.n_params
    roi = roi_of(prob.project(np.r_[truth, turned.as_vector()]), 30)
    m = model.mean.shape[0]
    pm = PointModel("v1", np.arange(m), model.mean, model.basis, rng.uniform(0.5, 1.5, m),
                    rng.normal(0, 0.5, (3, m, 2)))
    cam_pts = model.shape(truth) @ turned.matrix.T + turned.translation
    uv = camera.project(cam_pts) + rng.normal(0, 1.0, (m, 2))
    uv[[3, 7]] = np.nan  # points not read
    # (writable arrays, as the tracker's: a Pose's read-only ones are another type to numba)
    start = (truth + rng.normal(size=7) * 0.3, pose.rotation.copy(), pose.translation.copy())
    kw: dict = {}
    if case == "fused":
        info = np.diag(np.r_[np.full(k, 2.0), np.full(3, 1e3), np.full(3, 0.5)])
        kw = dict(points=PointTerm(pm, camera, uv, float(turned.translation[2]), 3.0, 0.3),
                  state_prior=StatePrior(start[0], rotation_matrix(start[1]), start[2], info),
                  appearance_weight=0.7, estimate_gain=True, gain0=1.05)
        pol = FitPolicy(max_iterations=4, max_rejections=2)
    else:
        kw = dict(pose_ref=(start[1], start[2]), alpha_ref=start[0])
        pol = FitPolicy(max_iterations=6, pose_sigma_rad=0.003, pose_sigma_mm=0.5,
                        alpha_sigma=0.5, robust_scale=None if case == "least_squares" else 2.0)
    calls = []
    kernels.warm_up()
    first, step = kernels.gn_terms, kernels.lm_step
    compiled_types = [set(f.signatures) for f in (first, step)]

    def counted_first(*args):
        calls.append(1)
        return first(*args)

    def counted_step(*args):
        out = step(*args)
        calls.append(out[2])  # its evaluations
        return out

    monkeypatch.setattr(kernels, "gn_terms", counted_first)
    monkeypatch.setattr(kernels, "lm_step", counted_step)
    fits = []
    for on in (True, False):
        monkeypatch.setattr(fitting, "FIT_TERMS", on)
        maps = image_pyramid(img, roi, app.sigma, (0,), lazy=case == "fused")[0]
        fits.append(fit_gauss_newton(prob, maps, 0, *start, pol, **kw))
    assert sum(calls) == fits[0].evals > 2  # the compiled path ran, every evaluation
    # kernels.warm_up() compiled it for the types a fit passes (no compilation on a first frame)
    assert [set(f.signatures) for f in (first, step)] == compiled_types
    fast, ref = fits
    assert (fast.evals, fast.iterations, fast.converged) == (ref.evals, ref.iterations,
                                                            ref.converged)
    for name in ("alpha", "rotation", "translation", "cost", "residual", "gain",
                 "robust_residual", "valid_fraction", "point_q", "costs", "information"):
        a, b = getattr(fast, name), getattr(ref, name)
        if b is None:
            assert a is None, name
            continue
        b = np.asarray(b, float)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * max(np.abs(b).max(), 1.0),
                                   err_msg=name)
    assert np.abs(fast.alpha - start[0]).max() > 0.05  # the fit moved: a real comparison


def test_lazy_smoothing_sums_each_pixel_as_the_separable_definition():
    """kernels._smooth_pixel, _smooth_column and _smooth_cell (the lazy maps' blur: one
    pixel, up to four of a column with their passes side by side, or a sample's 12) are
    exactly the separable Gaussian with OpenCV's reflect-101 border: each row pass summed
    tap by tap in float64 and kept in float32, then the column pass the same way -- bit for
    bit, inside and at every border, whichever pixel asks first (the row passes kept
    column-major: rows (w, h, 3))."""
    import cv2

    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(4)
    h, w = 23, 31
    src = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    taps = cv2.getGaussianKernel(17, 2.5).ravel()
    rad = len(taps) // 2

    def reflect(i, n):
        i = -i if i < 0 else i
        return 2 * n - 2 - i if i >= n else i

    def row_pass(yy, x):
        acc = np.zeros(3)
        for i in range(-rad, rad + 1):
            acc += taps[i + rad] * src[yy, reflect(x + i, w)].astype(np.float64)
        return acc.astype(np.float32)

    def want(y, x):
        acc = np.zeros(3)
        for j in range(-rad, rad + 1):
            acc += taps[j + rad] * row_pass(reflect(y + j, h), x).astype(np.float64)
        return acc.astype(np.float32)

    sm, rows = np.zeros((h, w, 3), np.float32), np.zeros((w, h, 3), np.float32)
    done, rdone = np.zeros((h, w), np.uint8), np.zeros((w, h), np.uint8)
    pixels = [(0, 0), (h - 1, w - 1), (11, 15), (12, 15), (3, 29), (20, 1)]
    pixels += [tuple(p) for p in rng.integers(0, [h, w], (30, 2))]
    for y, x in pixels:
        kernels._smooth_pixel(src, sm, done, rows, rdone, taps, y, x)
        assert done[y, x] == 1
        np.testing.assert_array_equal(sm[y, x], want(y, x))
    # columns of 1-4 pixels, some already done, at the borders and inside
    need = np.empty(len(taps) + 3, np.int64)
    for x, y0, y1 in [(0, 0, 3), (w - 1, h - 4, h - 1), (15, 10, 13), (15, 9, 14), (7, 2, 3),
                      (29, 20, 22), (16, 11, 11)]:
        for y in range(y0, y1 + 1, 4):
            kernels._smooth_column(src, sm, done, rows, rdone, taps, x, y, min(y + 3, y1),
                                   need)
        for y in range(y0, y1 + 1):
            assert done[y, x] == 1
            np.testing.assert_array_equal(sm[y, x], want(y, x))
    assert done.sum() > 40
    # a sample's cell (its 12 pixels; inside, the four columns' row passes side by side),
    # on fresh buffers and on buffers some cells filled already, inside and at the borders
    sm, rows = np.zeros((h, w, 3), np.float32), np.zeros((w, h, 3), np.float32)
    done, rdone = np.zeros((h, w), np.uint8), np.zeros((w, h), np.uint8)
    for ix, iy in [(12, 10), (13, 11), (9, 1), (20, h - 3), (1, 5), (w - 3, 12), (15, 2)]:
        kernels._smooth_cell(src, sm, done, rows, rdone, taps, ix, iy, need)
        for x, y in ([(ix - 1, iy), (ix - 1, iy + 1), (ix + 2, iy), (ix + 2, iy + 1)]
                     + [(x, y) for x in (ix, ix + 1) for y in range(iy - 1, iy + 3)]):
            assert done[y, x] == 1
            np.testing.assert_array_equal(sm[y, x], want(y, x))
    for x, yy in zip(*np.nonzero(rdone), strict=True):
        np.testing.assert_array_equal(rows[x, yy], row_pass(yy, x))


def test_fit_to_landmarks_is_levenberg_marquardt_with_every_step_recomputed():
    """The start's fit (faces.fit.fit_to_landmarks) keeps a rejected step's normal equations
    (the state, hence they, did not move: only the damping grows) instead of forming them
    again: the same state bit for bit as the plain loop that recomputes them every
    iteration, here with several rejected steps and the state moved by the fit."""
    from articast.core.faces.fit import (
        fit_to_landmarks,
        landmark_cost,
        landmark_normal_equations,
        landmark_step,
    )
    from articast.core.model.camera import Camera, axis_angle
    from articast.core.synthetic import default_speaker

    model = default_speaker(0).model()
    camera = Camera.default()
    rng = np.random.default_rng(3)
    k = model.n_params
    true_alpha = rng.normal(0.0, 0.8, k)
    truth = Pose(np.array([0.1, -0.2, 0.05]), np.array([5.0, -8.0, 420.0]))
    uv = camera.project(model.shape(true_alpha) @ truth.matrix.T + truth.translation)
    uv = uv + rng.normal(0.0, 1.5, uv.shape)
    alpha0 = true_alpha + rng.normal(0.0, 0.5, k)
    pose0 = Pose(truth.rotation + 0.03, truth.translation + [4.0, -3.0, 15.0])

    def plain(iterations=10, sigma_px=2.0, alpha_sd=1.5):  # the former loop: every
        # iteration forms the normal equations afresh (the same two steps it is made of)
        a = np.array(alpha0, np.float64)
        rot = rotation_matrix(pose0.rotation)
        tr = np.array(pose0.translation, np.float64)
        w_prior = (sigma_px / alpha_sd) ** 2
        live = np.ptp(model.basis.reshape(k, -1), axis=1) > 0
        lam = 1e-3
        cost, r, jac, pc = landmark_cost(model, camera, uv, w_prior, a, rot, tr)
        rejected = 0
        for _ in range(iterations):
            h, g = landmark_normal_equations(model, rot, tr, a, live, w_prior, r, jac, pc)
            a_new, rot_new, t_new = landmark_step(h, g, lam, live, a, rot, tr)
            c_new, r_new, jac_new, pc_new = landmark_cost(model, camera, uv, w_prior, a_new,
                                                          rot_new, t_new)
            if np.isfinite(c_new) and c_new < cost:
                a, rot, tr, cost, r, jac, pc = a_new, rot_new, t_new, c_new, r_new, jac_new, pc_new
                lam = max(lam / 10, 1e-7)
            else:
                lam *= 10
                rejected += 1
        return a, Pose(axis_angle(rot), tr), rejected

    want_alpha, want_pose, rejected = plain()
    alpha, pose = fit_to_landmarks(model, camera, uv, alpha0, pose0)
    assert rejected >= 2  # the kept equations were used
    assert np.abs(want_alpha - alpha0).max() > 0.1  # and the fit moved
    np.testing.assert_array_equal(alpha, want_alpha)
    np.testing.assert_array_equal(pose.rotation, want_pose.rotation)
    np.testing.assert_array_equal(pose.translation, want_pose.translation)


def test_the_compiled_projection_and_box_are_the_numpy_ones(trained):
    """Problem.project (kernels.sample_uv) and roi_of (kernels.roi_box), once a tracked
    frame each, give their numpy references' numbers: the projection to the last bit on
    this machine (the same BLAS products; another CPU's BLAS may sum in another order), the
    box exactly (points behind the camera or not finite left out, none: an empty box)."""
    from articast.core.appearance.maps import roi_of_numpy
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = trained
    prob = Problem(model, app, camera)
    rng = np.random.default_rng(5)
    for _ in range(20):
        theta = np.r_[rng.normal(size=model.n_params), pose.rotation + rng.normal(0, 0.1, 3),
                      pose.translation + rng.normal(0, 5.0, 3)]
        uv = prob.project(theta)
        ref = prob.project_numpy(theta)
        np.testing.assert_allclose(uv, ref, rtol=1e-13, atol=1e-10)
        for margin in (0.0, 24.0, 3.7):
            assert roi_of(uv, margin) == roi_of_numpy(uv, margin)
    behind = np.r_[np.zeros(model.n_params), pose.rotation, 0.0, 0.0, -50.0]
    assert np.isnan(prob.project(behind)).all() and np.isnan(prob.project_numpy(behind)).all()
    uv = rng.uniform(-50, 700, (30, 2))
    uv[[2, 9]] = np.nan
    uv[4, 0] = np.inf
    assert roi_of(uv, 5.5) == roi_of_numpy(uv, 5.5)
    assert roi_of(uv[[2, 9]], 5.0) == roi_of_numpy(uv[[2, 9]], 5.0) == (0, 0, 0, 0)

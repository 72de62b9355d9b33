"""The pieces of fused live tracking on constructed data where the answer is known: the
landmark observation model and its term (with the errors the points share), the motion model,
and the three-cornered hat that weighs the evidence."""

import numpy as np
import pytest

from articast.core.errors import ModelFileError
from articast.core.model.camera import FRONTAL, Camera, Pose, rotation_matrix
from articast.core.tracking.fitting import FitPolicy, StatePrior, fit_gauss_newton
from articast.core.tracking.kalman import ConstantVelocity, MotionNoise, process_noise
from articast.core.tracking.points import (
    PointModel,
    PointTerm,
    learn_point_model,
    learn_reading_regression,
    offset_fraction,
)
from tests.blobface import blob_trained

CAM = Camera.default(640, 480, 60.0)


def _points(rng, m=60, k=4):
    mean = np.column_stack([rng.uniform(-40, 40, m), rng.uniform(-50, 30, m),
                            rng.uniform(-10, 20, m)])
    return mean, rng.normal(0, 3.0, (k, m, 3))


def test_compiled_landmark_term_matches_the_numpy_reference():
    rng = np.random.default_rng(0)
    mean, basis = _points(rng, 80, 7)
    pm = PointModel("v1", np.arange(80), mean, basis, rng.uniform(0.3, 1.0, 80))
    uv = rng.uniform(100, 500, (80, 2))
    uv[5] = np.nan
    term = PointTerm(pm, CAM, uv, 500.0)
    a = rng.normal(0, 1, 7)
    rot = rotation_matrix(FRONTAL + rng.normal(0, 0.1, 3))
    t = np.array([5.0, -3.0, 500.0])
    r1, j1 = term.residuals(a, rot, t, True)
    r2, j2 = term.residuals_numpy(a, rot, t, True)
    assert term.n_points == 79 and r1.shape == (158,)
    np.testing.assert_allclose(r1, r2, atol=1e-9)
    np.testing.assert_allclose(j1, j2, atol=1e-9 * np.abs(j2).max())
    # and the Jacobian is the residuals' derivative
    eps = 1e-6
    for j in (0, 7, 9, 11):
        d = np.zeros(13)
        d[j] = eps
        def at(x):
            return term.residuals_numpy(a + x[:7], rotation_matrix(x[7:10]) @ rot, t + x[10:],
                                        False)[0]
        num = (at(d) - at(-d)) / (2 * eps)
        assert np.abs(j2[:, j] - num).max() < 1e-4 * (np.abs(num).max() + 1e-9), j


def _face_model(rng, m=60, k=4):
    from articast.core.model.face import FaceModel, ParamStats

    mean, basis = _points(rng, m, k)
    stats = ParamStats(np.zeros(k), np.ones(k), np.full(k, -3.0), np.full(k, 3.0))
    return FaceModel(mean=mean, basis=basis, param_names=tuple(f"p{i}" for i in range(k)),
                     stats=stats, point_names=tuple(f"n{i}" for i in range(m)), groups={},
                     triangles=np.zeros((0, 3), np.int64), feature_points={},
                     fapu_overrides={}, name="test")


def _readings(model, states, offset, dbasis, shared, own_sd, rng, camera=CAM):
    """What a network with a known observation model reads: the model's points moved by a
    fixed offset and an articulation-dependent change, plus errors shared by all points (a
    random multiple of ``shared`` (M, 2) mm) and each point's own."""
    out = []
    for alpha, pose in states:
        pts = model.shape(alpha) + offset + np.tensordot(alpha, dbasis, axes=1)
        cam = pts @ pose.matrix.T + pose.translation
        uv = camera.project(cam)
        mm = rng.normal() * shared + rng.normal(0, own_sd, shared.shape)
        out.append(uv + mm * camera.fx / cam[:, 2:3])
    return np.array(out)


def _states(rng, n, k):
    return [(rng.normal(0, 1, k), Pose(FRONTAL + rng.normal(0, 0.05, 3),
                                       np.array([0, 0, 450.0]) + rng.normal(0, 10, 3)))
            for _ in range(n)]


def test_the_observation_model_is_learned_from_readings():
    rng = np.random.default_rng(1)
    model = _face_model(rng)
    m, k = model.mean.shape[0], model.n_params
    offset = rng.normal(0, 1.0, (m, 3)) * [1, 1, 0]
    dbasis = rng.normal(0, 0.8, (k, m, 3)) * [1, 1, 0]
    shared = np.tile([0.0, 1.5], (m, 1))  # the whole face read 1.5 mm low or high at once
    states = _states(rng, 400, k)
    reads = _readings(model, states, offset, dbasis, shared, 0.3, rng)
    pm = learn_point_model(model, CAM, states, reads, np.arange(m), np.arange(m), "v1",
                           ridge=1e-3)
    # a point's prediction moves like the network's reading, not like the model's point
    a = np.array([1.0, -1.0, 0.5, 0.0])
    want = model.shape(a) + offset + np.tensordot(a, dbasis, axes=1)
    assert np.abs(pm.points(a) - want)[:, :2].max() < 0.4
    assert np.abs(model.shape(a) - want)[:, :2].max() > 1.0  # (the model's own are not)
    # each point's own error, and the shared one as the first mode (in units of sigma)
    assert np.median(pm.sigma_mm) == pytest.approx(0.3, rel=0.25)
    first = pm.modes[0] * pm.sigma_mm[:, None]
    assert np.abs(np.abs(first[:, 1]).mean() - 1.5) < 0.3
    assert np.abs(first[:, 0]).mean() < 0.3


def test_shared_errors_count_once_in_the_fit(tmp_path):
    """A reading whose points are all off by the same shared error: the fit that knows the
    errors are shared moves the articulation less than the fit that takes them as
    independent."""
    rng = np.random.default_rng(2)
    model, camera, pose, app = blob_trained(seed=5)
    k = model.n_params
    m = model.mean.shape[0]
    shared = rng.normal(0, 1.0, (m, 2))  # one pattern of error, of a random size per frame
    states = _states(rng, 300, k)
    states = [(a * 0.5, Pose(pose.rotation + (p.rotation - FRONTAL), pose.translation
                             + p.translation - [0, 0, 450])) for a, p in states]
    reads = _readings(model, states, 0.0, np.zeros((k, m, 3)), shared, 0.2, rng, camera)
    pm = learn_point_model(model, camera, states, reads, np.arange(m), np.arange(m), "v1")
    independent = PointModel("v1", pm.landmarks, pm.mean, pm.basis, pm.sigma_mm)
    pm.save(tmp_path / "points.npz")
    assert np.allclose(PointModel.load(tmp_path / "points.npz", k).modes, pm.modes)
    alpha = np.zeros(k)
    cam_pts = model.shape(alpha) @ pose.matrix.T + pose.translation
    uv = camera.project(cam_pts) + 2.0 * shared * camera.fx / cam_pts[:, 2:3]
    moved = {}
    for name, obs in (("shared", pm), ("independent", independent)):
        term = PointTerm(obs, camera, uv, float(pose.translation[2]), None)
        prior = StatePrior(alpha, pose.matrix, pose.translation,
                           np.diag(np.r_[np.full(k, 1.0), np.full(3, 1e4), np.full(3, 1.0)]))
        fit = fit_gauss_newton(_problem(model, app, camera), None, 0, alpha, pose.rotation,
                               pose.translation, FitPolicy(max_iterations=10), points=term,
                               state_prior=prior, appearance_weight=0.0)
        moved[name] = float(np.abs(fit.alpha).max())
    assert moved["shared"] < 0.5 * moved["independent"]


def _problem(model, app, camera):
    from articast.core.tracking.fitting import Problem

    return Problem(model, app, camera)


def test_the_offset_of_a_reading_is_a_fraction_of_the_face_size():
    rng = np.random.default_rng(4)
    pred = rng.uniform(100, 300, (50, 2))
    size = np.sqrt(np.mean(np.sum((pred - pred.mean(0)) ** 2, 1)))
    moved = pred + [0.05 * size, 0.0]
    assert offset_fraction(pred, moved) == pytest.approx(0.05)
    # the median: a few points read far away (a hand, a wrong contour) do not move it
    moved[:10] += 500.0
    moved[10] = np.nan
    assert offset_fraction(pred, moved) == pytest.approx(0.05)
    assert np.isnan(offset_fraction(pred, np.full_like(pred, np.nan)))


def test_the_enrolment_keeps_how_far_its_readings_were(tmp_path):
    """The observation model records the 99th percentile of its readings' offsets at the
    enrolled states (what ``ok`` is judged against live), and keeps it on disk; a file saved
    before it existed reads as unknown."""
    rng = np.random.default_rng(5)
    model = _face_model(rng)
    m, k = model.mean.shape[0], model.n_params
    states = _states(rng, 200, k)
    reads = _readings(model, states, 0.0, np.zeros((k, m, 3)), np.zeros((m, 2)), 0.5, rng)
    pm = learn_point_model(model, CAM, states, reads, np.arange(m), np.arange(m), "v1")
    noisier = learn_point_model(model, CAM, states, _readings(
        model, states, 0.0, np.zeros((k, m, 3)), np.zeros((m, 2)), 2.0, rng),
        np.arange(m), np.arange(m), "v1")
    assert 0.0 < pm.offset_p99 < noisier.offset_p99
    assert noisier.offset_p99 == pytest.approx(4 * pm.offset_p99, rel=0.3)
    pm.save(tmp_path / "p.npz")
    assert PointModel.load(tmp_path / "p.npz").offset_p99 == pytest.approx(pm.offset_p99)
    from dataclasses import replace

    replace(pm, offset_p99=float("nan")).save(tmp_path / "old.npz")
    assert np.isnan(PointModel.load(tmp_path / "old.npz").offset_p99)


def test_observation_model_files_are_checked(tmp_path):
    rng = np.random.default_rng(3)
    mean, basis = _points(rng, 10, 3)
    pm = PointModel("v1", np.arange(10), mean, basis, np.ones(10))
    pm.save(tmp_path / "p.npz")
    with pytest.raises(ModelFileError, match="3 parameters"):
        PointModel.load(tmp_path / "p.npz", 7)
    with pytest.raises(ModelFileError):
        PointModel("v1", np.arange(10), mean, basis, np.zeros(10))


def _ramp(n, dt, speed, noise, rng):
    t = np.arange(n) * dt
    return t, speed * t, speed * t + rng.normal(0, noise, n)


def test_the_motion_model_smooths_without_lagging_a_steady_motion():
    """A state moving at constant speed, measured with noise: the filtered state is closer to
    the truth than the measurements, and not behind it (a smoother would be)."""
    rng = np.random.default_rng(4)
    k = 1
    kf = ConstantVelocity(k, MotionNoise(np.r_[np.full(k, 5.0), np.full(6, 1.0)],
                                         np.ones(k + 6)))
    dt, noise = 0.04, 0.1
    _, truth, meas = _ramp(400, dt, 2.0, noise, rng)
    info = np.diag(np.r_[1.0 / noise**2, np.full(6, 1e6)])
    kf.start(meas[:1], FRONTAL, np.zeros(3), info)
    out = [meas[0]]
    for z in meas[1:]:
        prior = kf.predict(dt)
        # the fit: the prior and one measurement of alpha -> the posterior mean
        lam = prior.information[0, 0]
        a = (lam * prior.alpha[0] + z / noise**2) / (lam + 1.0 / noise**2)
        kf.update(np.array([a]), FRONTAL, np.zeros(3), info)
        out.append(a)
    err = np.array(out)[100:] - truth[100:]
    assert np.sqrt(np.mean(err**2)) < 0.7 * noise  # the measurements: 1.0 x noise
    assert abs(err.mean()) < 0.02 * noise * 10  # not behind: a lag of one frame is 0.08


def test_process_noise_separates_motion_from_measurement_noise():
    rng = np.random.default_rng(5)
    dt, q, sd, n = 0.04, 50.0, 0.05, 3000
    acc = rng.normal(0, np.sqrt(q / dt), n)
    vel = np.cumsum(acc) * dt
    x = np.cumsum(vel) * dt
    alpha = (x + rng.normal(0, sd, n))[:, None]
    zeros = np.zeros((n, 3))
    times = np.arange(n) * dt
    mn = process_noise(alpha, zeros + FRONTAL, zeros, times)
    assert 0.5 * q < mn.q[0] < 2.0 * q  # not the measurement noise's ~6 sd^2 / (2/3 dt^3)
    # gaps are allowed (the equally spaced triples are used); a sparse clip keeps the defaults
    keep = np.ones(n, bool)
    keep[::7] = False
    assert 0.5 * q < process_noise(alpha[keep], (zeros + FRONTAL)[keep], zeros[keep],
                                   times[keep]).q[0] < 2.0 * q
    assert process_noise(alpha[::3], zeros[::3] + FRONTAL, zeros[::3], times[::3]).q[0] == \
        MotionNoise.default(1).q[0]


def test_the_motion_models_prediction_covariance_is_f_p_ft_plus_q():
    """The block-wise prediction equals the textbook one: F P F^T + Q, F = [[I, dt I], [0, I]],
    Q of white-noise acceleration (dt^3/3, dt^2/2, dt per unit of q)."""
    from articast.core.tracking.kalman import ConstantVelocity

    rng = np.random.default_rng(0)
    k, dt = 7, 0.04
    n = k + 6
    cv = ConstantVelocity(k)
    cv.start(rng.normal(size=k), 0.1 * rng.normal(size=3), rng.normal(size=3))
    a = rng.normal(size=(2 * n, 2 * n))
    cv.p = a @ a.T
    p0 = cv.p.copy()
    prior = cv.predict(dt)
    f = np.eye(2 * n)
    f[:n, n:] = dt * np.eye(n)
    q, i = cv.noise.q, np.arange(n)
    qm = np.zeros((2 * n, 2 * n))
    qm[i, i] = q * dt**3 / 3
    qm[i, n + i] = qm[n + i, i] = q * dt**2 / 2
    qm[n + i, n + i] = q * dt
    want = f @ p0 @ f.T + qm
    np.testing.assert_allclose(cv._pred[3], want, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(prior.information @ want[:n, :n], np.eye(n), atol=1e-6)


def _correlated_prior(rng, k=7, alpha_sd=2.0):
    """A prediction whose articulation and pose are correlated, with the pose's own scales
    (0.02 rad, 5 mm: small turns stay small), and its information."""
    n = k + 6
    a = rng.normal(size=(n, n))
    d = np.sqrt(np.r_[np.ones(k), np.full(3, 0.02**-2), np.full(3, 5.0**-2)])
    info = d[:, None] * (a @ a.T / n + 0.5 * np.eye(n)) * d[None, :]
    return StatePrior(rng.normal(size=k) * alpha_sd,
                      rotation_matrix(np.array([0.05, -0.1, 0.02])),
                      np.array([3.0, -2.0, 600.0]), info), info


def test_the_speakers_prior_is_the_product_of_the_two_gaussians():
    # the combined prior's cost must equal the prediction's plus w |alpha|^2 up to a
    # constant, at any state: compare the gradients (zero at the combined mean, equal
    # elsewhere), with the pose correlated to alpha so that it moves too
    rng = np.random.default_rng(3)
    k = 7
    pred, info = _correlated_prior(rng)
    for w in (1.0, 0.3):
        both = pred.with_speaker(w)

        def grad_sum(alpha, rot, t, w=w):
            return pred.terms(alpha, rot, t)[1] + np.r_[2.0 * w * alpha, np.zeros(6)]

        g = grad_sum(both.alpha, both.rotation, both.translation)
        # zero, to the small-turn approximation of the rotation (second order in its 0.02 rad)
        assert np.abs(g[:k]).max() < 1e-3 and np.abs(g[k + 3:]).max() < 1e-3
        assert np.abs(g[k:k + 3]).max() < 1e-2 * np.sqrt(info[k, k])
        # its mean is pulled towards the speaker's mean, not past it
        assert np.linalg.norm(both.alpha) < np.linalg.norm(pred.alpha)
        assert not np.allclose(both.translation, pred.translation)  # correlated: moves too
        # and its information is the sum (the Hessians of the two costs)
        assert np.allclose(both.information[:k, :k] - info[:k, :k], w * np.eye(k))
        x = (rng.normal(size=k), rotation_matrix(rng.normal(size=3) * 0.02) @ pred.rotation,
             pred.translation + rng.normal(size=3))
        gx = grad_sum(*x)
        diff = np.abs(both.terms(*x)[1] - gx)
        assert np.delete(diff, np.s_[k:k + 3]).max() < 1e-2 * np.abs(gx).max()
    # weight 0: the prediction itself
    same = pred.with_speaker(0.0)
    assert np.allclose(same.alpha, pred.alpha) and np.allclose(same.rotation, pred.rotation)


def test_the_compiled_offset_of_a_state_is_the_numpy_one():
    """state_offset (the live tracker's gate, re-read and agreement tests) runs a compiled
    kernel on a camera without distortion; the numpy reference is the definition: same
    fraction, with points not read (NaN rows) and at a turned head."""
    from articast.core.tracking import kernels
    from articast.core.tracking.points import state_offset, state_offset_numpy

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(6)
    mean, basis = _points(rng, 90, 7)
    pm = PointModel("v1", np.arange(90), mean, basis, rng.uniform(0.3, 1.0, 90))
    values = []
    for trial in range(5):
        a = rng.normal(0, 1, 7)
        rot = rotation_matrix(FRONTAL + rng.normal(0, 0.2, 3))
        t = np.array([rng.normal(0, 20), rng.normal(0, 20), rng.uniform(300, 700)])
        seen = CAM.project((mean + np.tensordot(a, basis, 1)) @ rot.T + t)
        seen = seen + rng.normal(0, 1.0 + 3 * trial, seen.shape)
        seen[rng.choice(90, 7, replace=False)] = np.nan
        fast = state_offset(pm, CAM, a, rot, t, seen)
        ref = state_offset_numpy(pm, CAM, a, rot, t, seen)
        assert fast == pytest.approx(ref, rel=1e-12)
        values.append(ref)
    assert len(set(np.round(values, 6))) == 5 and all(0 < v < 1 for v in values)
    nothing = np.full((90, 2), np.nan)
    assert np.isnan(state_offset(pm, CAM, a, rot, t, nothing))
    assert np.isnan(state_offset_numpy(pm, CAM, a, rot, t, nothing))


@pytest.mark.parametrize("told", [True, False])
def test_the_compiled_motion_model_steps_are_the_numpy_ones(monkeypatch, told):
    """ConstantVelocity.predict and update run one compiled call each (kernels.cv_predict,
    cv_update); their numpy code is the reference: the same prior, covariance and velocity
    over a few steps, with the frame's information and without (None: the prediction's
    covariance is kept)."""
    from articast.core.tracking import kernels
    from articast.core.tracking.kalman import ConstantVelocity

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    k = 7
    n = k + 6
    runs = []
    for compiled in (True, False):
        monkeypatch.setattr(kernels, "AVAILABLE", compiled)
        r = np.random.default_rng(3)
        cv = ConstantVelocity(k)
        cv.start(r.normal(size=k), FRONTAL + 0.1 * r.normal(size=3), r.normal(size=3))
        a = r.normal(size=(2 * n, 2 * n))
        cv.p = a @ a.T / n
        out = []
        for step in range(4):
            prior = cv.predict(0.04 + 0.01 * step)
            x = r.normal(size=(3 * n, n))
            info = x.T @ x if told else None
            cv.update(prior.alpha + 0.1 * r.normal(size=k),
                      FRONTAL + 0.01 * r.normal(size=3),
                      prior.translation + r.normal(size=3), info)
            out.append((prior.information, prior.alpha, prior.rotation, prior.translation,
                        cv.p.copy(), cv.v.copy()))
        runs.append(out)
    fast, ref = runs
    for got, want in zip(fast, ref, strict=True):
        for x, y in zip(got, want, strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9 * np.abs(y).max())
    assert np.abs(ref[-1][5]).max() > 1e-3  # the velocity moved: a real comparison



def test_the_prediction_s_speaker_prior_is_with_speaker_s():
    """ConstantVelocity(speaker=w) makes the speaker's prior in predict's compiled call
    (kernels.cv_predict): with_speaker(w) returns it, the very numbers of with_speaker's own
    compiled call on the same prediction (and the numpy reference's to 1e-9); another weight
    is worked out as before."""
    from dataclasses import replace

    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    k, n = 7, 13
    r = np.random.default_rng(5)
    cv = ConstantVelocity(k, speaker=0.7)
    cv.start(r.normal(size=k), FRONTAL + 0.1 * r.normal(size=3), r.normal(size=3))
    a = r.normal(size=(2 * n, 2 * n))
    cv.p = a @ a.T / n
    cv.v = r.normal(size=n)
    for step in range(3):
        prior = cv.predict(0.04 + 0.01 * step)
        assert prior.speaker is not None
        got = prior.with_speaker(0.7)
        bare = replace(prior)  # (a prior made otherwise: without it)
        assert bare.speaker is None
        own = bare.with_speaker(0.7)
        ref = bare.with_measurement_numpy(np.zeros(k), 0.7 * np.eye(k))
        for name in ("alpha", "rotation", "translation", "information"):
            x, y, z = getattr(got, name), getattr(own, name), getattr(ref, name)
            assert x.tobytes() == y.tobytes(), name
            np.testing.assert_allclose(x, z, rtol=1e-9, atol=1e-9 * np.abs(z).max())
        assert np.abs(got.alpha - prior.alpha).max() > 1e-3  # the speaker's prior moved it
        other = prior.with_speaker(2.0)  # not the one made: worked out
        assert other.alpha.tobytes() == bare.with_speaker(2.0).alpha.tobytes()
        cv.update(prior.alpha, FRONTAL + 0.01 * r.normal(size=3), prior.translation, None)
    plain = ConstantVelocity(k)
    plain.start(np.zeros(k), FRONTAL, np.zeros(3))
    assert plain.predict(0.04).speaker is None

def _regression_case(seed=7, n=300, own_sd=3.0):
    """A network that reads the articulation its own way (offsets, an articulation-dependent
    change of its points) with errors shared by all its points; its observation model and
    reading regression learned from ``n`` enrolment frames; and 200 new frames it reads."""
    rng = np.random.default_rng(seed)
    model = _face_model(rng)
    m, k = model.mean.shape[0], model.n_params
    offset = rng.normal(0, 1.0, (m, 3)) * [1, 1, 0]
    dbasis = rng.normal(0, 0.8, (k, m, 3)) * [1, 1, 0]
    shared = np.tile([0.0, 1.0], (m, 1))
    states = _states(rng, n, k)
    reads = _readings(model, states, offset, dbasis, shared, own_sd, rng)
    pm = learn_point_model(model, CAM, states, reads, np.arange(m), np.arange(m), "v1")
    reg = learn_reading_regression(pm.mean, CAM, [p for _, p in states],
                                   np.array([a for a, _ in states]), reads, np.arange(n) / 25.0)
    test = _states(rng, 200, k)
    return pm, reg, test, _readings(model, test, offset, dbasis, shared, own_sd, rng)


def test_the_articulation_is_read_off_a_reading_and_says_how_sure_it_is():
    """The enrolment's regression reads the articulation of new readings, and the error it
    expects (its information, from a cross-validation in time at enrolment, each half
    learned from the other: a little more than the whole's) is about the error it makes,
    never much less."""
    pm, reg, test, reads = _regression_case()
    assert reg is not None and reg.weights.shape == (2 * len(pm.mean), 4)
    got = np.array([reg.alpha(reg.features(pm.mean, CAM, uv, p.matrix, p.translation))
                    for (_, p), uv in zip(test, reads, strict=True)])
    err = got - np.array([a for a, _ in test])
    assert np.sqrt((err ** 2).mean()) < 0.3  # of the articulation's 1 s.d.
    assert np.allclose(reg.information, reg.information.T)
    mahalanobis = float(np.einsum("fi,ij,fj->f", err, reg.information, err).mean()) / 4
    assert 0.25 < mahalanobis < 1.2
    # noisier readings: a larger error, and it says so
    _, noisy, _, _ = _regression_case(own_sd=9.0)
    assert noisy is not None
    assert np.trace(np.linalg.inv(noisy.information)) > 2 * np.trace(
        np.linalg.inv(reg.information))
    # too few frames to learn it: none
    assert _regression_case(n=12)[1] is None


def _raw_offsets(mean, uv, rot, t):
    cam = mean @ rot.T + t
    pred = CAM.project(cam)
    d = np.zeros((len(mean), 3))
    d[:, 0] = (uv[:, 0] - pred[:, 0]) * cam[:, 2] / CAM.fx
    d[:, 1] = (uv[:, 1] - pred[:, 1]) * cam[:, 2] / CAM.fy
    return (d @ rot)[:, :2].reshape(-1)


def test_a_small_error_of_the_predicted_pose_is_not_read_as_articulation():
    """Live, the reading is placed at the motion model's predicted pose: a pose ~0.7 degrees
    and 1-3 mm off moves every point's offset alike, which the features leave out (to first
    order), so the articulation read barely moves."""
    pm, reg, test, reads = _regression_case()
    assert reg is not None
    shifts, raw_shifts, moved = [], [], []
    for (_, p), uv in list(zip(test, reads, strict=True))[:20]:
        off = Pose(p.rotation + np.array([0.008, -0.006, 0.004]),
                   p.translation + np.array([1.0, -1.0, 3.0]))
        f0 = reg.features(pm.mean, CAM, uv, p.matrix, p.translation)
        f1 = reg.features(pm.mean, CAM, uv, off.matrix, off.translation)
        shifts.append(np.linalg.norm(f1 - f0))
        raw_shifts.append(np.linalg.norm(_raw_offsets(pm.mean, uv, off.matrix, off.translation)
                                         - _raw_offsets(pm.mean, uv, p.matrix, p.translation)))
        moved.append(np.abs(reg.alpha(f1) - reg.alpha(f0)).max())
    assert np.median(shifts) < 0.1 * np.median(raw_shifts)
    assert max(moved) < 0.1


def test_the_reading_regression_is_kept_with_the_observation_model(tmp_path):
    from dataclasses import replace

    pm, reg, _, _ = _regression_case()
    assert reg is not None
    with_reg = replace(pm, regression=reg)
    with_reg.save(tmp_path / "p.npz")
    back = PointModel.load(tmp_path / "p.npz", 4).regression
    assert back is not None and back.ridge == reg.ridge
    for key in ("feature_mean", "feature_scale", "weights", "alpha_mean", "information"):
        assert np.array_equal(getattr(back, key), getattr(reg, key))
    pm.save(tmp_path / "old.npz")  # a model saved before the regression existed
    assert PointModel.load(tmp_path / "old.npz").regression is None
    with pytest.raises(ModelFileError, match="regression"):
        replace(pm, regression=replace(reg, weights=reg.weights[:, :3],
                                       alpha_mean=reg.alpha_mean[:3],
                                       information=reg.information[:3, :3]))
    with pytest.raises(ModelFileError, match="regression"):
        replace(reg, information=np.full((4, 4), np.nan))
    with pytest.raises(ModelFileError, match="positive semi-definite"):
        replace(reg, information=-reg.information)


def test_a_measurement_of_the_articulation_is_the_product_of_the_two_gaussians():
    rng = np.random.default_rng(4)
    k = 7
    pred, info = _correlated_prior(rng, alpha_sd=1.0)
    # the speaker's own distribution is a measurement of alpha = 0 with information w I
    a1, a2 = pred.with_speaker(0.7), pred.with_measurement(np.zeros(k), 0.7 * np.eye(k))
    assert np.allclose(a1.alpha, a2.alpha) and np.allclose(a1.translation, a2.translation)
    assert np.allclose(a1.rotation, a2.rotation) and np.allclose(a1.information, a2.information)
    # any other: the summed cost's gradient vanishes at the combined mean
    b = rng.normal(size=(k, k))
    m_info = b @ b.T / k + 0.1 * np.eye(k)
    meas = rng.normal(size=k) * 2.0
    both = pred.with_measurement(meas, m_info)
    g = pred.terms(both.alpha, both.rotation, both.translation)[1]
    g[:k] += 2.0 * m_info @ (both.alpha - meas)
    assert np.abs(g[:k]).max() < 1e-3 and np.abs(g[k + 3:]).max() < 1e-3
    assert np.allclose(both.information[:k, :k], info[:k, :k] + m_info)
    # between the two means, nearer the surer
    assert np.linalg.norm(both.alpha - meas) < np.linalg.norm(pred.alpha - meas)


def test_the_compiled_measurement_of_the_articulation_is_the_numpy_one():
    """StatePrior.with_measurement runs kernels.state_measured (two calls a live frame): the
    numpy reference's numbers to rounding (its solve is a compiled LU, not LAPACK's: ~1e-15
    apart on values of ~1), where a wrong term would be off by far more."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(9)
    k = 7
    for _ in range(20):
        pred, _ = _correlated_prior(rng, alpha_sd=1.0)
        b = rng.normal(size=(k, k))
        m_info = b @ b.T / k + 0.1 * np.eye(k)
        meas = rng.normal(size=k) * 2.0
        for got, ref in ((pred.with_measurement(meas, m_info),
                          pred.with_measurement_numpy(meas, m_info)),
                         (pred.with_speaker(0.7),
                          pred.with_measurement_numpy(np.zeros(k), 0.7 * np.eye(k)))):
            for a, b in ((got.alpha, ref.alpha), (got.translation, ref.translation),
                         (got.information, ref.information)):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
            np.testing.assert_allclose(got.rotation, ref.rotation, rtol=0, atol=1e-15)


@pytest.mark.skipif(not __import__("articast.core.tracking.kernels",
                                   fromlist=["AVAILABLE"]).AVAILABLE,
                    reason="numba is not installed: the numpy path is the only one")
def test_the_compiled_reading_features_are_the_numpy_ones():
    """The live tracker's compiled features (normal equations) give the numpy reference's
    (QR) on the regression case's readings, at the true and at a wrong pose."""
    from articast.core.tracking import kernels
    from articast.core.tracking.points import ReadingRegression

    pm, reg, test, reads = _regression_case()
    assert reg is not None and kernels.AVAILABLE
    for (_, p), uv in list(zip(test, reads, strict=True))[:10]:
        for pose in (p, Pose(p.rotation + 0.02, p.translation + 5.0)):
            want = ReadingRegression.features_numpy(pm.mean, CAM, uv, pose.matrix,
                                                    pose.translation)
            got = reg.features(pm.mean, CAM, uv, pose.matrix, pose.translation)
            assert np.abs(want).max() > 1e-3  # (offsets there to compare)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("n", [3, 6, 13, 20])
def test_the_compiled_small_solve_and_inverse_are_numpy_s(n):
    """kernels.solve_small and inverse_small (LU with partial pivoting: the tracking kernels'
    systems, instead of LAPACK's gesv) give np.linalg.solve's and inv's numbers to rounding
    on well- and ill-conditioned systems, non-symmetric ones and one with a zero leading
    entry (pivoting) included, and raise numpy's LinAlgError where numba's solve does
    (singular, non-finite)."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(n)
    for trial in range(60):
        m = rng.normal(size=(n, n))
        a = m @ m.T * rng.uniform(0.01, 100) + 10.0 ** rng.uniform(-8, 0) * np.eye(n)
        if trial % 3 == 1:
            a = m  # not symmetric: pivoting matters
        if trial % 3 == 2:
            a = m.copy()
            a[0, 0] = 0.0
        b = rng.normal(size=n)
        cond = np.linalg.cond(a)
        x, want = kernels.solve_small(a, b), np.linalg.solve(a, b)
        assert np.abs(x - want).max() <= 1e-13 * cond * np.abs(want).max()
        inv, want_inv = kernels.inverse_small(a), np.linalg.inv(a)
        assert inv.flags.c_contiguous
        assert np.abs(inv - want_inv).max() <= 1e-13 * cond * np.abs(want_inv).max()
    with pytest.raises(np.linalg.LinAlgError):
        kernels.solve_small(np.ones((n, n)), np.ones(n))
    with pytest.raises(np.linalg.LinAlgError):
        kernels.inverse_small(np.zeros((n, n)))
    bad = np.eye(n)
    bad[1, 1] = np.nan
    with pytest.raises(np.linalg.LinAlgError):
        kernels.solve_small(bad, np.ones(n))

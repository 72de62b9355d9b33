"""The Tracker on the blob stand-in face: warm-started sequences, occlusion and recovery,
appearance files. Accuracy on the real synthetic speaker is measured by core/evaluate."""

from dataclasses import replace

import numpy as np
import pytest

from articast.core.appearance.models import AppearanceModel, TrainingFrame, train_appearance
from articast.core.errors import InputError, ModelFileError
from articast.core.model.camera import Pose
from articast.core.tracking.tracker import Tracker, TrackingPolicy
from tests.blobface import blob_trained, render_blobs

# the blob face's features are small discs: the initial search needs a fine grid
TOY = TrackingPolicy(search_step_mm=2.0, search_radius_mm=16.0)


@pytest.fixture(scope="module")
def setup():
    return blob_trained(seed=7)


def trajectory(n):
    t = np.arange(n) / 25.0
    alpha = np.stack([np.sin(2 * np.pi * f * t + p) * 0.9 for f, p in
                      zip([1.1, 0.7, 0.9, 0.5, 0.6, 0.4, 0.3], [0, 1, 2, 3, 4, 5, 6])], 1)
    return t, alpha


def rms_mm(model, a, b):
    return float(np.sqrt(((model.shape(a) - model.shape(b)) ** 2).sum(-1).mean()))


def test_tracks_a_sequence_and_counts_work(setup):
    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(25)
    errs, evals = [], []
    for i in range(len(t)):
        res = tracker.track(render_blobs(model, camera, alpha[i], pose), t[i])
        assert res.ok, res.reason
        assert res.frame == i
        errs.append(rms_mm(model, res.alpha, alpha[i]))
        evals.append(res.evals)
    neutral = np.median([rms_mm(model, np.zeros(7), a) for a in alpha])
    assert np.median(errs) < 0.8 < neutral
    assert np.median(evals[1:]) <= 10


def test_blank_frames_are_not_ok_and_tracking_recovers(setup):
    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(20)
    out = []
    for i in range(len(t)):
        img = render_blobs(model, camera, alpha[i], pose)
        if 8 <= i < 12:
            img[:] = 0
        out.append(tracker.track(img, t[i]))
    assert all(not r.ok for r in out[8:12])
    assert all("blank" in r.reason for r in out[8:12])
    # the state streamed during the gap is the last good one, not a guess
    np.testing.assert_array_equal(out[9].alpha, out[7].alpha)
    assert all(r.ok for r in out[12:15])
    assert rms_mm(model, out[14].alpha, alpha[14]) < 1.0


def test_garbage_frame_is_flagged_as_divergence(setup):
    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(12)
    for i in range(10):
        assert tracker.track(render_blobs(model, camera, alpha[i], pose), t[i]).ok
    noise = np.random.default_rng(0).integers(0, 255, (camera.height, camera.width, 3), np.uint8)
    res = tracker.track(noise, t[10])
    assert not res.ok and "residual" in res.reason


def test_a_few_mispredicted_points_are_tracked_through_but_a_covered_face_is_not(setup):
    """The divergence test judges the robust residual: foreign patches over an eighth of the
    sample points (what the linear model cannot predict, e.g. lips beyond the enrolment's
    range) leave the frame ok and accurate; a patch over most of the face is flagged."""
    import cv2

    from articast.core.tracking.fitting import Problem

    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(14)
    for i in range(10):
        assert tracker.track(render_blobs(model, camera, alpha[i], pose), t[i]).ok
    prob = Problem(model, app, camera)
    uv = prob.project(np.r_[alpha[10], pose.as_vector()])
    img = render_blobs(model, camera, alpha[10], pose).copy()
    rng = np.random.default_rng(5)
    for i in rng.choice(len(uv), size=len(uv) // 8, replace=False):
        u, v = (int(round(z)) for z in uv[i])
        cv2.rectangle(img, (u - 6, v - 6), (u + 6, v + 6),
                      tuple(int(z) for z in rng.integers(0, 255, 3)), -1)
    res = tracker.track(img, t[10])
    assert res.ok, res.reason
    assert rms_mm(model, res.alpha, alpha[10]) < 0.3 * rms_mm(model, np.zeros(7), alpha[10])
    covered = render_blobs(model, camera, alpha[11], pose).copy()
    x0, y0 = np.floor(uv.min(0)).astype(int) - 10
    x1, y1 = np.ceil(uv.max(0)).astype(int) + 10
    cv2.rectangle(covered, (x0, y0), ((x0 + 3 * x1) // 4, y1), (60, 90, 170), -1)
    cv2.circle(covered, (int(uv[0, 0]), int(uv[0, 1])), 9, (250, 250, 250), -1)
    res = tracker.track(cv2.GaussianBlur(covered, (0, 0), 1.0), t[11])
    assert not res.ok and "residual" in res.reason


def test_without_initial_pose_the_frame_is_not_ok(setup):
    model, camera, pose, app = setup
    res = Tracker(model, app, camera).track(render_blobs(model, camera, np.zeros(7), pose), 0.0)
    assert not res.ok and "initial pose" in res.reason


def test_initial_search_finds_an_offset_face(setup):
    model, camera, pose, app = setup
    true_pose = Pose(pose.rotation, pose.translation + [14.0, -9.0, 0.0])
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    res = tracker.track(render_blobs(model, camera, np.zeros(7), true_pose), 0.0)
    assert res.ok
    assert np.abs(res.pose.translation[:2] - true_pose.translation[:2]).max() < 2.0


def test_nelder_mead_baseline_tracks_too(setup):
    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera,
                      TrackingPolicy(optimiser="nelder-mead", search_step_mm=2.0,
                                     search_radius_mm=16.0), pose)
    t, alpha = trajectory(6)
    res = [tracker.track(render_blobs(model, camera, alpha[i], pose), t[i]) for i in range(6)]
    assert all(r.ok for r in res)
    assert np.mean([r.evals for r in res[1:]]) > 50  # the simplex spends far more evaluations


def test_appearance_round_trip_and_errors(setup, tmp_path):
    model, camera, pose, app = setup
    app.save(tmp_path / "a.npz")
    again = AppearanceModel.load(tmp_path / "a.npz", model)
    assert again.kind == app.kind and again.levels == app.levels
    np.testing.assert_array_equal(again.weights, app.weights)
    np.testing.assert_array_equal(again.samples.index, app.samples.index)
    model.save(tmp_path / "m.npz")
    with pytest.raises(ModelFileError, match="expected an articast appearance-model"):
        AppearanceModel.load(tmp_path / "m.npz")
    with pytest.raises(InputError, match="appearance kind"):
        train_appearance(model, camera, [], "la_quadratic")


@pytest.mark.parametrize("kind, gain", [("la_cst", 0.5), ("tex_lin", 0.5), ("tex_cst", 1.0)])
def test_other_appearance_kinds_track(setup, kind, gain):
    """Every kind tracks; tex_cst (the paper's weakest) must at least beat standing still."""
    model, camera, pose, app = setup
    rng = np.random.default_rng(3)
    frames = []
    for _ in range(20):
        a = rng.normal(size=7) * 0.8
        frames.append(TrainingFrame(render_blobs(model, camera, a, pose), a, pose))
    app2 = train_appearance(model, camera, frames, kind, sigma=2.0, levels=(0, 1),
                            tex_spacing_mm=3.0)
    tracker = Tracker(model, app2, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(10)
    res = [tracker.track(render_blobs(model, camera, alpha[i] * 0.5, pose), t[i]) for i in range(10)]
    assert all(r.ok for r in res)
    start = rms_mm(model, np.zeros(7), alpha[9] * 0.5)
    assert rms_mm(model, res[9].alpha, alpha[9] * 0.5) < gain * start


def test_pose_anchor_centres_the_pose_prior_on_the_average_rig_pose(setup):
    """With ``pose_anchor_rate`` r the pose prior is centred on the running average of the
    accepted poses (a head-mounted rig's pose, which a previous-frame prior lets drift);
    without it, on the previous frame's pose."""
    model, camera, pose, app = setup
    for rate in (None, 0.0, 0.5):
        pol = replace(TOY, pose_anchor_rate=rate)
        tracker = Tracker(model, app, camera, pol)
        tracker.reset(pose, np.zeros(7))
        assert np.allclose(tracker.pose_prior_centre, pose.as_vector())
        avg = None
        for i in range(6):
            p = Pose(pose.rotation, pose.translation + [0.5 * i, 0.0, 0.0])
            res = tracker.track(render_blobs(model, camera, np.zeros(7), p), i / 25.0)
            assert res.ok
            vec = res.pose.as_vector()
            avg = vec if avg is None else (1 - (rate or 0)) * avg + (rate or 0) * vec
        want = vec if rate is None else avg
        np.testing.assert_allclose(tracker.pose_prior_centre, want, atol=1e-9)
        if rate == 0.0:  # fixed on the first frame
            assert abs(tracker.pose_prior_centre[3] - pose.translation[0]) < 0.3


def test_information_selection_finds_the_points_that_show_a_depth_mode():
    """A parameter that moves some points a lot along the camera's line of sight (invisible:
    jaw advance under a frontal camera) and others a little across the image: the paper's
    largest-displacement rule picks the invisible ones, the information rule the visible."""
    from articast.core.appearance.models import informative_points, select_points, visible_points
    from articast.core.model.face import FaceModel
    from tests.blobface import blob_setup

    model, camera, pose = blob_setup()
    basis = model.basis.copy()
    rng = np.random.default_rng(1)
    order = rng.permutation(model.n_points)
    hidden, shown = order[:6], order[6:12]
    ray = pose.matrix.T @ np.array([0.0, 0.0, 1.0])  # the optical axis in the head frame
    across = pose.matrix.T @ np.array([1.0, 0.0, 0.0])
    basis[6] = 0.0
    basis[6, hidden] = 6.0 * ray
    basis[6, shown] = 1.5 * across
    m = FaceModel(model.mean, basis, model.param_names, model.stats, model.point_names,
                  model.groups, model.triangles, model.feature_points, {}, "depth")
    frames = []
    for _ in range(24):
        a = rng.normal(size=7) * 0.8
        frames.append(TrainingFrame(render_blobs(m, camera, a, pose), a, pose))
    vis = visible_points(m, camera, frames)
    by_motion = select_points(m, 2, vis)
    by_info = informative_points(m, camera, frames, vis, by_motion.size, sigma=2.0)
    assert len(set(hidden) & set(by_motion)) >= 2  # the rule takes the invisible motion
    assert len(set(shown) & set(by_info)) > len(set(shown) & set(by_motion))
    assert by_info.size == by_motion.size == len(set(by_info))


def test_information_selection_with_an_unknown_pose_keeps_points_that_pin_the_head():
    """Points the articulation never moves tell nothing about alpha if the head pose is known,
    so the plain information rule leaves them out; when the pose is estimated with alpha (a
    desk camera), a point's motion is only informative relative to points that fix the head,
    and the pose-marginalised rule takes some of them (the nose and eyes of a real face)."""
    from articast.core.appearance.models import informative_points, visible_points
    from articast.core.model.face import FaceModel
    from tests.blobface import blob_setup

    model, camera, pose = blob_setup()
    rng = np.random.default_rng(3)
    rigid = rng.permutation(model.n_points)[:10]
    basis = model.basis.copy()
    basis[:, rigid] = 0.0
    m = FaceModel(model.mean, basis, model.param_names, model.stats, model.point_names,
                  model.groups, model.triangles, model.feature_points, {}, "rigid")
    frames = []
    for _ in range(30):
        a = rng.normal(size=7) * 0.8
        p = Pose(pose.rotation + rng.normal(size=3) * 0.02,
                 pose.translation + rng.normal(size=3) * 3)
        frames.append(TrainingFrame(render_blobs(m, camera, a, p), a, p))
    vis = visible_points(m, camera, frames)
    known = informative_points(m, camera, frames, vis, 14, sigma=2.0)
    unknown = informative_points(m, camera, frames, vis, 14, sigma=2.0, pose_sigma=(0.003, 0.5))
    assert not set(rigid) & set(known)
    assert len(set(rigid) & set(unknown)) >= 2
    assert unknown.size == 14 == len(set(unknown))


def test_a_sudden_exposure_step_is_absorbed_by_the_gain(setup):
    """A webcam's auto-exposure can step the image gain between two frames: la models
    estimate the gain, so the frames stay ok and accurate, with the gain following."""
    model, camera, pose, app = setup
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(16)
    for i in range(16):
        img = render_blobs(model, camera, alpha[i], pose)
        if i >= 10:  # 40 % less contrast around mid grey from frame 10 on
            img = np.clip(img * 0.6 + 0.4 * 128, 0, 255).astype(np.uint8)
        res = tracker.track(img, t[i])
        assert res.ok, (i, res.reason)
        assert rms_mm(model, res.alpha, alpha[i]) < 0.5
    assert abs(res.extra["gain"] - 0.6) < 0.05


def test_filter_scale_is_the_same_size_on_the_face_at_any_distance():
    """la filters are sized on the face (0.7 mm), not in pixels: a face twice as far gets
    half the scale, down to a floor where sensor noise would dominate."""
    from articast.core.appearance.models import SIGMA_MIN_PX, face_sigma
    from tests.blobface import blob_setup

    _, camera, pose = blob_setup()

    def at(depth):
        p = Pose(pose.rotation, [0.0, 0.0, depth])
        return face_sigma(camera, [TrainingFrame(np.zeros((2, 2, 3), np.uint8), np.zeros(7), p)])

    near, far = at(100.0), at(200.0)
    assert near == pytest.approx(2 * far) and far > SIGMA_MIN_PX
    assert at(5000.0) == SIGMA_MIN_PX
    assert at(200.0) * 200.0 / camera.fx == pytest.approx(0.7)


@pytest.mark.parametrize("kind", ["la_lin", "la_quad"])
def test_the_tracker_calls_only_the_kernels_its_warm_up_compiles(kind, monkeypatch):
    """A session without a speaker (``articast demo``) compiles only kernels.TRACKER on its
    first run (issue 39: all of them took 65 s of CPU, the landmark, iris and Kalman kernels
    half of it, which this tracker never calls). Every kernel a tracked frame calls is in it,
    with the argument types its warm-up compiled: nothing is compiled while tracking."""
    from articast.core.tracking import kernels
    from tests.kernel_spies import KernelSpies

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = blob_trained(seed=7, kind=kind)
    spies = KernelSpies()

    every = ("la_residuals", "cauchy", "point_residuals", "gn_terms", "lm_step",
             "fit_information", "sample_uv", "roi_box", "pixels_sd2", "facing_cos", "occlusion_votes",
             "point_offset", "cv_predict", "cv_update", "iris_chords", "iris_former_rows")
    kernels.warm_up(kernels.TRACKER)  # compiled (or loaded) before the spies: lm_step
    # calls gn_terms (and it la_residuals) as a global, which a spy in its place would not type
    for name in every:
        monkeypatch.setattr(kernels, name, spies.wrap(name, getattr(kernels, name)))
    kernels.warm_up(kernels.TRACKER)
    warmed = spies.take()
    assert set(warmed) == set(kernels.TRACKER) < set(every)
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    t, alpha = trajectory(8)
    assert all(tracker.track(render_blobs(model, camera, alpha[i], pose), t[i]).ok
               for i in range(8))
    seen = spies.take()
    assert {"gn_terms", "lm_step"} <= set(seen)  # the compiled path ran
    for name, types in seen.items():
        assert name in kernels.TRACKER and types <= warmed[name], (name, types)


def test_the_compiled_contrast_is_opencvs_to_the_last_bit():
    """kernels.pixels_sd3 / pixels_sd2 (the live frame's and the face's contrast checks, read
    in place from strided views) are cv2.meanStdDev of a contiguous copy, bit for bit: exact
    integer sums, then OpenCV's formula."""
    import cv2

    from articast.core.tracking import kernels
    from articast.core.tracking.tracker import pixel_spread as _spread

    _contrast = _spread  # (the live frame's check and the face's: one function)

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    rng = np.random.default_rng(5)

    def ref(p):
        return float(cv2.meanStdDev(np.ascontiguousarray(p).reshape(-1, 1))[1][0, 0])

    for i in range(200):
        h, w = (int(v) for v in rng.integers(8, 300, 2))
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        if i % 3 == 0:  # a face-like frame: smooth, few levels
            img = (np.add.outer(np.arange(h), np.arange(w))[:, :, None] % 7 * 30
                   + np.arange(3)).astype(np.uint8)
        if i % 2:
            img.setflags(write=False)
        for view in (img, img[::8, ::8], img[1::3, 2::5]):
            assert _contrast(view) == ref(view)
            assert float(kernels.pixels_sd3(view)) == ref(view)
            assert _spread(view[:, :, 1]) == ref(view[:, :, 1])
            assert float(kernels.pixels_sd2(view[::4, ::4, 1])) == ref(view[::4, ::4, 1])
    assert _contrast(np.full((4, 4, 3), 9, np.uint8)) == 0.0


def test_the_compiled_occlusion_votes_are_the_numpy_ones():
    """Tracker.occlusion runs kernels.occlusion_votes: the numpy reference's points judged
    and voting (and their counts), exactly, over residuals round their limits, gains above
    and below 1, staying or not, with and without a pose (the facing test)."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = blob_trained(seed=7, kind="la_lin")
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    pol = tracker.policy
    assert pol.occlusion_q is not None and pol.occlusion_facing is not None
    assert tracker._normals is not None
    s = len(tracker._judged)
    rng = np.random.default_rng(8)
    tracker._qlevel = rng.uniform(0.5, 2.0, s) * pol.occlusion_floor
    votes = 0
    for i in range(60):
        limit = np.maximum(pol.occlusion_q, pol.occlusion_factor * np.maximum(
            tracker._qlevel, pol.occlusion_floor))
        q = limit * rng.uniform(0.5, 1.5, s)
        q[rng.random(s) < 0.1] = 0.0  # outside the image
        if i % 7 == 0:
            q[rng.integers(s)] = limit[0]  # on a limit
        gain = float(rng.uniform(0.8, 1.3))
        at = (None if i % 5 == 0 else
              Pose(pose.rotation + rng.normal(0, 0.5, 3), pose.translation))
        staying = bool(i % 3 == 0)
        got = tracker._votes(q, gain, staying, at)
        ref = tracker.occlusion_numpy(q, gain, staying, at)
        np.testing.assert_array_equal(got[0], ref[0])
        assert got[1:] == ref[1:]
        votes += got[1]
    assert votes > 0


def test_the_compiled_facing_is_the_numpy_one():
    """Tracker.facing (every frame's occlusion test) runs kernels.facing_cos: the numpy
    reference's cosines, to the last bit, at poses round the tracked one."""
    from articast.core.tracking import kernels

    if not kernels.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model, camera, pose, app = blob_trained(seed=7, kind="la_lin")
    tracker = Tracker(model, app, camera, TOY, initial_pose=pose)
    assert tracker._normals is not None
    rng = np.random.default_rng(3)
    for _ in range(50):
        at = Pose(pose.rotation + rng.normal(0, 0.2, 3), pose.translation + rng.normal(0, 20, 3))
        got, ref = tracker.facing(at), tracker.facing_numpy(at)
        np.testing.assert_array_equal(got, ref)

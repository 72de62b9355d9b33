"""The built-in synthetic speaker: geometry, corpus/model acceptance, renderer, sequences, CLI."""

import json

import cv2
import numpy as np
import pytest

from articast.core.errors import InputError
from articast.core.model.build import Corpus, build_model, invert
from articast.core.model.camera import FRONTAL, Camera, Pose, rotation_matrix
from articast.core.model.face import FEATURE_POINTS, PARAM_NAMES, POINT_GROUPS, FaceModel
from articast.core.synthetic import (
    RenderOptions,
    default_speaker,
    make_corpus,
    make_geometry,
    make_sequence,
    rest_pose,
)
from articast.core.synthetic.render import rasterize
from articast.core.synthetic.sequence import default_camera

OPEN = np.array([2.0, 0.3, -0.3, 0.0, 0.3, 0.0, 0.0])  # /a/


# ---------------------------------------------------------------- geometry
def test_geometry_has_every_group_label_and_a_front_facing_mesh():
    g = make_geometry(0)
    assert 250 <= g.n_points <= 500
    for name in POINT_GROUPS:
        assert g.groups[name].size > 0, name
    assert g.groups["lip_inner"].size >= 30 and g.groups["lip_outer"].size >= 30
    assert set(FEATURE_POINTS) <= set(g.feature_points)
    assert len(set(g.point_names)) == g.n_points
    partition = np.concatenate([g.groups[k] for k in ("jaw_line", "lower_teeth", "lip_inner",
                                                      "lip_outer", "lip_beads", "rest")])
    assert np.array_equal(np.sort(partition), np.arange(g.n_points))
    p = g.neutral[g.triangles]
    e1, e2 = p[:, 1, :2] - p[:, 0, :2], p[:, 2, :2] - p[:, 0, :2]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    assert np.all(area > 0), "triangles must be counter-clockwise seen from +z"
    left, right = g.neutral[g.feature_points["8.3"]], g.neutral[g.feature_points["8.4"]]
    assert left[0] > 15 and right[0] < -15  # x is the speaker's left


def test_each_control_moves_the_face_the_way_its_name_says():
    g = make_geometry(0)
    fp = g.feature_points
    rest = g.articulate(np.zeros(7))

    def moved(k, amount=1.0):
        c = np.zeros(7)
        c[k] = amount
        return g.articulate(c) - rest

    assert moved(0)[fp["2.1"], 1] < -5  # jaw1 opens: chin down
    d = moved(1)
    assert d[fp["8.3"], 0] > 1.5 and d[fp["8.4"], 0] < -1.5  # lips1 spreads
    d = moved(1, -1.0)
    assert d[fp["8.3"], 0] < -2 and d[fp["8.1"], 2] > 2  # rounding: narrower, protruded
    assert moved(2)[fp["2.3"], 1] > 2  # lips2 raises the lower lip
    assert moved(3)[fp["8.1"], 1] < -2  # lips3 lowers the upper lip
    d = moved(4)
    assert d[fp["8.3"], 1] > 2 and d[fp["8.4"], 1] > 2  # lips4 raises the corners
    assert moved(5)[fp["2.1"], 2] > 2  # jaw2 advances the jaw
    throat = g.groups["rest"][np.argsort(g.neutral[g.groups["rest"], 1])[:5]]
    assert moved(6)[throat, 1].mean() > 2  # lar1 raises the throat


def test_articulation_is_not_linear():
    g = make_geometry(0)
    rest = g.articulate(np.zeros(7))
    for k in (0, 1):
        c = np.zeros(7)
        c[k] = 1.0
        d1, d2 = g.articulate(c) - rest, g.articulate(2 * c) - rest
        assert np.abs(d2 - 2 * d1).max() > 0.8, PARAM_NAMES[k]


def test_articulate_rejects_bad_controls():
    g = make_geometry(0)
    with pytest.raises(InputError):
        g.articulate(np.zeros(6))
    with pytest.raises(InputError):
        g.articulate(np.full(7, np.nan))


# ---------------------------------------------------------------- corpus and built model
def test_corpus_has_the_papers_68_postures_with_lip_closure():
    c = make_corpus(3)
    assert c.postures.shape[0] == 68 and len(set(c.posture_names)) == 68
    assert {"rest", "preph", "a", "i", "u", "apa", "ifi"} <= set(c.posture_names)
    assert c.controls.shape == (68, 7) and c.control_names == PARAM_NAMES
    clean = make_corpus(3, noise_mm=0.0)
    noise = np.sqrt(((c.postures - clean.postures) ** 2).sum(-1).mean())
    assert noise == pytest.approx(0.3, rel=0.05)
    up, lo = c.feature_points["2.2"], c.feature_points["2.3"]
    gap = {n: clean.postures[i, up, 1] - clean.postures[i, lo, 1]
           for i, n in enumerate(c.posture_names)}
    for name in ("apa", "ibi", "umu", "ypy"):
        assert gap[name] < 0.6, name  # bilabial closure
    assert gap["a"] > 8


@pytest.mark.parametrize("seed", [11, 12])
def test_built_model_meets_the_acceptance_criteria(seed):
    corpus = make_corpus(seed)
    model, table = build_model(corpus)
    assert table.cumulative_pct[-1] >= 95.0
    rms = np.array(list(table.rms_mm_per_posture.values()))
    assert np.median(rms) <= 0.6
    scores = invert(model, corpus.postures)
    for k, name in enumerate(PARAM_NAMES):
        r = np.corrcoef(scores[:, k], corpus.controls[:, k])[0, 1]
        assert abs(r) >= 0.9, f"{name}: |r| = {abs(r):.3f}"
    # ... but the speaker is not linear: without any measurement noise it still leaves error
    _, clean_table = build_model(make_corpus(seed, noise_mm=0.0))
    assert np.median(list(clean_table.rms_mm_per_posture.values())) > 0.2


def test_corpus_round_trips_and_speaker_model_is_cached(tmp_path):
    c = make_corpus(0)
    c.save(tmp_path / "c.npz")
    back = Corpus.load(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.controls, c.controls)
    sp = default_speaker(0)
    assert sp.model() is sp.model()
    assert sp.model().n_points == c.postures.shape[1]


# ---------------------------------------------------------------- renderer
def test_rasterize_depth_test_nearer_surface_wins_in_any_order():
    xy = np.array([[10, 10], [60, 10], [10, 60], [20, 20], [70, 20], [20, 70]], float)
    inv_z = np.array([1 / 100] * 3 + [1 / 50] * 3)  # second triangle nearer
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    for order in ([0, 1], [1, 0]):
        ids, zbuf = rasterize(xy, inv_z, tris[order], np.zeros(2, bool), 80, 80)
        near = order.index(1)
        assert ids[30, 30] == near  # overlap: the nearer one
        assert ids[12, 12] == 1 - near  # only the far one covers this pixel
        assert ids[5, 5] == -1 and zbuf[5, 5] == 0
        assert zbuf[30, 30] == pytest.approx(1 / 50)


def test_rasterize_culls_back_faces_only_when_asked():
    xy = np.array([[10, 10], [10, 60], [60, 10]], float)  # clockwise on screen = front
    ids, _ = rasterize(xy, np.full(3, 0.01), np.array([[0, 1, 2]]), np.ones(1, bool), 80, 80)
    assert (ids == 0).sum() > 1000
    ids, _ = rasterize(xy, np.full(3, 0.01), np.array([[0, 2, 1]]), np.ones(1, bool), 80, 80)
    assert (ids == 0).sum() == 0


def test_rasterize_in_chunks_gives_the_same_image(monkeypatch):
    import articast.core.synthetic.render as render

    whole = _render(OPEN)
    monkeypatch.setattr(render, "MAX_SPAN_PIXELS", 5000)
    assert np.array_equal(_render(OPEN), whole)


def _render(controls, **kw):
    sp = default_speaker(0)
    opts = RenderOptions(**{"noise_sigma": 0.0, **kw})
    return sp.render(np.asarray(controls, float), rest_pose("head"), default_camera("head"), opts)


def _mouth_box(controls, margin=4):
    sp = default_speaker(0)
    pts = sp.points(np.asarray(controls, float))[sp.geometry.groups["lip_inner"]]
    uv = default_camera("head").project_head(pts, rest_pose("head"))
    x0, y0 = np.floor(uv.min(0)).astype(int) + margin
    x1, y1 = np.ceil(uv.max(0)).astype(int) - margin
    return slice(y0, y1), slice(x0, x1)


def test_opening_the_jaw_shows_a_dark_cavity_and_bright_teeth():
    closed, open_ = _render(np.zeros(7)), _render(OPEN)
    box = _mouth_box(OPEN)
    y_closed = cv2.cvtColor(closed, cv2.COLOR_BGR2GRAY)[box].astype(float)
    y_open = cv2.cvtColor(open_, cv2.COLOR_BGR2GRAY)[box].astype(float)
    assert y_open.mean() < y_closed.mean() - 40
    assert (y_open < 40).mean() > 0.3  # a dark cavity
    hsv = cv2.cvtColor(open_, cv2.COLOR_BGR2HSV)[box]
    teeth = (hsv[..., 2] > 120) & (hsv[..., 1] < 70)
    assert teeth.sum() > 150  # bright, unsaturated teeth pixels


def test_lips_are_redder_than_the_skin():
    sp = default_speaker(0)
    img = _render(np.zeros(7))
    ycc = cv2.cvtColor(img, cv2.COLOR_BGR2YCrCb).astype(float)
    g = sp.geometry
    pose, cam = rest_pose("head"), default_camera("head")
    uv_lip = cam.project_head(sp.points(np.zeros(7))[g.groups["lip_beads"]], pose)
    skin = np.flatnonzero(g.ring == 6)
    uv_skin = cam.project_head(sp.points(np.zeros(7))[skin], pose)
    uv_skin = uv_skin[cam.inside(uv_skin, 2)]

    def cr(uv):
        return ycc[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int), 1]

    assert np.median(cr(uv_lip)) > np.median(cr(uv_skin)) + 8


def test_visibility_hides_the_lower_teeth_behind_closed_lips_and_the_far_cheek():
    sp = default_speaker(0)
    g = sp.geometry
    pose, cam = rest_pose("head"), default_camera("head")
    vis = sp.visible(np.zeros(7), pose, cam)
    assert not vis[g.groups["lower_teeth"]].any()
    assert vis[g.groups["lip_outer"]].all()
    turned = Pose(rotation_matrix_to_vec(np.radians(60)), [0.0, -10.0, 500.0])
    vis = sp.visible(np.zeros(7), turned, cam)
    x = g.neutral[:, 0]
    far, near = (x > 45) & (g.ring >= 6), (x < -45) & (g.ring >= 6)
    assert vis[near].mean() > 0.8 and vis[far].mean() < 0.3


def rotation_matrix_to_vec(yaw):
    """Axis-angle of a frontal view with the head turned by ``yaw`` (rad) to its left."""
    from articast.core.model.camera import axis_angle

    return axis_angle(rotation_matrix(FRONTAL) @ rotation_matrix([0.0, yaw, 0.0]))


def test_render_is_deterministic_and_noise_follows_the_seed():
    a = _render(OPEN, noise_sigma=3.0, seed=5)
    b = _render(OPEN, noise_sigma=3.0, seed=5)
    c = _render(OPEN, noise_sigma=3.0, seed=6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_render_options_change_the_image_as_specified():
    clean = _render(OPEN).astype(float)
    noisy = _render(OPEN, noise_sigma=6.0, seed=1).astype(float)
    mid = (clean > 30) & (clean < 225)  # away from clipping
    assert (noisy - clean)[mid].std() == pytest.approx(6.0, rel=0.1)
    dark = _render(OPEN, gain=0.5).astype(float)
    assert dark.mean() / clean.mean() == pytest.approx(0.5, rel=0.03)
    blurred = _render(OPEN, blur_sigma=2.0)
    lap = [cv2.Laplacian(cv2.cvtColor(im.astype(np.uint8), cv2.COLOR_BGR2GRAY), cv2.CV_64F).var()
           for im in (clean, blurred)]
    assert lap[1] < lap[0] / 4
    lit_left = _render(OPEN, light_azimuth_deg=-60.0).astype(float)
    lit_right = _render(OPEN, light_azimuth_deg=60.0).astype(float)
    w = clean.shape[1]
    assert (lit_left[:, : w // 3].mean() - lit_left[:, -w // 3:].mean()
            > lit_right[:, : w // 3].mean() - lit_right[:, -w // 3:].mean())
    box = _mouth_box(OPEN)
    hand = _render(OPEN, occluder="hand")
    assert cv2.cvtColor(hand, cv2.COLOR_BGR2GRAY)[box].mean() > 100  # the dark mouth is hidden
    assert _render(OPEN, occluder="black").max() == 0
    with pytest.raises(InputError):
        RenderOptions(occluder="glove")
    with pytest.raises(InputError):
        RenderOptions(noise_sigma=-1)


def test_renderer_works_at_other_sizes_and_poses():
    sp = default_speaker(0)
    cam = Camera.default(160, 120, 50)
    turned = Pose(FRONTAL + np.array([0.0, 0.5, 0.0]), [0.0, 0.0, 500.0])
    img = sp.render(np.zeros(7), turned, cam, RenderOptions())
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    behind = Pose(FRONTAL, [0.0, 0.0, -500.0])  # face behind the camera: background only
    assert sp.render(np.zeros(7), behind, cam, RenderOptions(noise_sigma=0)).std() < 20


# ---------------------------------------------------------------- sequences
def _angle_deg(r_a, r_b):
    rel = rotation_matrix(r_a) @ rotation_matrix(r_b).T
    return np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("rig", ["head", "desk"])
def test_sequence_is_smooth_with_exact_still_segments(rig):
    seq = make_sequence(4, 200, 50.0, rig)
    assert seq.points.shape == (200, make_geometry(4).n_points, 3)
    vel = np.diff(seq.controls, axis=0) * seq.fps
    acc = np.diff(seq.controls, 2, axis=0) * seq.fps**2
    assert np.abs(vel).max() < 50  # units/s: no jumps
    assert np.abs(acc).max() < 3000  # units/s^2: bounded acceleration
    assert np.abs(vel).max(0).min() > 0.5  # every control moves
    segments = seq.still_segments()
    assert len(segments) >= 2 and all(b - a >= 15 for a, b in segments)
    for a, b in segments:
        assert np.abs(seq.controls[a:b] - seq.controls[a]).max() < 1e-12
        assert np.abs(seq.poses[a:b] - seq.poses[a]).max() < 1e-9
        assert np.abs(seq.points[a:b] - seq.points[a]).max() < 1e-9
    pose_acc = np.diff(seq.poses[:, 3:], 2, axis=0) * seq.fps**2
    assert np.abs(pose_acc).max() < 2000  # mm/s^2


def test_quintic_path_passes_its_keyframes_with_their_velocities():
    from articast.core.synthetic.sequence import quintic_path

    key_t = np.array([0.0, 0.1, 0.25, 0.4])
    key_x = np.array([[0.0], [1.0], [-0.5], [0.2]])
    key_v = np.array([[0.0], [4.0], [-2.0], [0.0]])
    np.testing.assert_allclose(quintic_path(key_t, key_t, key_x, key_v), key_x, atol=1e-12)
    h = 1e-6
    for k in (1, 2):
        slope = (quintic_path(key_t[k:k + 1] + h, key_t, key_x, key_v)
                 - quintic_path(key_t[k:k + 1] - h, key_t, key_x, key_v)) / (2 * h)
        assert slope[0, 0] == pytest.approx(key_v[k, 0], rel=1e-4)


def test_head_mounted_rig_moves_little_and_desk_rig_moves():
    head, desk = make_sequence(2, 250, 50.0, "head"), make_sequence(2, 250, 50.0, "desk")
    rot = [max(_angle_deg(s.poses[i, :3], s.poses[0, :3]) for i in range(s.n_frames))
           for s in (head, desk)]
    trans = [np.linalg.norm(s.poses[:, 3:] - s.poses[0, 3:], axis=1).max() for s in (head, desk)]
    assert rot[0] < 0.5 and trans[0] < 1.0
    assert rot[1] > 1.5 and trans[1] > 5.0
    # head rig: the mouth is near the image centre and the lower face fills the frame
    g = make_geometry(2)
    uv = head.camera.project_head(head.points[0], head.pose(0))
    lips = uv[g.groups["lip_outer"]]
    assert np.all(head.camera.inside(lips, 20))
    assert np.ptp(uv[g.groups["jaw_line"], 0]) > 0.6 * head.camera.width
    uv = desk.camera.project_head(desk.points[0], desk.pose(0))
    assert np.all(desk.camera.inside(uv[g.groups["jaw_line"]], 10))


def test_sequence_rejects_bad_arguments():
    with pytest.raises(InputError):
        make_sequence(0, 10, rig="helmet")
    with pytest.raises(InputError):
        make_sequence(0, 0)
    with pytest.raises(InputError):
        make_sequence(0, 10, fps=-1)
    with pytest.raises(InputError):
        make_sequence(-3, 10)
    with pytest.raises(InputError):
        make_corpus(-3)


# ---------------------------------------------------------------- CLI
def test_cli_synth_sequence_writes_consistent_files(tmp_path):
    from articast.service.cli import main

    out = tmp_path / "seq"
    rc = main(["synth", "sequence", "-o", str(out), "--frames", "7", "--size", "160x120",
               "--seed", "1", "--noise", "3", "--still-frames", "0", "--occluder", "black",
               "--occlude-frames", "5:9"])
    assert rc == 0
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    frames = 0
    while cap.read()[0]:
        frames += 1
    assert frames == 7
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    means = [cap.read()[1].mean() for _ in range(7)]
    assert min(means[:5]) > 40 and max(means[5:]) < 10  # black from frame 5 on
    lines = [json.loads(x) for x in (out / "truth.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in lines] == list(range(7))
    assert set(lines[0]) >= {"frame", "t", "alpha", "pose", "controls"}
    assert [r["occluded"] for r in lines] == [False] * 5 + [True] * 2
    assert list(lines[0]["alpha"]) == list(PARAM_NAMES)
    with np.load(out / "truth.npz") as npz:
        points, controls, poses = npz["points"], npz["controls"], npz["poses"]
    assert points.shape[0] == controls.shape[0] == poses.shape[0] == 7
    model = FaceModel.load(out / "model.npz")
    alpha = np.array([list(r["alpha"].values()) for r in lines])
    np.testing.assert_allclose(alpha, invert(model, points), atol=1e-9)
    np.testing.assert_allclose([r["pose"]["translation"] for r in lines], poses[:, 3:])
    cam = Camera.load(out / "camera.json")
    assert (cam.width, cam.height) == (160, 120)


def test_cli_synth_reports_bad_input_clearly(tmp_path, capsys):
    from articast.service.cli import main

    assert main(["synth", "sequence", "-o", str(tmp_path), "--size", "big"]) == 2
    assert "--size must look like 640x480" in capsys.readouterr().err
    assert main(["synth", "corpus", "-o", str(tmp_path / "c.npz"), "--seed", "2"]) == 0
    assert Corpus.load(tmp_path / "c.npz").postures.shape[0] == 68

"""A whole head scan in its own frame and unit bound by its landmarks (core/dense/scan.py,
``bind-dense --landmarks``), on a head the tests make from the model (tests/scan_head.py)."""

from __future__ import annotations

import json
import time
from functools import lru_cache

import numpy as np
import pytest

from articast.core.bundle import load_bundle
from articast.core.dense.landmarks import load_landmarks, parse_landmarks
from articast.core.dense.scan import (
    align_scan,
    bind_scan,
    closest_point_coordinates,
    mouth_facets,
    similarity,
)
from articast.core.dense.texture import TEXTURE_ARRAYS, mouth_cavity, texture_from_arrays
from articast.core.dense.transfer import Binding, apply, dense_modes, linearity_error
from articast.core.errors import InputError, ModelFileError
from articast.core.model.camera import rotation_matrix
from articast.service.cli import main
from tests.scan_head import head_scan, write_ljson, write_obj, write_pts, write_textured


@pytest.fixture(scope="module")
def bound():
    h = head_scan()
    al = align_scan(h.model, h.scan, h.triangles, h.landmarks)
    binding, report = bind_scan(h.model, al.transform.apply(h.scan), h.triangles)
    return h, al, binding, report


def _edges(triangles):
    return np.unique(np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)


def test_landmark_files_read_alike_and_the_menpo3d_group_order_is_undone(tmp_path):
    pts = head_scan().landmarks
    write_ljson(tmp_path / "a.ljson", pts)  # eyes listed before brows, as menpo3d's james
    write_ljson(tmp_path / "b.ljson", pts, menpo3d_order=False)
    write_pts(tmp_path / "c.pts", pts)
    (tmp_path / "d.json").write_text(json.dumps(pts.tolist()))
    for name in ("a.ljson", "b.ljson", "c.pts", "d.json"):
        assert np.allclose(load_landmarks(tmp_path / name), pts, atol=1e-8), name
    raw = json.loads((tmp_path / "a.ljson").read_text())
    listed = np.array(raw["groups"]["LJSON"]["landmarks"]["points"])
    assert not np.allclose(listed, pts)  # the file's own order is not iBUG's
    with pytest.raises(InputError, match=r"c.pts: need the 68 points .* got 67 points"):
        write_pts(tmp_path / "c.pts", pts[:67])
        load_landmarks(tmp_path / "c.pts")
    for text, kind in (("[[1, 2, 3], ", "json"), ('{"groups": {}}', "ljson"),
                       ('{"points": {"a": 1}}', "json"), ("{\n1 2\n}", "pts"),
                       ('{"landmarks": {"points": [[1, 2, "x"]]}}', "ljson")):
        with pytest.raises(InputError, match=f"x.{kind}: not a {kind} landmark file"):
            parse_landmarks(text, kind, f"x.{kind}")
    with pytest.raises(InputError, match="must be .ljson, .pts or .json"):
        load_landmarks(tmp_path / "a.txt")


def test_similarity_recovers_scale_rotation_and_shift():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(7, 3)) * 30
    rot = rotation_matrix([0.4, -1.1, 0.7])
    dst = 0.004 * src @ rot.T + [1.0, 2.0, -3.0]
    sim = similarity(src, dst, np.ones(7))
    assert sim.scale == pytest.approx(0.004, rel=1e-9)
    assert np.allclose(sim.rotation, rot) and np.allclose(sim.apply(src), dst)
    with pytest.raises(InputError, match="lie on a line"):
        similarity(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [3, 2, 1]),
                   np.ones(5))


def test_a_head_in_metres_and_another_frame_is_brought_into_the_head_frame(bound):
    h, al, _, _ = bound
    assert al.icp_converged and al.overlap_fraction > 0.95
    assert al.transform.scale == pytest.approx(1000.0, rel=0.005)
    assert al.landmark_rms_mm < 0.5 and al.icp_rms_mm < 1.0
    # the scan is the model's surface smoothed by subdivision (shrunk by up to ~1.5 mm on
    # the curved parts): the fit of the model onto it lands within 2 mm everywhere
    err = np.linalg.norm(al.transform.apply(h.scan) - h.head, axis=1)
    assert np.median(err) < 1.0 and err.max() < 2.0


def test_the_face_moves_with_the_model_and_the_rest_of_the_head_with_the_head(bound):
    h, al, binding, rep = bound
    m = h.model
    x = al.transform.apply(h.scan)
    assert rep.n_articulated + rep.n_border + rep.n_held == len(x)
    assert rep.n_articulated > 0.5 * len(x) and rep.n_held > 100 and rep.n_border > 100
    assert rep.inside_support_fraction >= 0.95
    assert not np.any(rep.articulated & ~h.face)  # only points the model moves are articulated
    for a in (np.r_[m.stats.max[0], np.zeros(6)], m.stats.max, 0.5 * m.stats.min):
        moved = apply(binding, m.shape(a))
        truth = h.truth(a)
        err = np.linalg.norm(moved - truth, axis=1)[rep.articulated]
        motion = np.linalg.norm(truth - h.head, axis=1)[rep.articulated]
        assert np.median(err) < 0.6 and err.max() < 3.5, (np.median(err), err.max())
        assert np.median(err) < 0.1 * motion.max()
        held = binding.follow == 0
        assert np.array_equal(moved[held], x[held])  # the cranium does not move at all
    back = x[:, 2] < x[:, 2].min() + 30  # the back of the head
    assert np.all(binding.follow[back] == 0)
    err = linearity_error(binding, m, np.random.default_rng(0).uniform(
        m.stats.min, m.stats.max, (16, m.n_params)), points=rep.articulated)
    assert np.median(err) <= 0.5 and err.max() <= 2.0


def test_no_tear_at_the_border_and_the_neck_follows_the_jaw_partly(bound):
    """Across the edges that leave the support, the scan stretches no more than the face
    itself does under the model's motion (truth); cutting the motion off at the support's
    edge (share 1 inside, 0 outside) tears it there."""
    h, al, binding, rep = bound
    m = h.model
    x = al.transform.apply(h.scan)
    e = _edges(h.triangles)
    length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
    leaving = ~(rep.articulated[e[:, 0]] & rep.articulated[e[:, 1]])
    jaw = np.r_[m.stats.max[0], np.zeros(6)]
    truth = h.truth(jaw) - h.head
    face = h.face[e[:, 0]] & h.face[e[:, 1]]
    face_strain = (np.linalg.norm(truth[e[:, 0]] - truth[e[:, 1]], axis=1) / length)[face].max()
    cut = Binding(binding.sparse_vertices, binding.triangles, binding.dense_vertices,
                  binding.facet, binding.local, binding.weights, binding.offset, binding.inside,
                  binding.corner_normals, binding.curvature, binding.lambda2,
                  binding.dense_triangles, follow=rep.articulated.astype(float),
                  turn=binding.turn)
    strains = []
    for b in (binding, cut):
        d = apply(b, m.shape(jaw)) - x
        strains.append((np.linalg.norm(d[e[:, 0]] - d[e[:, 1]], axis=1) / length)[leaving].max())
    assert strains[0] <= face_strain < strains[1], (strains, face_strain)
    d = np.linalg.norm(apply(binding, m.shape(jaw)) - x, axis=1)
    neck = (x[:, 1] < -90) & ~rep.articulated  # below the jaw, off the model
    partly = neck & (binding.follow > 0) & (binding.follow < 1) & (d > 0.01)
    assert partly.sum() > 20
    assert d[partly].max() < d[rep.articulated].max()


def test_bind_dense_with_landmarks_reports_and_refuses(tmp_path, capsys, bound):
    h = bound[0]
    h.model.save(tmp_path / "m.npz")
    write_obj(tmp_path / "head.obj", h.scan, h.triangles)
    write_ljson(tmp_path / "head.ljson", h.landmarks)
    base = ["bind-dense", str(tmp_path / "head.obj"), "--model", str(tmp_path / "m.npz"),
            "-o", str(tmp_path / "b.npz"), "--json"]
    assert main([*base, "--landmarks", str(tmp_path / "head.ljson")]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["icp_converged"] and rep["scale_to_mm"] == pytest.approx(1000, rel=0.005)
    assert rep["points_articulated"] + rep["points_border"] + rep["points_head_only"] == len(
        h.head)
    assert rep["inside_fraction"] >= 0.95 and rep["dense_modes_max_error_mm"] <= 2.0
    assert set(rep["landmark_pairs"]) >= {"8.3", "8.4", "8.1", "9.15", "3.5", "3.6"}
    b = Binding.load(tmp_path / "b.npz")
    assert b.follow is not None and np.isclose(b.follow.min(), 0) and b.turn is not None
    assert np.allclose(apply(b, h.model.mean), b.dense_vertices)
    # no landmarks, scan in metres in its own frame: told what is needed
    assert main(base) == 2
    err = capsys.readouterr().err.strip()
    assert "--landmarks FILE" in err and len(err.splitlines()) == 1
    # mirrored landmarks (left and right swapped): they fit no rigid placement
    mirrored = h.landmarks.copy()
    mirrored[[54, 48]], mirrored[36:42], mirrored[42:48] = (
        h.landmarks[[48, 54]], h.landmarks[42:48], h.landmarks[36:42])
    write_pts(tmp_path / "mirrored.pts", mirrored)
    assert main([*base, "--landmarks", str(tmp_path / "mirrored.pts")]) == 2
    assert "do not fit the model's feature points" in capsys.readouterr().err
    # landmarks of another head (placed 80 mm off): the scan does not cover the face
    write_pts(tmp_path / "off.pts", h.landmarks + h.to_scan(np.array([[0.0, 80.0, 0.0]]))
              - h.to_scan(np.zeros((1, 3))))
    assert main([*base, "--landmarks", str(tmp_path / "off.pts")]) == 2
    assert "covers" in capsys.readouterr().err
    # too few shared points
    few = h.landmarks.copy()
    few[[33, 51, 57, *range(36, 48)]] = np.nan
    (tmp_path / "few.json").write_text(json.dumps(
        [None if np.isnan(p).any() else p.tolist() for p in few]))
    assert main([*base, "--landmarks", str(tmp_path / "few.json")]) == 2
    assert "only 2 landmarks have a counterpart" in capsys.readouterr().err
    assert main([*base, "--landmarks", str(tmp_path / "head.ljson"), "--no-register"]) == 2
    assert "give one of them" in capsys.readouterr().err


def test_binding_file_refuses_bad_shares(tmp_path, bound):
    b = bound[2]
    b.save(tmp_path / "b.npz")
    arrays = dict(np.load(tmp_path / "b.npz", allow_pickle=False))
    assert np.array_equal(Binding.load(tmp_path / "b.npz").turn, b.turn)
    arrays["follow"] = arrays["follow"] * 2
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError, match="'follow' must be"):
        Binding.load(tmp_path / "bad.npz")


def test_closest_point_coordinates_on_and_off_the_triangle():
    a, b, c = np.zeros(3), np.array([10.0, 0, 0]), np.array([0, 10.0, 0])
    p = np.array([[2.0, 3, 5], [20, 0, 1], [-3, -4, 0], [6, 6, 2]])
    bc = closest_point_coordinates(p, *(np.tile(v, (4, 1)) for v in (a, b, c)))
    q = bc @ np.stack([a, b, c])
    assert np.allclose(q, [[2, 3, 0], [10, 0, 0], [0, 0, 0], [5, 5, 0]])


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    """The test head bound with its texture (bind-dense, the .obj's material), its model."""
    d = tmp_path_factory.mktemp("textured")
    files = write_textured(d)
    head_scan().model.save(d / "m.npz")
    assert main(["bind-dense", str(files["obj"]), "--landmarks", str(files["ljson"]),
                 "--model", str(d / "m.npz"), "-o", str(d / "b.npz")]) == 0
    return d, files


def test_bind_dense_keeps_the_texture_and_its_render_mesh(textured, tmp_path, capsys):
    d, files = textured
    arrays, _ = load_bundle(d / "b.npz", "dense-binding", (1,))
    tex = texture_from_arrays(arrays, len(head_scan().head))
    assert tex is not None and tex.mime == "image/png"
    assert tex.image == files["png"].read_bytes()
    b = Binding.load(d / "b.npz")
    # each render triangle is its scan facet, point for point
    assert np.array_equal(tex.render_index[tex.triangles], b.dense_triangles)
    args = ["bind-dense", str(files["obj"]), "--landmarks", str(files["ljson"]), "--model",
            str(d / "m.npz"), "-o", str(tmp_path / "x.npz")]
    assert main([*args, "--texture", str(files["ljson"])]) == 2
    assert "head.ljson: the texture must be a JPEG or PNG image" in capsys.readouterr().err
    plain = tmp_path / "plain.obj"  # facets without texture coordinates
    write_obj(plain, head_scan().scan, head_scan().triangles)
    args[1] = str(plain)
    assert main([*args, "--texture", str(files["png"])]) == 2
    assert "texture coordinates (vt) on every facet" in capsys.readouterr().err
    assert main(args) == 0  # no texture asked, none found: a plain binding
    capsys.readouterr()
    assert "texture" not in load_bundle(tmp_path / "x.npz", "dense-binding", (1,))[0]


def test_the_server_serves_the_scan_per_session_model_and_its_texture_with_the_token(
        textured, tmp_path):
    from articast.service.app import ServiceConfig, create_app
    from articast.service.security import AccessPolicy
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from tests.service_helpers import ServerThread
    from tests.test_browser import jaw_recording

    d, files = textured
    sessions = (SessionSpec("s", f"replay-record:{jaw_recording(tmp_path / 's.jsonl', 1.0)}"
                                 "?loop=yes"),)
    config = ServiceConfig(server=ServerSettings(log_level="critical", scan=str(d / "b.npz")),
                           sessions=sessions, access=AccessPolicy(token="t0ken"))
    with ServerThread(config) as srv, srv.client() as c:
        deadline = time.monotonic() + 30
        while (r := c.get("/api/sessions/s/scan")).status_code == 409:
            assert time.monotonic() < deadline, r.text
            time.sleep(0.1)
        assert r.status_code == 200, r.text
        doc = r.json()
        b = Binding.load(d / "b.npz")
        model = head_scan().model
        mean, modes = dense_modes(b, model)
        assert doc["n_points"] == b.n_dense
        assert np.allclose(np.reshape(doc["mean"], (-1, 3)), mean, atol=1e-3)
        assert np.allclose(np.reshape(doc["basis"], modes.shape), modes, atol=1e-3)
        tex = c.get("/api/sessions/s/scan/texture")
        assert tex.status_code == 200 and tex.content == files["png"].read_bytes()
        assert tex.headers["content-type"] == "image/png"
        import httpx

        bare = httpx.get(f"{srv.http}/api/sessions/s/scan/texture", timeout=10)
        assert bare.status_code == 401  # a face: the token is needed
        assert c.get("/api/sessions/nobody/scan").status_code == 404
    # a scan bound to another model than the session's: refused with the reason
    other = head_scan().model
    shifted = Binding(b.sparse_vertices + 1.0, b.triangles, b.dense_vertices, b.facet, b.local,
                      b.weights, b.offset, b.inside, b.corner_normals, b.curvature, b.lambda2,
                      b.dense_triangles, follow=b.follow, turn=b.turn)
    arrays, _ = load_bundle(d / "b.npz", "dense-binding", (1,))
    shifted.save(tmp_path / "other.npz", extra={k: arrays[k] for k in TEXTURE_ARRAYS})
    from articast.service.scan import ScanAsset

    with pytest.raises(InputError, match="was bound to another model"):
        ScanAsset(tmp_path / "other.npz").json_for(other)
    # a binding without texture: the server does not start, and says why
    b.save(tmp_path / "bare.npz")
    with pytest.raises(ModelFileError, match="has no texture"):
        create_app(ServiceConfig(server=ServerSettings(scan=str(tmp_path / "bare.npz"))))


def test_a_closed_mouth_opens_where_the_lips_meet_over_a_dark_cavity():
    """A head whose lips are joined: the facets across the lips are found (only there), and
    the cavity closing the opening follows the lips linearly, behind them."""
    assert not mouth_facets(*_bound_head(False)[:2]).any()  # an open mouth: nothing to cut
    binding, model, x = _bound_head(True)
    cut = mouth_facets(binding, model)
    tri = binding.dense_triangles
    centre = x[tri[cut]].mean(axis=1)
    inner = model.mean[model.group("lip_inner")]
    assert 20 <= cut.sum() < 0.05 * len(tri)
    assert np.all(np.abs(centre[:, 0]) < np.abs(inner[:, 0]).max())  # between the corners
    assert np.all(np.abs(centre[:, 1] - inner[:, 1].mean()) < 10)  # on the lip line
    mean, modes = dense_modes(binding, model)
    cav, cav_modes, cav_tris = mouth_cavity(mean, modes, tri, ~cut)
    assert len(cav) > 10 and cav_tris.max() == len(mean) + len(cav) - 1
    assert np.all(cav[:, 2] < mean[np.unique(tri[cut]), 2].max())  # behind the lips
    jaw = np.r_[model.stats.max[0], np.zeros(model.n_params - 1)]
    lips_open = mean + np.tensordot(jaw, modes, 1)
    cavity_open = cav + np.tensordot(jaw, cav_modes, 1)
    # the cavity's back point stays at the same place relative to the lips' centre
    ring = np.unique(cav_tris[cav_tris < len(mean)])
    rel_rest = cav[-1] - mean[ring].mean(0)
    rel_open = cavity_open[-1] - lips_open[ring].mean(0)
    assert np.allclose(rel_rest, rel_open, atol=1e-9)
    assert np.ptp(lips_open[ring, 1]) > np.ptp(mean[ring, 1]) + 5  # the lips parted


@lru_cache(maxsize=2)
def _bound_head(closed: bool):
    h = head_scan(closed)
    al = align_scan(h.model, h.scan, h.triangles, h.landmarks)
    x = al.transform.apply(h.scan)
    return bind_scan(h.model, x, h.triangles)[0], h.model, x

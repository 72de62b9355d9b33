"""MPEG-4 FAPs: units, semantics from geometry, the .fap text format, and export-fap."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from articast.core.errors import InputError
from articast.core.model.camera import FRONTAL, Pose, axis_angle, rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.outputs.fap import (
    AU,
    GEOMETRIC_FAPS,
    FapEncoder,
    fap_values,
    fapu_from_model,
    format_fap,
    head_angles,
    lip_aperture,
    lip_width,
    parse_fap,
    read_fap,
    reconstruct_feature_points,
    write_fap,
)  # fmt: skip
from articast.core.outputs.fap_table import FAP_BY_NAME, FAP_TABLE, N_FAPS
from articast.core.tracking.result import TrackResult
from articast.service.cli import main
from tests.handmade_face import make_face_model

MODEL = make_face_model()
LIP_FAPS = np.array(GEOMETRIC_FAPS)


def col(name: str) -> int:
    return FAP_BY_NAME[name].number - 1


def frontal_poses(n: int) -> np.ndarray:
    return np.tile(np.r_[FRONTAL, 0.0, 0.0, 450.0], (n, 1))


def head_pose(rot_head: np.ndarray) -> np.ndarray:
    """Pose vector of a head rotated by ``rot_head`` (3, 3) in its own frame, seen frontally."""
    return np.r_[axis_angle(rotation_matrix(FRONTAL) @ rot_head), 5.0, -3.0, 420.0]


def one(name: str, value: float) -> np.ndarray:
    a = np.zeros((1, MODEL.n_params))
    a[0, MODEL.param_names.index(name)] = value
    return a


def geometry(alpha: np.ndarray) -> dict[str, np.ndarray]:
    pts = MODEL.shape(alpha)
    return {lab: pts[:, i] for lab, i in MODEL.feature_points.items()}


# ----------------------------------------------------------------------------- units
def test_fapu_measured_on_the_neutral_face():
    fapu, m = fapu_from_model(MODEL), MODEL.mean
    p = MODEL.point
    assert fapu.MW0 == pytest.approx(m[p("8.3"), 0] - m[p("8.4"), 0])
    assert fapu.MNS0 == pytest.approx(m[p("9.15"), 1] - m[p("2.2"), 1])
    assert fapu.ENS0 == pytest.approx(m[p("3.5"), 1] - m[p("9.15"), 1])
    assert fapu.ES0 == pytest.approx(m[p("3.5"), 0] - m[p("3.6"), 0])
    assert fapu.IRISD0 == pytest.approx(fapu.ES0 * 11.7 / 63)
    assert fapu.unit("MNS") == pytest.approx(fapu.MNS0 / 1024) and fapu.unit("AU") == AU


def _variant(**changes) -> FaceModel:
    fields = {f: getattr(MODEL, f) for f in ("mean", "basis", "stats", "point_names",
                                            "triangles", "feature_points", "name")}
    fields.update(changes)
    return FaceModel(**fields)


def test_fapu_overrides_win_and_missing_points_need_one():
    fp = {k: v for k, v in MODEL.feature_points.items() if k not in ("3.5", "3.6")}
    with pytest.raises(InputError, match=r"cannot define ENS0: no feature point\(s\) \['3.5'\]"):
        fapu_from_model(_variant(feature_points=fp))
    fapu = fapu_from_model(_variant(feature_points=fp,
                                    fapu_overrides={"ES0": 61.0, "ENS0": 35.0, "IRISD0": 12.0}))
    assert (fapu.ES0, fapu.ENS0, fapu.IRISD0) == (61.0, 35.0, 12.0)


def test_swapped_left_right_labels_are_refused():
    fp = dict(MODEL.feature_points)
    fp["8.3"], fp["8.4"] = fp["8.4"], fp["8.3"]
    with pytest.raises(InputError, match="MW0 .* must be positive"):
        fapu_from_model(_variant(feature_points=fp))


def test_mask_holds_lip_jaw_and_head_faps_only():
    mask = FapEncoder(MODEL).mask
    expected = {*GEOMETRIC_FAPS, 48, 49, 50}
    assert {i + 1 for i in np.flatnonzero(mask)} == expected
    fp = {k: v for k, v in MODEL.feature_points.items() if k != "8.5"}
    assert not FapEncoder(_variant(feature_points=fp)).mask[col("lower_t_lip_lm_o")]


# ----------------------------------------------------------------------------- semantics
def test_opening_the_jaw_raises_open_jaw_and_lowers_the_lower_lip():
    alpha = np.vstack([one("jaw1", a)[0] for a in (0.5, 1.0, 2.0)])
    g0, g = geometry(np.zeros((1, 7))), geometry(alpha)
    unit = fapu_from_model(MODEL).unit("MNS")
    absolute, _ = fap_values(MODEL, alpha, frontal_poses(3), jaw_relative=False)
    relative, _ = fap_values(MODEL, alpha, frontal_poses(3))
    drop = g0["2.1"][:, 1] - g["2.1"][:, 1]  # mm, jaw going down
    assert np.all(drop > 0)
    np.testing.assert_array_equal(absolute[:, col("open_jaw")], np.rint(drop / unit))
    assert np.all(np.diff(absolute[:, col("open_jaw")]) > 0)
    for name in ("raise_b_midlip", "raise_b_lip_lm", "raise_b_lip_rm", "raise_b_midlip_o",
                 "raise_b_lip_lm_o", "raise_b_lip_rm_o", "depress_chin"):
        assert np.all(absolute[:, col(name)] < 0), name  # "raise" is up; the lip goes down
        # relative = absolute + open_jaw (both MNS units), up to rounding
        assert np.all(np.abs(relative[:, col(name)] - absolute[:, col(name)]
                             - absolute[:, col("open_jaw")]) <= 1), name
        assert np.all(np.abs(relative[:, col(name)]) < np.abs(absolute[:, col(name)])), name
    for name in ("lower_t_midlip", "lower_t_midlip_o", "stretch_l_cornerlip", "shift_jaw"):
        assert np.all(relative[:, col(name)] == 0), name  # the upper lip and sides stay


def test_spreading_lips_stretches_both_corners_symmetrically():
    values, _ = fap_values(MODEL, one("lips1", 2.0), frontal_poses(1))
    g0, g = geometry(np.zeros((1, 7))), geometry(one("lips1", 2.0))
    left_move = g["8.3"][0, 0] - g0["8.3"][0, 0]  # +x is the speaker's left
    assert left_move > 0
    v = values[0]
    assert v[col("stretch_l_cornerlip_o")] == np.rint(left_move / fapu_from_model(MODEL).unit("MW"))
    for l_name, r_name in (("stretch_l_cornerlip", "stretch_r_cornerlip"),
                           ("stretch_l_cornerlip_o", "stretch_r_cornerlip_o")):
        assert v[col(l_name)] > 0 and v[col(l_name)] == v[col(r_name)]
    smile, _ = fap_values(MODEL, one("lips4", 1.5), frontal_poses(1))
    assert smile[0, col("raise_l_cornerlip_o")] > 0
    assert smile[0, col("raise_l_cornerlip_o")] == smile[0, col("raise_r_cornerlip_o")]


@pytest.mark.parametrize("axis, fap, check", [
    # pitch down: the face's forward axis turns towards the camera's +y (image down)
    (0, 48, lambda r: (r @ [0, 0, 1])[1] > 0),
    # yaw left: forward turns towards the speaker's left, the image's right (camera +x)
    (1, 49, lambda r: (r @ [0, 0, 1])[0] > 0),
    # roll right: the top of the head tilts to the speaker's right, the image's left
    (2, 50, lambda r: (r @ [0, 1, 0])[0] < 0),
])  # fmt: skip
def test_head_rotation_gives_head_faps_and_no_lip_faps(axis, fap, check):
    angle = 0.2
    rot_head = rotation_matrix(np.eye(3)[axis] * angle)
    pose = head_pose(rot_head)[None]
    assert check(rotation_matrix(pose[0, :3]))
    values, _ = fap_values(MODEL, np.zeros((1, 7)), pose)
    head = values[0, 47:50]
    assert head[fap - 48] == round(angle / AU)
    assert np.all(np.delete(head, fap - 48) == 0)
    steps = np.array([FAP_TABLE[n - 1].quant_step for n in LIP_FAPS])
    assert np.all(np.abs(values[0, LIP_FAPS - 1]) <= steps)
    # articulation under head motion gives the same lip FAPs as without it
    a = np.array([[1.2, -0.7, 0.5, 0.3, 0.8, -0.4, 0.2]])
    moved, _ = fap_values(MODEL, a, pose)
    still, _ = fap_values(MODEL, a, frontal_poses(1))
    np.testing.assert_array_equal(moved[:, LIP_FAPS - 1], still[:, LIP_FAPS - 1])


def test_head_angles_are_relative_to_the_reference():
    rot_ref = axis_angle(rotation_matrix(FRONTAL) @ rotation_matrix([0.0, 0.3, 0.0]))
    pose = head_pose(rotation_matrix([0.0, 0.3, 0.0]) @ rotation_matrix([0.1, 0.0, 0.0]))
    ang = head_angles(pose[None, :3], rot_ref)
    np.testing.assert_allclose(ang, [[0.1, 0.0, 0.0]], atol=1e-9)


@pytest.mark.parametrize("jaw_relative", [True, False])
def test_lip_aperture_and_width_rebuilt_from_faps_within_0_2_mm(rng, jaw_relative):
    s = MODEL.stats
    alpha = rng.uniform(s.min, s.max, size=(200, 7))
    enc = FapEncoder(MODEL, jaw_relative=jaw_relative)
    values, _ = enc.values(alpha, frontal_poses(200))
    rebuilt, truth = reconstruct_feature_points(enc, values), geometry(alpha)
    ap_err = np.abs(lip_aperture(rebuilt) - lip_aperture(truth))
    assert ap_err.max() < 0.2
    assert np.abs(lip_width(rebuilt) - lip_width(truth)).max() < 0.2
    assert np.ptp(lip_aperture(truth)) > 5.0  # the test spans real openings


def test_frame_dict_matches_the_batch():
    enc = FapEncoder(MODEL)
    a, pose = one("jaw1", 1.3), frontal_poses(1)
    d = enc.frame_dict(a[0], pose[0])
    values, mask = enc.values(a, pose)
    assert set(d) == {str(n + 1) for n in np.flatnonzero(mask)}
    assert d["3"] == values[0, 2] > 0 and all(isinstance(v, int) for v in d.values())


def test_values_reject_bad_shapes_and_nan():
    enc = FapEncoder(MODEL)
    with pytest.raises(InputError, match=r"alpha must have shape \(F, 7\)"):
        enc.values(np.zeros(7), frontal_poses(1))
    with pytest.raises(InputError, match=r"pose must have shape \(2, 6\)"):
        enc.values(np.zeros((2, 7)), frontal_poses(1))
    with pytest.raises(InputError, match="finite"):
        enc.values(np.full((1, 7), np.nan), frontal_poses(1))


# ----------------------------------------------------------------------------- file format
def test_writer_output_is_what_every_player_reads(tmp_path):
    values, mask = fap_values(MODEL, np.vstack([one("jaw1", 1.0), one("lips1", -1.0)]),
                              frontal_poses(2))
    write_fap(tmp_path / "t.fap", values, mask, 25, name="my talk\tnow")
    raw = (tmp_path / "t.fap").read_bytes()
    text = raw.decode("ascii")
    lines = text.split("\n")
    assert lines[0] == "2.1 my_talk_now 25 2" and lines[-1] == "" and b"\r" not in raw
    body = lines[1:-1]
    assert len(body) == 4 and all(line and "  " not in line for line in body)
    for i in range(2):
        flags = body[2 * i].split(" ")
        assert len(flags) == N_FAPS and flags[:2] == ["0", "0"]
        vals = body[2 * i + 1].split(" ")
        assert vals[0] == str(i) and len(vals) == 1 + flags.count("1")
        assert all(v.lstrip("-").isdigit() for v in vals)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 12), st.integers(1, 120), st.text(max_size=12),
    st.integers(0, 2**32 - 1), st.booleans(),
)  # fmt: skip
def test_round_trip_is_exact_for_random_tracks(n, fps, name, seed, relative):
    rng = np.random.default_rng(seed)
    alpha = rng.uniform(-3, 3, size=(n, 7))
    rot = rng.normal(scale=0.3, size=(n, 3))
    poses = np.array([np.r_[axis_angle(rotation_matrix(FRONTAL) @ rotation_matrix(r)),
                            rng.normal(size=3) * 20 + [0, 0, 400]] for r in rot])
    values, mask = fap_values(MODEL, alpha, poses, jaw_relative=relative)
    seq = parse_fap(format_fap(values, mask, fps, name))
    assert seq.n_frames == n and seq.fps == fps and seq.version == "2.1"
    np.testing.assert_array_equal(seq.values, values)
    np.testing.assert_array_equal(seq.mask, np.broadcast_to(mask, (n, N_FAPS)))
    assert " " not in seq.name and seq.name


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_round_trip_with_random_masks_per_frame(seed, n):
    rng = np.random.default_rng(seed)
    values = rng.integers(-100000, 100000, size=(n, N_FAPS))
    mask = rng.random((n, N_FAPS)) < 0.5
    mask[:, :2] = False
    values[~mask] = 0
    seq = parse_fap(format_fap(values, mask, 30, "x"))
    np.testing.assert_array_equal(seq.values, values)
    np.testing.assert_array_equal(seq.mask, mask)


def test_writer_refuses_what_players_would_misread():
    values, mask = np.zeros((2, N_FAPS), np.int64), np.zeros(N_FAPS, bool)
    bad_mask = mask.copy()
    bad_mask[0] = True
    with pytest.raises(InputError, match="FAP 1 .* must be masked out"):
        format_fap(values, bad_mask, 25, "x")
    with pytest.raises(InputError, match="must be integers"):
        format_fap(values + 0.5, mask, 25, "x")
    with pytest.raises(InputError, match="fps must be a positive number"):
        format_fap(values, mask, 0, "x")
    with pytest.raises(InputError, match="fps must be a positive number"):
        format_fap(values, mask, float("nan"), "x")


@pytest.mark.parametrize("fps, text", [(25, "25"), (29.97, "29.97"), (30000 / 1001, "29.97"),
                                       (59.94, "59.94"), (12.5, "12.5"), (23.976, "23.976")])
def test_real_frame_rates_are_kept(fps, text):
    values, mask = np.zeros((2, N_FAPS), np.int64), np.zeros(N_FAPS, bool)
    header = format_fap(values, mask, fps, "x").splitlines()[0]
    assert header.split()[2] == text
    assert parse_fap(format_fap(values, mask, fps, "x")).fps == float(text)


def _valid_text() -> list[str]:
    mask = np.zeros(N_FAPS, bool)
    mask[[2, 3, 47]] = True
    values = np.zeros((3, N_FAPS), np.int64)
    values[:, [2, 3, 47]] = [[10, -2, 300], [20, -4, 0], [30, 5, -300]]
    return format_fap(values, mask, 25, "talk.fap").split("\n")[:-1]


def _edit(lines, number, new):
    lines = list(lines)
    if new is None:
        del lines[number - 1]
    else:
        lines[number - 1] = new
    return "\n".join(lines) + "\n"


FLAGS = "0 0 1 1" + " 0" * 43 + " 1" + " 0" * 20


@pytest.mark.parametrize("number, new, line, reason", [
    (1, "2.1 talk.fap 25", 1, "bad header: expected 'version name fps nframes'"),
    (1, "2.1 talk.fap fast 3", 1, "bad header: fps 'fast'"),
    (1, "2.1 talk.fap 25 -3", 1, "bad header: frame count '-3'"),
    (1, "v2 talk.fap 25 3", 1, "bad header: version 'v2'"),
    (2, FLAGS + " 0", 2, "expected 68 mask flags, found 69"),
    (4, FLAGS.rsplit(" ", 1)[0], 4, "expected 68 mask flags, found 67"),
    (2, FLAGS.replace("1", "2", 1), 2, "mask flags must be 0 or 1, found '2'"),
    (3, "0 10 -2.5 300", 3, r"value 2 \('-2.5'\) is not an integer"),
    (3, "0 10 x 300", 3, r"value 2 \('x'\) is not an integer"),
    (5, "2 20 -4 0", 5, "expected frame 1, found frame 2"),
    (5, "1 20 -4", 5, "value count mismatch: the mask flags 3 FAP.*3 value.*has 2"),
    (3, "0  10 -2 300", 3, "fields must be separated by single spaces"),
    (3, "", 3, "blank line"),
    (4, "# a comment", 4, "comment line"),
])  # fmt: skip
def test_malformed_files_name_line_and_reason(number, new, line, reason):
    with pytest.raises(InputError, match=rf"<fap>: line {line}: {reason}"):
        parse_fap(_edit(_valid_text(), number, new))


def test_missing_and_extra_frames_are_reported():
    lines = _valid_text()
    with pytest.raises(InputError, match="line 6: file ends after 2 of 3 frames"):
        parse_fap("\n".join(lines[:5]) + "\n")
    with pytest.raises(InputError, match="line 7: file ends before the values of frame 2"):
        parse_fap("\n".join(lines[:6]) + "\n")
    with pytest.raises(InputError, match="line 8: unexpected content after the last frame"):
        parse_fap("\n".join(lines + ["0 1"]) + "\n")
    with pytest.raises(InputError, match="line 1: empty file"):
        parse_fap("")
    commented = "\n".join(lines[:3] + ["# Xface skips comments"] + lines[3:]) + "\n"
    assert parse_fap(commented, allow_comments=True).n_frames == 3


def test_high_level_faps_of_other_tools_are_counted():
    lines = _valid_text()
    lines[1] = "1" + FLAGS[1:]
    with pytest.raises(InputError, match="line 3: value count mismatch"):
        parse_fap("\n".join(lines) + "\n")
    lines[2] = "0 1 2 0 0 10 -2 300"  # FAP 1 carries 4 integers
    seq = parse_fap("\n".join(lines) + "\n")
    assert seq.mask[0, 0] and seq.values[0, 2] == 10 and seq.values[0, 0] == 0


def test_read_fap_names_the_file(tmp_path):
    path = tmp_path / "bad.fap"
    path.write_text("2.1 x 25 1\n")
    with pytest.raises(InputError, match=r"bad\.fap: line 2: file ends after 0 of 1"):
        read_fap(path)


# ----------------------------------------------------------------------------- export-fap
def _track(tmp_path, n=6, fps=30.0, not_ok=(3,), corrupt=None):
    MODEL.save(tmp_path / "speaker.npz")
    lines = []
    for i in range(n):
        alpha = one("jaw1", 0.3 * i)[0]
        r = TrackResult(frame=i, t=10.0 + i / fps, alpha=alpha,
                        pose=Pose(FRONTAL + [0.0, 0.02 * i, 0.0], [0.0, 0.0, 400.0]),
                        ok=i not in not_ok, reason="" if i not in not_ok else "lost")
        lines.append(json.dumps(r.to_dict(MODEL.param_names)))
    if corrupt is not None:
        lines[corrupt[0]] = corrupt[1]
    (tmp_path / "t.jsonl").write_text("\n".join(lines) + "\n")
    return ["export-fap", str(tmp_path / "t.jsonl"), "--model", str(tmp_path / "speaker.npz"),
            "-o", str(tmp_path / "out.fap")]


def test_export_fap_writes_held_frames_at_the_track_rate(tmp_path, capsys):
    assert main(_track(tmp_path) + ["--name", "my take"]) == 0
    seq = read_fap(tmp_path / "out.fap")
    assert seq.n_frames == 6 and seq.fps == 30 and seq.name == "my_take"
    jaw = seq.values[:, col("open_jaw")]
    assert jaw[3] == jaw[2] and jaw[4] > jaw[2] and np.all(np.diff(jaw[:3]) > 0)
    alpha = np.vstack([one("jaw1", 0.3 * i) for i in range(6)])
    alpha[3] = alpha[2]
    expected, _ = fap_values(MODEL, alpha, np.array(
        [np.r_[FRONTAL + [0, 0.02 * (2 if i == 3 else i), 0], 0, 0, 400] for i in range(6)]))
    np.testing.assert_array_equal(seq.values[:, seq.mask[0]], expected[:, seq.mask[0]])
    assert "1 of 6 track frames not ok" in capsys.readouterr().out


@pytest.mark.parametrize("jitter_ms", [0.0, 0.5])
def test_export_fap_keeps_an_ntsc_track_at_29_97(tmp_path, jitter_ms):
    """A 29.97 fps track (time stamps exact, or rounded to the millisecond as containers give
    them) is one .fap frame per record at 29.97, not resampled to 30."""
    args = _track(tmp_path, n=90, fps=30000 / 1001, not_ok=())
    assert main(args) == 0
    exact = parse_fap((tmp_path / "out.fap").read_text())
    if jitter_ms:
        rows = [json.loads(line) for line in (tmp_path / "t.jsonl").read_text().splitlines()]
        for r in rows:
            r["t"] = round(r["t"], 3)
        (tmp_path / "t.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
        assert main(args) == 0
    seq = parse_fap((tmp_path / "out.fap").read_text())
    assert seq.fps == 29.97 and seq.n_frames == 90
    np.testing.assert_array_equal(seq.values, exact.values)  # every record once, in order
    assert len(np.unique(seq.values[:, 2])) == 90  # open_jaw changes every frame


def test_export_fap_resamples_to_a_given_fps(tmp_path):
    assert main(_track(tmp_path, n=7, not_ok=()) + ["--fps", "15"]) == 0
    seq = read_fap(tmp_path / "out.fap")
    assert seq.n_frames == 4 and seq.fps == 15
    direct = read_fap(tmp_path / "out.fap").values
    main(_track(tmp_path, n=7, not_ok=()))
    np.testing.assert_array_equal(direct, read_fap(tmp_path / "out.fap").values[::2])


@pytest.mark.parametrize("corrupt, message", [
    ((2, "{not json"), "t.jsonl: line 3: not a track record"),
    ((1, '{"frame": 1, "t": 0.1}'), "t.jsonl: line 2: not a track record: missing field 'alpha'"),
    ((2, '{"frame": 2, "t": 10.07, "alpha": {"jaw1": NaN}, "pose": {"rotation": [3, 0, 0], '
         '"translation": [0, 0, 400]}}'), "t.jsonl: line 3: .*alpha values must be finite"),
    ((4, '{"frame": 4, "t": 1, "alpha": {"tongue": 1}, "pose": {}}'),
     r"line 5: not a track record: parameters \['tongue'\] are not in the model"),
    # issue 39: a string time stamp was read as a number and the file passed
    ((0, '{"frame": 0, "t": "0", "alpha": {"jaw1": 0}, "pose": {"rotation": [3, 0, 0], '
         '"translation": [0, 0, 400]}}'),
     r"line 1: not a track record: t must be a number of seconds, not '0'"),
    ((1, '{"frame": 1, "t": 10.03, "alpha": {"jaw1": "0.5"}, "pose": {"rotation": [3, 0, 0], '
         '"translation": [0, 0, 400]}}'),
     r"line 2: not a track record: alpha jaw1 must be a number, not '0.5'"),
    ((1, '{"frame": 1, "t": 10.03, "alpha": {"jaw1": 0}, "pose": {"rotation": ["3", 0, 0], '
         '"translation": [0, 0, 400]}}'),
     r"line 2: not a track record: pose rotation must be 3 numbers, not \['3', 0, 0\]"),
    ((3, '{"frame": 3, "t": 10.1, "alpha": {"jaw1": 0}, "pose": {"rotation": [3, 0, 0], '
         '"translation": [0, 0, 400]}, "quality": {"ok": "false"}}'),
     r"line 4: not a track record: quality ok must be true or false, not 'false'"),
    ((2, '{"frame": 2, "t": 10.07, "alpha": {"jaw1": 0}, "pose": {"rotation": [3, 0, 0], '
         '"translation": [0, 0, 400]}, "quality": {"residual": "0.1"}}'),
     r"line 3: not a track record: quality residual must be a number, not '0.1'"),
])  # fmt: skip
def test_export_fap_reports_malformed_lines(tmp_path, capsys, corrupt, message):
    assert main(_track(tmp_path, corrupt=corrupt)) == 2
    err = capsys.readouterr().err
    assert err.startswith("articast export-fap: error:")
    assert re.search(message, err), err


def test_export_fap_without_time_stamps_needs_fps_and_keeps_every_record(tmp_path, capsys):
    args = _track(tmp_path, n=4, fps=float("inf"), not_ok=())  # every t = 10.0
    assert main(args) == 2
    assert "cannot infer fps from the time stamps" in capsys.readouterr().err
    assert main(args + ["--fps", "25"]) == 0
    seq = read_fap(tmp_path / "out.fap")
    assert seq.n_frames == 4 and seq.fps == 25
    assert np.all(np.diff(seq.values[:, col("open_jaw")]) > 0)


def test_a_lying_frame_count_is_an_error_not_an_allocation():
    lines = _valid_text()
    lines[0] = "2.1 talk.fap 25 999999999999"
    with pytest.raises(InputError, match="line 8: file ends after 3 of 999999999999 frames"):
        parse_fap("\n".join(lines) + "\n")

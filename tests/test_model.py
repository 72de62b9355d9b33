"""FaceModel: geometry, and the file format's round trip and clear errors."""

import json
import zipfile

import numpy as np
import pytest

from articast.core.bundle import save_bundle
from articast.core.errors import InputError, ModelFileError
from articast.core.model.face import FaceModel, ParamStats


def small_model(rng, n=12, k=7):
    return FaceModel(
        mean=rng.normal(size=(n, 3)) * 30,
        basis=rng.normal(size=(k, n, 3)),
        stats=ParamStats(np.zeros(k), np.ones(k), -np.ones(k) * 2.5, np.ones(k) * 2.7),
        point_names=tuple(f"pt{i}" for i in range(n)),
        groups={"jaw_line": [0, 1, 2], "lip_outer": [3, 4, 5, 6], "rest": [7, 8, 9, 10, 11]},
        triangles=[[0, 1, 2], [3, 4, 5]],
        feature_points={"8.3": 3, "8.4": 5, "2.1": 0},
        fapu_overrides={"ES0": 62.0},
        name="unit",
    )


def test_shape_is_linear_and_vectorised(rng):
    m = small_model(rng)
    alphas = rng.normal(size=(4, 5, 7))
    out = m.shape(alphas)
    assert out.shape == (4, 5, 12, 3)
    manual = m.mean + np.einsum("k,knd->nd", alphas[2, 3], m.basis)
    np.testing.assert_allclose(out[2, 3], manual, atol=1e-12)
    np.testing.assert_allclose(m.shape(np.zeros(7)), m.mean)


def test_shape_rejects_wrong_length(rng):
    with pytest.raises(InputError, match=r"alpha must end in \(7,\)"):
        small_model(rng).shape(np.zeros(6))


def test_round_trip_is_exact(rng, tmp_path):
    m = small_model(rng)
    m.save(tmp_path / "m.npz")
    m2 = FaceModel.load(tmp_path / "m.npz")
    assert np.array_equal(m.mean, m2.mean) and np.array_equal(m.basis, m2.basis)
    assert np.array_equal(m.triangles, m2.triangles)
    assert m.point_names == m2.point_names and m.param_names == m2.param_names
    assert dict(m.feature_points) == dict(m2.feature_points)
    assert dict(m.fapu_overrides) == dict(m2.fapu_overrides)
    assert {g: list(v) for g, v in m.groups.items()} == {g: list(v) for g, v in m2.groups.items()}
    for a in ("mean", "std", "min", "max"):
        assert np.array_equal(getattr(m.stats, a), getattr(m2.stats, a))
    assert m2.name == "unit"


def test_model_is_immutable(rng):
    m = small_model(rng)
    with pytest.raises(ValueError):
        m.mean[0, 0] = 1.0


def _rewrite(path, out, **changes):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("__meta__")).decode())
    for k, v in changes.items():
        if k.startswith("meta_"):
            meta[k[5:]] = v
        else:
            arrays[k] = v
    kind, version = meta.pop("kind"), meta.pop("version")
    save_bundle(out, kind, version, arrays, meta)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"meta_version": 99}, "format version 99 is not supported"),
        ({"meta_kind": "posture-corpus"}, "expected an articast face-model file"),
        ({"basis": np.zeros((7, 11, 3))}, r"basis has shape \(7, 11, 3\), expected \(K, 12, 3\)"),
        ({"mean": np.full((12, 3), np.nan)}, "NaN or infinite"),
        ({"triangles": np.array([[0, 1, 99]])}, "triangles index points that do not exist"),
        ({"meta_point_names": ["a"]}, "1 point names for 12 points"),
    ],
)
def test_malformed_files_get_one_clear_error(rng, tmp_path, changes, message):
    small_model(rng).save(tmp_path / "ok.npz")
    _rewrite(tmp_path / "ok.npz", tmp_path / "bad.npz", **changes)
    with pytest.raises(ModelFileError, match=message):
        FaceModel.load(tmp_path / "bad.npz")


def test_truncated_and_foreign_files(rng, tmp_path):
    small_model(rng).save(tmp_path / "ok.npz")
    data = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "trunc.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="truncated or not an npz"):
        FaceModel.load(tmp_path / "trunc.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(ModelFileError, match="truncated or not an npz"):
        FaceModel.load(tmp_path / "text.npz")
    with pytest.raises(ModelFileError, match="no such file"):
        FaceModel.load(tmp_path / "missing.npz")
    with zipfile.ZipFile(tmp_path / "plain.npz", "w") as z:
        z.writestr("x.npy", b"")
    with pytest.raises(ModelFileError):
        FaceModel.load(tmp_path / "plain.npz")

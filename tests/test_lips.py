"""Lip measures (mm) on the fitted geometry: against the synthetic speaker's true lips."""

import numpy as np
import pytest

from articast.core.model.build import invert
from articast.core.model.face import FaceModel
from articast.core.outputs.lips import lip_measures, lips_dict
from articast.core.synthetic.speaker import SyntheticSpeaker


def test_lip_measures_follow_the_true_lips_of_the_synthetic_speaker():
    sp = SyntheticSpeaker(0)
    model = sp.model()
    corpus = sp.corpus()
    alpha = invert(model, corpus.postures)
    ap, wd = lip_measures(model, alpha)
    pts = corpus.postures
    fp = model.feature_points
    ap_true = np.linalg.norm(pts[:, fp["2.2"]] - pts[:, fp["2.3"]], axis=-1)
    wd_true = np.linalg.norm(pts[:, fp["2.4"]] - pts[:, fp["2.5"]], axis=-1)
    # the linear model's own error only: sub-millimetre typically, ~2 mm at the extremes
    assert np.median(np.abs(ap - ap_true)) < 0.5 and np.median(np.abs(wd - wd_true)) < 0.5
    assert np.abs(ap - ap_true).max() < 2.5 and np.abs(wd - wd_true).max() < 2.5
    assert np.corrcoef(ap, ap_true)[0, 1] > 0.98
    names = list(corpus.posture_names)
    # /a/ opens more than a bilabial closure; /i/ is wider than /u/
    assert ap[names.index("a")] > ap[names.index("aba")] + 5
    assert wd[names.index("i")] > wd[names.index("u")] + 5


def test_lips_dict_is_none_without_inner_lip_points_or_finite_alpha():
    sp = SyntheticSpeaker(0)
    model = sp.model()
    assert lips_dict(model, np.full(model.n_params, np.nan)) is None
    bare = FaceModel(model.mean, model.basis)
    assert lips_dict(bare, np.zeros(model.n_params)) is None
    d = lips_dict(model, np.zeros(model.n_params))
    ap, wd = lip_measures(model, np.zeros(model.n_params))
    assert d == {"aperture_mm": round(float(ap), 3), "width_mm": round(float(wd), 3)}


def test_one_frames_lips_in_python_floats_are_numpys_to_the_bit():
    """lips_dict's one-frame path (Python floats: einsum's sums over K from 0.0, the norm's
    squares) gives lip_measures' numpy numbers to the bit, before any rounding."""
    from articast.core.outputs.lips import _lip_measures_one

    sp = SyntheticSpeaker(0)
    model = sp.model()
    rng = np.random.default_rng(2)
    alphas = rng.normal(size=(3000, model.n_params)) * rng.choice([0.05, 1.0, 4.0], (3000, 1))
    ap, wd = lip_measures(model, alphas)
    got = [_lip_measures_one(model, a.tolist()) for a in alphas]
    assert [g[0] for g in got] == ap.tolist() and [g[1] for g in got] == wd.tolist()
    for a in alphas[:50]:  # and the dict of one frame, as before
        x, y = lip_measures(model, a)
        assert lips_dict(model, a) == {"aperture_mm": round(float(x), 3),
                                       "width_mm": round(float(y), 3)}


def test_the_compiled_lips_lengths_are_the_python_floats_to_the_bit():
    """lip_lengths (lips_dict's one-frame path where numba is) gives _lip_measures_one's
    numbers (the Python-float reference) to the bit, and says where an alpha is not
    finite."""
    from articast.core.outputs import lips as L

    if not L.AVAILABLE:
        pytest.skip("no compiled kernels (numba missing or ARTICAST_JIT=0)")
    model = SyntheticSpeaker(0).model()
    rows = L._lip_rows(model)[3]
    rng = np.random.default_rng(4)
    alphas = rng.normal(size=(3000, model.n_params)) * rng.choice([0.05, 1.0, 4.0, 40.0],
                                                                  (3000, 1))
    for a in alphas:
        ok, ap, wd = L.lip_lengths(rows, a)
        assert ok and (ap, wd) == L._lip_measures_one(model, a.tolist())
    a = alphas[0].copy()
    a[-1] = np.inf
    assert not L.lip_lengths(rows, a)[0] and lips_dict(model, a) is None

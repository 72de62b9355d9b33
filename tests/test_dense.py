"""Loop subdivision and the synthetic speaker's dense face."""

import numpy as np

from articast.core.dense.subdivide import loop_subdivide
from articast.core.synthetic import default_speaker
from articast.core.synthetic.dense import dense_face


def test_loop_subdivision_counts_and_smooths():
    # a unit octahedron: subdivision converges towards a smooth blob inside it
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    t = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    v2, t2 = loop_subdivide(v, t, 2)
    assert len(t2) == 8 * 16
    assert len(v2) == 6 + 12 + 48  # V - E + F = 2 on a closed mesh
    r = np.linalg.norm(v2, axis=1)
    assert r.max() < 1.0  # approximating scheme: pulled inside the hull

    def roundness(steps):
        rr = np.linalg.norm(loop_subdivide(v, t, steps)[0], axis=1)
        return rr.std() / rr.mean()

    assert roundness(3) < roundness(1)  # converging to a smooth surface


def test_dense_face_is_denser_and_its_modes_move_with_the_jaw():
    m = default_speaker(0).model()
    d = dense_face(m)
    assert len(d.mean) > 10 * m.n_points and d.modes.shape == (7, len(d.mean), 3)
    jaw = m.group("jaw_line")
    # the chin region of the dense mesh moves down with jaw1 like the sparse jaw line
    low = d.mean[:, 1] < m.mean[jaw, 1].max()
    assert d.modes[0, low, 1].mean() < 0 and m.basis[0, jaw, 1].mean() < 0
    assert d.linearity_error_mm < 1.5


def test_dense_face_labels_lips_and_adds_teeth_and_a_mouth_cavity():
    from articast.core.dense.mouth import LABELS

    m = default_speaker(1).model()
    d = dense_face(m)
    assert LABELS == ("skin", "lips", "teeth", "mouth")
    assert d.labels.shape == (len(d.mean),) and set(np.unique(d.labels)) == {0, 1, 2, 3}
    lips, teeth, mouth = (d.mean[d.labels == v] for v in (1, 2, 3))
    # the lip points lie around the mouth: between the corners, near the lip heights
    x_corners = sorted([m.mean[m.point("8.3"), 0], m.mean[m.point("8.4"), 0]])
    assert x_corners[0] - 3 < lips[:, 0].min() and lips[:, 0].max() < x_corners[1] + 3
    assert np.all(np.abs(lips[:, 1] - m.mean[m.point("2.2"), 1]) < 20)
    # teeth and cavity sit behind the lips
    assert teeth[:, 2].max() < lips[:, 2].max() and mouth[:, 2].min() < teeth[:, 2].min()
    # opening the jaw lowers the lower teeth, the upper teeth stay with the skull
    k = m.param_names.index("jaw1")
    move = d.modes[k][d.labels == 2]
    assert (move[:, 1] < -0.5).sum() > 0 and (np.abs(move).sum(1) == 0).sum() > 0
    # every triangle indexes points of the face
    assert d.triangles.max() < len(d.mean) and d.triangles.min() >= 0
    doc = d.to_dict()
    assert len(doc["labels"]) == doc["n_points"] and doc["label_names"] == list(LABELS)

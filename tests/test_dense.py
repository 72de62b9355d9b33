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

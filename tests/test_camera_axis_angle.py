"""axis_angle must invert rotation_matrix, also within 1e-4 rad of a half turn."""

import numpy as np
import pytest

from articast.core.model.camera import axis_angle, rotation_matrix


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, -1, 0], [-1, 1, 0], [0.3, -0.2, -0.9]])
@pytest.mark.parametrize("gap", [0.0, 3e-5, 1e-3, 0.5])
def test_axis_angle_round_trips_near_a_half_turn(axis, gap):
    r = np.asarray(axis, float) / np.linalg.norm(axis) * (np.pi - gap)
    back = rotation_matrix(axis_angle(rotation_matrix(r)))
    np.testing.assert_allclose(back, rotation_matrix(r), atol=1e-9)

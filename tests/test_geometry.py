import numpy as np
import pytest

from vio_graph.geometry import (
    matrix_from_quat_wxyz,
    pitch_of,
    quat_wxyz_from_matrix,
    remove_yaw,
    rot_x,
    rot_y,
    rot_z,
)


@pytest.mark.parametrize("pitch", [-3.0, -1.6, -0.5, 0.0, 0.7, 1.57, 2.0, 3.1])
@pytest.mark.parametrize("yaw", [-2.5, 0.0, 0.3])
def test_remove_yaw_keeps_pitch_for_any_pitch(pitch: float, yaw: float) -> None:
    R = rot_z(yaw) @ rot_y(pitch) @ rot_x(0.02)
    Rg = remove_yaw(R)
    np.testing.assert_allclose(Rg, rot_y(pitch) @ rot_x(0.02), atol=1e-9)
    assert abs(pitch_of(Rg) - pitch) < 1e-9 or abs(abs(pitch_of(Rg) - pitch) - 2 * np.pi) < 1e-9


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = rot_z(rng.uniform(-3, 3)) @ rot_y(rng.uniform(-3, 3)) @ rot_x(rng.uniform(-3, 3))
        q = quat_wxyz_from_matrix(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(matrix_from_quat_wxyz(q), R, atol=1e-12)


def test_rot_y_sign_convention() -> None:
    # a positive pitch tilts the body z axis towards world +x (knee ahead of ankle)
    assert rot_y(0.3)[0, 2] > 0 and rot_y(0.3)[2, 0] < 0

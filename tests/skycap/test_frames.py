import numpy as np
import pytest

from skycap import frames as F


def test_camera_looking_forward_projects_ahead_to_centre():
    K = F.intrinsics_matrix(500, 500, 320, 240)
    # Drone at origin, yaw 90 deg (facing east), camera level: a point 10 m east is at the image centre.
    R = F.R_world_body_from_euler(0.0, 0.0, np.pi / 2)
    T = F.T_world_cam_from_pose(np.zeros(3), R)
    uv, z = F.project_points(K, T, np.array([0.0, 10.0, 0.0]))
    assert z == pytest.approx(10.0)
    assert np.allclose(uv, [320, 240])
    # A point south of the line of sight (to the right when facing east) projects right of centre,
    # a point above (negative down) projects above the centre.
    uv, _ = F.project_points(K, T, np.array([[-1.0, 10.0, 0.0], [0.0, 10.0, -1.0]]))
    assert uv[0, 0] == pytest.approx(370) and uv[1, 1] == pytest.approx(190)


def test_gimbal_pitch_down_looks_at_ground():
    K = F.intrinsics_matrix(500, 500, 320, 240)
    T = F.T_world_cam_from_pose(np.array([0, 0, -8.0]), np.eye(3), gimbal_pitch_rad=-np.pi / 4)
    uv, z = F.project_points(K, T, np.array([8.0, 0.0, 0.0]))  # 8 m north on the ground, 8 m below
    assert np.allclose(uv, [320, 240]) and z == pytest.approx(8 * np.sqrt(2))


def test_inverse_and_euler_round_trip():
    R = F.R_world_body_from_euler(0.1, -0.2, 2.5)
    assert np.allclose(F.euler_from_R_world_body(R), (0.1, -0.2, 2.5))
    T = F.make_T(R, [1, 2, 3])
    assert np.allclose(F.invert_T(T) @ T, np.eye(4))


def test_conversions_are_proper_rotations_and_inverse():
    for M in (F.R_YUP_NED,):
        assert np.isclose(np.linalg.det(M), 1.0)
    p = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(F.yup_to_ned(F.ned_to_yup(p)), p)
    assert np.allclose(F.enu_to_ned(F.ned_to_enu(p)), p)
    assert np.allclose(F.ned_to_yup([0, 0, -1]), [0, 1, 0])  # up is up


def test_geodetic_round_trip():
    ned = np.array([[100.0, -50.0, -20.0]])
    lat, lon, alt = F.ned_to_geodetic(ned, 47.39, 8.54, 488.0)
    assert np.allclose(F.geodetic_to_ned(lat, lon, alt, 47.39, 8.54, 488.0), ned, atol=1e-6)
    assert alt[0] == pytest.approx(508.0)

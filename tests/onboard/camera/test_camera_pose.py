"""The pose of a real camera's frame from the vehicle's reported states and the gimbal's reports."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.camera.pose import CameraPoser
from skycap.frames import R_from_quat_wxyz, T_world_cam_mount, quat_wxyz_from_R
from scipy.spatial.transform import Rotation


def _state(t_ns, p, yaw_rad, roll_rad=0.0):
    R = Rotation.from_euler("ZYX", [yaw_rad, 0.0, roll_rad]).as_matrix()
    return SimpleNamespace(header=SimpleNamespace(t_measurement_ns=t_ns), position_ned_m=tuple(p),
                           q_world_body=quat_wxyz_from_R(R))


def _gimbal(t_ns, pitch, yaw=0.0):
    return SimpleNamespace(header=SimpleNamespace(t_measurement_ns=t_ns), pitch_rad=pitch, yaw_rad=yaw)


def test_gimbal_mount_looks_along_the_heading_at_the_reported_pitch():
    T = T_world_cam_mount((1.0, 2.0, -10.0), quat_wxyz_from_R(Rotation.from_euler("ZYX", [math.pi / 2, 0.1, 0.2]).as_matrix()),
                          "gimbal", -math.pi / 2 + 1e-9)
    np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-6)  # straight down despite the body's roll and pitch
    T = T_world_cam_mount((0, 0, -10.0), quat_wxyz_from_R(Rotation.from_euler("Z", math.pi / 2).as_matrix()), "gimbal", 0.0)
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-9)  # heading east, level: optical axis east
    with pytest.raises(ValueError, match="mount"):
        T_world_cam_mount((0, 0, 0), (1, 0, 0, 0), "tripod", 0.0)


def test_fixed_mount_turns_with_the_body_and_the_lever_arm_too():
    q = quat_wxyz_from_R(Rotation.from_euler("ZYX", [0.0, 0.0, 0.3]).as_matrix())  # rolled 0.3 rad
    T = T_world_cam_mount((0, 0, -5.0), q, "fixed", 0.0, lever_arm_body_m=(0.0, 0.0, 0.2))
    R_wb = R_from_quat_wxyz(q)
    np.testing.assert_allclose(T[:3, 3], np.array([0, 0, -5.0]) + R_wb @ [0, 0, 0.2])
    np.testing.assert_allclose(T[:3, 0], R_wb @ [0, 1, 0], atol=1e-9)  # image x = body right, rolled


def test_poser_interpolates_states_and_gimbal_at_the_capture_time():
    poser = CameraPoser("gimbal", pitch_rad=-0.3)
    assert poser.T_world_cam(1_000) is None  # nothing known yet
    poser.add_state(_state(1_000_000_000, (0.0, 0.0, -10.0), 0.0))
    poser.add_state(_state(1_100_000_000, (1.0, 0.0, -10.0), 0.2))
    T = poser.T_world_cam(1_050_000_000)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0.0, -10.0])
    heading = math.atan2(T[1, 2], T[0, 2])
    assert heading == pytest.approx(0.1, abs=1e-9)
    assert math.asin(-T[2, 2]) == pytest.approx(-0.3, abs=1e-9)  # optical axis down 0.3 rad: the configured pitch
    poser.add_gimbal(_gimbal(1_000_000_000, -0.5))
    poser.add_gimbal(_gimbal(1_100_000_000, -0.7, 0.1))
    T = poser.T_world_cam(1_050_000_000)
    assert math.asin(-T[2, 2]) == pytest.approx(-0.6, abs=1e-9)
    assert math.atan2(T[1, 2], T[0, 2]) == pytest.approx(0.1 + 0.05, abs=1e-9)
    # a frame before the history or well after the newest state has no pose
    assert poser.T_world_cam(900_000_000) is None
    assert poser.T_world_cam(1_100_000_000 + 300_000_000) is None
    assert poser.T_world_cam(1_100_000_000 + 100_000_000) is not None  # held for a short while


def test_poser_ignores_out_of_order_and_nan_and_forgets_old_history():
    poser = CameraPoser("fixed", pitch_rad=-0.2, history_s=1.0)
    poser.add_state(_state(2_000_000_000, (0, 0, -3.0), 0.0))
    poser.add_state(_state(1_500_000_000, (9, 9, -3.0), 0.0))  # out of order: ignored
    poser.add_state(_state(2_100_000_000, (float("nan"), 0, -3.0), 0.0))  # NaN: ignored
    poser.add_state(_state(3_500_000_000, (1, 0, -3.0), 0.0))
    assert poser.T_world_cam(2_000_000_000) is None  # older than the 1 s history
    np.testing.assert_allclose(poser.T_world_cam(3_500_000_000)[:3, 3], [1, 0, -3.0])
    with pytest.raises(ValueError, match="mount"):
        CameraPoser("tripod", 0.0)

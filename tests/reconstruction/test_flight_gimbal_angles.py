"""The flight reader's camera poses follow the gimbal's recorded reports (``gimbal`` topic) when there are any,
interpolated at each pose time; without them, ``camera_info``'s gimbal angles as before."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstruction.flight import read_drone_log
from skycap.frames import T_world_cam_from_pose

T0 = 1_767_225_600_000_000_000


def _write(path, with_gimbal: bool) -> None:
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, GimbalAttitude, Header, Keypoints2D, PersonKeypoints, VehicleState

    def hdr(t, seq=0):
        return Header(schema_version=1, sender_id="drone_1", t_measurement_ns=int(t), t_sent_ns=int(t), seq=seq)

    with Recorder(path, node_id="drone_1") as rec:
        rec.record_message("camera_info", CameraInfo(header=hdr(T0), camera_id="cam0", width_px=640, height_px=480,
                           fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=240.0, gimbal_pitch_rad=-0.3), T0)  # fmt: skip
        for k in range(51):  # 50 Hz for 1 s
            t = T0 + k * 20_000_000
            rec.record_message("state", VehicleState(header=hdr(t, k), position_ned_m=(0.0, 0.0, -5.0),
                               velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0)), t)  # fmt: skip
        if with_gimbal:
            for k in range(11):  # 10 Hz: pitch -0.2 -> -0.6, yaw across +-pi (unwrapped when interpolating)
                t = T0 + k * 100_000_000
                rec.record_message("gimbal", GimbalAttitude(
                    header=hdr(t, k), gimbal_id=1, roll_rad=0.0, pitch_rad=-0.2 - 0.04 * k,
                    yaw_rad=math.remainder(3.0 + 0.04 * k, 2 * math.pi), yaw_north_rad=0.0), t)  # fmt: skip
        person = PersonKeypoints(keypoints_px=(320.0, 240.0) * 17, confidence=(1.0,) * 17)
        rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(T0 + 500_000_000), camera_id="cam0",
                           frame_index=0, detector="sim", simulated=True, persons=[person]), T0 + 500_000_000)  # fmt: skip


def test_poses_use_the_recorded_gimbal_reports(tmp_path):
    _write(tmp_path / "drone_1.s001.mcap", with_gimbal=True)
    cam = read_drone_log(tmp_path / "drone_1.s001.mcap")
    k = 12  # 240 ms: between the reports at 200 and 300 ms
    assert cam.t_pose_ns[k] == T0 + 240_000_000
    pitch, yaw = -0.2 - 0.04 * 2.4, 3.0 + 0.04 * 2.4
    expected = T_world_cam_from_pose(np.array([0.0, 0.0, -5.0]), np.eye(3), pitch, yaw, None)
    assert np.allclose(cam.T_world_cam[k], expected, atol=1e-9)
    # held at the ends
    assert np.allclose(cam.T_world_cam[-1], T_world_cam_from_pose(np.array([0.0, 0.0, -5.0]), np.eye(3), -0.6,
                                                                    3.4, None), atol=1e-9)


def test_without_gimbal_reports_camera_info_angles(tmp_path):
    _write(tmp_path / "drone_1.s001.mcap", with_gimbal=False)
    cam = read_drone_log(tmp_path / "drone_1.s001.mcap")
    expected = T_world_cam_from_pose(np.array([0.0, 0.0, -5.0]), np.eye(3), -0.3, 0.0, None)
    assert np.allclose(cam.T_world_cam[7], expected) and cam.T_world_cam.shape == (51, 4, 4)
    assert pytest.approx(cam.t_pose_ns[7]) == T0 + 140_000_000

"""Gimbal reports whose clock slipped behind the wall clock (the simulator falling behind real time under load) are
re-timed by their send times, so the camera pitch taken at a frame is the one at that frame (a demo flight's gimbal
reports were stamped up to 32 s early: the camera tilt was wrong by 1-2 degrees, the person's root by ~0.1 m)."""

from __future__ import annotations

import numpy as np

from reconstruction.flight import read_drone_log, report_times_ns
from skycap.frames import T_world_cam_from_pose

T0 = 1_767_225_600_000_000_000
MS = 1_000_000


def test_consistent_stamps_are_kept():
    t = T0 + np.arange(20) * 100 * MS
    sent = t + np.array([3, 5, 2, 40, 7] * 4) * MS  # transport jitter within the tolerance
    assert np.array_equal(report_times_ns(t, sent, max_delay_s=0.1), t)


def test_slipped_stamps_follow_the_send_time():
    t_true = T0 + np.arange(50) * 100 * MS
    slip = np.arange(50) * 40 * MS  # the stamping clock loses 0.4 s per second
    t_meas = t_true - slip
    sent = t_true + 2 * MS
    out = report_times_ns(t_meas, sent, max_delay_s=0.1)
    assert np.all(out >= t_meas) and np.all(out <= sent)
    # within the tolerance of the true time (the first ones, slipped by less than the tolerance, keep their stamp)
    assert np.max(np.abs(out - t_true)) <= 100 * MS
    assert np.all(np.diff(out) > 0)


def test_without_send_times_nothing_changes():
    t = T0 + np.arange(5) * MS
    assert np.array_equal(report_times_ns(t, np.zeros(5, dtype=np.int64)), t)


def test_reader_takes_the_pitch_at_the_frame_not_seconds_later(tmp_path):
    """A recording whose gimbal reports were stamped 2 s early: the pose at t uses the pitch reported at t."""
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, GimbalAttitude, Header, Keypoints2D, PersonKeypoints, VehicleState

    def hdr(t, seq=0, sent=None):
        return Header(schema_version=1, sender_id="drone_1", t_measurement_ns=int(t),
                      t_sent_ns=int(t if sent is None else sent), seq=seq)

    path = tmp_path / "drone_1.s001.mcap"
    with Recorder(path, node_id="drone_1") as rec:
        rec.record_message("camera_info", CameraInfo(header=hdr(T0), camera_id="cam0", width_px=640, height_px=480,
                           fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=240.0, gimbal_pitch_rad=-0.3), T0)  # fmt: skip
        for k in range(201):  # 50 Hz for 4 s
            t = T0 + k * 20 * MS
            rec.record_message("state", VehicleState(header=hdr(t, k), position_ned_m=(0.0, 0.0, -5.0),
                               velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0)), t)  # fmt: skip
        for k in range(41):  # 10 Hz: the pitch steps from -0.3 to -0.6 at 2 s; stamps slip to 2 s early
            t = T0 + k * 100 * MS
            slip = 0 if k < 10 else (k - 10) * 100 * MS * 2 // 3  # grows up to 2 s
            pitch = -0.3 if k < 20 else -0.6
            rec.record_message("gimbal", GimbalAttitude(header=hdr(t - slip, k, sent=t + MS), gimbal_id=1,
                               roll_rad=0.0, pitch_rad=pitch, yaw_rad=0.0, yaw_north_rad=0.0), t)  # fmt: skip
        person = PersonKeypoints(keypoints_px=(320.0, 240.0) * 17, confidence=(1.0,) * 17)
        rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(T0 + 500 * MS), camera_id="cam0",
                           frame_index=0, detector="sim", simulated=True, persons=[person]), T0 + 500 * MS)  # fmt: skip
    cam = read_drone_log(path)
    at = {int(round((t - T0) / MS)): T for t, T in zip(cam.t_pose_ns, cam.T_world_cam)}
    p = np.array([0.0, 0.0, -5.0])
    # at 1.6 s the gimbal still pointed at -0.3 (the report stamped 1.6 - 0.4 s said so); with the stamps as
    # recorded the -0.6 of the report sent at 2.0 s (stamped 1.33 s) would already be in force
    assert np.allclose(at[1600], T_world_cam_from_pose(p, np.eye(3), -0.3, 0.0, None), atol=1e-9)
    assert np.allclose(at[3000], T_world_cam_from_pose(p, np.eye(3), -0.6, 0.0, None), atol=1e-9)


def test_a_single_late_publication_keeps_its_stamp():
    t = T0 + np.arange(30) * 100 * MS
    sent = t + 2 * MS
    sent[10] += 600 * MS  # the agent was busy once
    assert np.array_equal(report_times_ns(t, sent), t)

"""The ablation's substitutions and error figures (evaluation.ablation), as plain functions on synthetic cameras."""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.ablation import (AblationError, camera_rotation, estimate_time_lag_s, exact_keypoints, pan_tilt_roll,
                                 pose_errors, substitute_poses)
from reconstruction.capture import CameraCapture
from skycap.frames import T_world_cam_from_pose, intrinsics_matrix

T0 = 1_767_225_600_000_000_000


def _track(n=101, dt_ms=20, yaw0=np.pi, pitch=-0.6, yaw_err=0.0, pitch_err=0.0, pos_err=(0.0, 0.0, 0.0)):
    t = T0 + np.arange(n, dtype=np.int64) * dt_ms * 1_000_000
    s = (t - T0) * 1e-9
    T = []
    for k, tk in enumerate(s):
        yaw = yaw0 + 0.3 * tk + yaw_err
        c, si = np.cos(yaw), np.sin(yaw)
        R_yaw = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
        p = np.array([8 * np.cos(0.3 * tk), 8 * np.sin(0.3 * tk), -6.0]) + np.asarray(pos_err)
        T.append(T_world_cam_from_pose(p, R_yaw, pitch + pitch_err, 0.0, None))
    return t, np.stack(T)


def _cam(t, T, frames=None):
    frames = t[::5] if frames is None else frames
    F = len(frames)
    return CameraCapture(name="drone_1", t_pose_ns=t, T_world_cam=T, pos_sigma_m=0.03, rot_sigma_deg=1.0,
                         t_intrinsics_ns=t[:1], K=intrinsics_matrix(500.0, 500.0, 320.0, 240.0), width_px=640,
                         height_px=480, t_frame_ns=frames, keypoints_px=np.zeros((F, 1, 17, 2)),
                         confidence=np.ones((F, 1, 17)))  # fmt: skip


def test_pan_tilt_roll_round_trip_and_meaning():
    _, T = _track(n=3, pitch=-0.6)
    ptr = pan_tilt_roll(T[:, :3, :3])
    assert np.allclose(ptr[:, 1], -0.6) and np.allclose(ptr[:, 2], 0.0, atol=1e-9)
    assert np.allclose(np.cos(ptr[:, 0] - np.pi - 0.3 * np.arange(3) * 0.02), 1.0)
    assert np.allclose(camera_rotation(ptr), T[:, :3, :3], atol=1e-12)


@pytest.mark.parametrize("which", ["tilt", "pan", "true"])
def test_substitute_attitude_parts(which):
    t, T_true = _track()
    _, T_rec = _track(yaw_err=0.02, pitch_err=-0.03, pos_err=(0.1, 0.0, 0.0))
    cam = substitute_poses(_cam(t, T_rec), t, T_true, position=False, attitude=which)
    d = pan_tilt_roll(cam.T_world_cam[:, :3, :3]) - pan_tilt_roll(T_true[:, :3, :3])
    pan_ok, tilt_ok = np.allclose(d[:, 0], 0, atol=1e-9), np.allclose(d[:, 1], 0, atol=1e-9)
    assert (pan_ok, tilt_ok) == {"tilt": (False, True), "pan": (True, False), "true": (True, True)}[which]
    assert np.allclose(cam.T_world_cam[:, :3, 3], T_rec[:, :3, 3])  # positions kept
    cam = substitute_poses(_cam(t, T_rec), t, T_true, position=True, attitude="recorded")
    assert np.allclose(cam.T_world_cam[:, :3, 3], T_true[:, :3, 3]) and np.allclose(cam.T_world_cam[:, :3, :3],
                                                                                      T_rec[:, :3, :3])
    with pytest.raises(AblationError):
        substitute_poses(_cam(t, T_rec), t, T_true, position=False, attitude="roll")


def test_pose_errors_report_the_injected_errors():
    t, T_true = _track()
    _, T_rec = _track(yaw_err=np.radians(1.0), pitch_err=np.radians(-2.0), pos_err=(0.05, 0.0, 0.0))
    e = pose_errors(_cam(t, T_rec), t, T_true)
    assert e["pan_tilt_roll_err_mean_deg"] == pytest.approx([1.0, -2.0, 0.0], abs=1e-3)
    assert e["pos_err_rms_mm"] == pytest.approx(50.0, abs=0.1)
    assert e["att_err_rms_deg"] == pytest.approx(np.hypot(1.0, 2.0), abs=0.02)


def test_time_lag_is_recovered():
    t = T0 + np.arange(500, dtype=np.int64) * 20_000_000
    s = (t - T0) * 1e-9
    p = np.stack([8 * np.cos(0.3 * s), 8 * np.sin(0.3 * s), -6 + 0 * s], -1)
    v = np.stack([-2.4 * np.sin(0.3 * s), 2.4 * np.cos(0.3 * s), 0 * s], -1)
    lag = 0.05
    rec = np.stack([8 * np.cos(0.3 * (s - lag)), 8 * np.sin(0.3 * (s - lag)), -6 + 0 * s], -1) + [0.01, -0.02, 0.0]
    got, b = estimate_time_lag_s(t, rec, t, p, v)
    assert got == pytest.approx(lag, abs=2e-3) and np.allclose(b, [0.01, -0.02, 0.0], atol=3e-3)


def test_exact_keypoints_project_the_true_joints():
    t, T_true = _track()
    rng = np.random.default_rng(0)
    joints = np.broadcast_to(rng.normal(0.0, 0.3, (17, 3)) + [0.0, 0.0, -1.0], (len(t), 17, 3)).copy()
    cam = _cam(t, T_true)
    cam.confidence[0, 0, 5] = 0.0  # not detected: stays missing
    out = exact_keypoints(cam, t, T_true, joints)
    assert out.confidence[0, 0, 5] == 0.0 and out.confidence[1, 0, 5] == 1.0
    for f in (0, 3):
        uv = out.project(joints[0], f, T_world_cam=cam.pose_at(cam.t_frame_ns[f:f + 1])[0])
        ok = out.confidence[f, 0] > 0
        assert np.allclose(uv[ok], out.keypoints_px[f, 0][ok], atol=1e-6)
    assert not np.allclose(out.keypoints_px, 0.0)



def test_joint_offsets_split_a_constant_offset_from_noise():
    from evaluation.ablation import joint_offsets_body_frame

    rng = np.random.default_rng(1)
    T = 200
    heading = np.linspace(0, 2 * np.pi, T)  # the person turns: a body-frame offset is not a world one
    gt = rng.normal(0, 0.3, (17, 3))[None].repeat(T, 0)
    fwd = np.stack([np.cos(heading), np.sin(heading), 0 * heading], -1)
    left = np.stack([np.sin(heading), -np.cos(heading), 0 * heading], -1)  # fwd x down... left in NED
    gt[:, 11] = 0.1 * left  # hips: left hip to the left of the right hip
    gt[:, 12] = -0.1 * left
    pred = gt.copy()
    pred[:, 9] += 0.03 * fwd  # the left wrist 30 mm forward of the truth, whichever way the person faces
    pred[:, 0] += rng.normal(0, 0.01, (T, 3))  # the nose: noise only
    out = joint_offsets_body_frame(pred, gt)
    assert out["left_wrist"]["offset_fwd_left_up_mm"] == pytest.approx([30.0, 0.0, 0.0], abs=0.5)
    assert out["left_wrist"]["varying_rms_mm"] < 0.5
    assert out["nose"]["offset_mm"] < 3.0 and 12.0 < out["nose"]["varying_rms_mm"] < 22.0

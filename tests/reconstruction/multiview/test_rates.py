"""The drones' velocity and angular-velocity channels: capture contract, synthetic truth, the fused camera
track (pure least squares, checked against the noise it must average) and their use in the product fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from reconstruction.capture import Capture, CameraCapture, CaptureError
from reconstruction.multiview.fit import FitConfig, fit_capture
from reconstruction.multiview.observations import fuse_rates, smooth_poses
from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture, true_rates
from skycap.frames import make_T


def _orbit(P: int = 400, rate_hz: float = 50.0):
    """A camera circling at 1 m/s on an 8 m orbit, yawing with it and nodding slowly: (t_ns, T (P, 4, 4))."""
    t = np.arange(P) / rate_hz
    ang = t / 8.0
    pos = np.stack([8 * np.cos(ang), 8 * np.sin(ang), -8.0 + 0.3 * np.sin(0.5 * t)], -1)
    R = Rotation.from_euler("zyx", np.stack([ang + np.pi, 0.2 * np.sin(0.7 * t), 0.1 * np.cos(0.3 * t)], -1)).as_matrix()
    return (t * 1e9).astype(np.int64), make_T(R, pos)


def test_true_rates_integrate_back_to_the_track():
    t_ns, T = _orbit()
    t = t_ns * 1e-9
    v, w = true_rates(t, T)
    R = Rotation.from_matrix(T[:, :3, :3])
    # forward model of the angular velocity is exact: R[k+1] = R[k] exp(w[k] dt)
    R_next = R[:-1] * Rotation.from_rotvec(w[:-1] * np.diff(t)[:, None])
    assert np.max((R_next * R[1:].inv()).magnitude()) < 1e-9
    disp = np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], axis=0)
    np.testing.assert_allclose(disp, T[-1, :3, 3] - T[0, :3, 3], atol=2e-3)


def test_cumulative_rotations_compose_the_steps_in_order():
    """The prefix scan of the fit's gyro integration equals composing the steps one by one (non-commuting steps,
    lengths that are and are not powers of two, and none)."""
    from reconstruction.multiview.fit import _cumulative_rotations

    rng = np.random.default_rng(1)
    for n in (0, 1, 5, 64, 301):
        steps = Rotation.from_rotvec(rng.normal(0.0, 0.3, (n, 3)).reshape(n, 3))
        G = _cumulative_rotations(steps)
        R = np.eye(3)
        ref = [R]
        for k in range(n):
            R = R @ steps[k].as_matrix()
            ref.append(R)
        np.testing.assert_allclose(G.as_matrix(), np.array(ref), atol=1e-12)


def test_fused_track_averages_white_pose_noise_over_the_whole_track():
    rng = np.random.default_rng(0)
    t_ns, T = _orbit()
    P = len(t_ns)
    v, w = true_rates(t_ns * 1e-9, T)
    s_p, s_r = 0.5, np.radians(2.0)  # RMS 3D, white per sample (the harness default)
    noisy = make_T(Rotation.from_rotvec(rng.normal(0, s_r / np.sqrt(3), (P, 3))).as_matrix() @ T[:, :3, :3],
                   T[:, :3, 3] + rng.normal(0, s_p / np.sqrt(3), (P, 3)))  # fmt: skip
    bias = np.radians([0.02, -0.01, 0.015])
    fused = fuse_rates(t_ns, noisy, np.full(P, s_p), np.full(P, s_r), v + rng.normal(0, 0.01, v.shape), np.full(P, 0.02),
                       w + bias + rng.normal(0, np.radians(0.1), w.shape), np.full(P, np.radians(0.2)))  # fmt: skip
    sg = smooth_poses(t_ns, noisy, 6.0, 2)
    pos_err = lambda X: np.sqrt(np.mean(np.sum((X[:, :3, 3] - T[:, :3, 3]) ** 2, -1)))  # noqa: E731
    rot_err = lambda X: np.sqrt(np.mean((Rotation.from_matrix(X[:, :3, :3]) * Rotation.from_matrix(T[:, :3, :3]).inv()).magnitude() ** 2))  # noqa: E731
    # precise rates leave only a constant offset, the mean of P white samples: RMS s / sqrt(P)
    assert pos_err(fused) < 2.5 * s_p / np.sqrt(P)
    assert rot_err(fused) < 2.5 * s_r / np.sqrt(P)
    assert pos_err(fused) < 0.8 * pos_err(sg) and rot_err(fused) < 0.8 * rot_err(sg)


def test_capture_rates_round_trip_and_validation(tmp_path):
    J, t_ns, *_ = procedural_walker(12)
    cap, _ = synthesize_capture(J, t_ns, SynthConfig(drones=2), seed=1)
    c = cap.cameras[0]
    assert c.has_velocity and c.has_angular_velocity
    back = Capture.load(cap.save(tmp_path / "cap.npz"))
    np.testing.assert_array_equal(back.cameras[0].vel_world_mps, c.vel_world_mps)
    np.testing.assert_array_equal(back.cameras[1].omega_sigma_radps, cap.cameras[1].omega_sigma_radps)
    plain, _ = synthesize_capture(J, t_ns, SynthConfig(drones=2, imu_rates=False), seed=1)
    assert not plain.cameras[0].has_velocity
    np.testing.assert_array_equal(plain.cameras[0].keypoints_px, c.keypoints_px)  # same seed, same draws
    assert Capture.load(plain.save(tmp_path / "plain.npz")).cameras[0].vel_world_mps is None
    kw = dict(name="a", t_pose_ns=c.t_pose_ns, T_world_cam=c.T_world_cam, pos_sigma_m=0.5, rot_sigma_deg=2.0,
              t_intrinsics_ns=c.t_intrinsics_ns, K=c.K, width_px=c.width_px, height_px=c.height_px,
              t_frame_ns=c.t_frame_ns, keypoints_px=c.keypoints_px, confidence=c.confidence, detectors=c.detectors)  # fmt: skip
    with pytest.raises(CaptureError, match="vel_world_mps must be"):
        CameraCapture(**kw, vel_world_mps=c.vel_world_mps[:-1])
    bad = c.omega_cam_radps.copy()
    bad[3, 1] = np.nan
    with pytest.raises(CaptureError, match="omega_cam_radps holds NaN"):
        CameraCapture(**kw, omega_cam_radps=bad)


def test_product_fit_uses_the_rates():
    """Same capture with and without the rate channels: the rates pull the refined cameras closer."""
    J, t_ns, *_ = procedural_walker(45)
    cfg = SynthConfig(noise_px=2.0, outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0, speed_mps=1.0)
    errs = {}
    for rates in (True, False):
        cap, truth = synthesize_capture(J, t_ns, SynthConfig(**{**cfg.__dict__, "imu_rates": rates}), seed=3)
        res = fit_capture(cap, t_ns, FitConfig(iters=120), progress=False)
        Tt = np.concatenate(truth.T_world_cam_true_frames)
        e = np.linalg.norm(res.T_world_cam_refined[:, :3, 3] - Tt[:, :3, 3], axis=-1).mean()
        e0 = np.linalg.norm(res.T_world_cam_drone[:, :3, 3] - Tt[:, :3, 3], axis=-1).mean()
        errs[rates] = (e0, e)
    assert errs[True][1] < errs[True][0] and errs[False][1] < errs[False][0]
    assert errs[True][1] < 0.8 * errs[False][1]

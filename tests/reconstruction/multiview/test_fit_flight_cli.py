"""The fits on small synthetic cases, the flight-folder reader (real MCAP files), and the CLIs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reconstruction.capture import Capture, CameraCapture
from reconstruction.metrics import w_mpjpe_mm
from reconstruction.multiview.fit import FitConfig, fit_capture
from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose, intrinsics_matrix, make_T, project_points
from skycap.skeleton import SCORED_JOINTS


def _offset_camera(cap: Capture, ci: int, dp: np.ndarray, yaw_deg: float) -> Capture:
    """Bias camera ``ci``'s drone poses by a world shift ``dp`` and a yaw turn; make it the uncertain one."""
    from scipy.spatial.transform import Rotation

    cams = []
    for i, c in enumerate(cap.cameras):
        T = c.T_world_cam.copy()
        ps, rs = 0.02, 0.2
        if i == ci:
            R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
            T = make_T(R @ T[:, :3, :3], T[:, :3, 3] + dp)
            ps = 1.0  # the drone's attitude is good; its position is not
        cams.append(CameraCapture(c.name, c.t_pose_ns, T, ps, rs, c.t_intrinsics_ns, c.K, c.width_px, c.height_px,
                                  c.t_frame_ns, c.keypoints_px, c.confidence, c.detectors))  # fmt: skip
    return Capture(cams, cap.meta)


@pytest.fixture(scope="module")
def walker_capture():
    J, t_ns, shape, *_ = procedural_walker(36)
    cfg = SynthConfig(noise_px=1.0, outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0, camera_pos_noise_m=0.0,
                      camera_rot_noise_deg=0.0, speed_mps=0.5)  # fmt: skip
    cap, truth = synthesize_capture(J, t_ns, cfg, seed=2)
    # shift camera 1 across its line of sight (a shift along it only changes the apparent size)
    view = truth.T_world_cam_true[1][0][:3, 2]
    across = np.cross(view, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    return J, t_ns, shape, _offset_camera(cap, 1, 0.45 * across + np.array([0, 0, 0.2]), 0.0), truth


def test_product_fit_recovers_pose_and_camera_offset(walker_capture):
    J, t_ns, shape, cap, truth = walker_capture
    res = fit_capture(cap, t_ns, FitConfig(iters=250), progress=False)
    assert w_mpjpe_mm(res.joints_ned, J, SCORED_JOINTS) < 25.0
    np.testing.assert_allclose(res.shape[[1, 2, 6, 7]], shape[[1, 2, 6, 7]], atol=0.02)  # limb lengths
    sel = res.cam_index == 1
    from reconstruction.capture import interpolate_poses

    Tt = interpolate_poses(cap.cameras[1].t_pose_ns, truth.T_world_cam_true[1], res.cam_t_ns[sel])
    before = np.linalg.norm(res.T_world_cam_drone[sel][:, :3, 3] - Tt[:, :3, 3], axis=-1).mean()
    after = np.linalg.norm(res.T_world_cam_refined[sel][:, :3, 3] - Tt[:, :3, 3], axis=-1).mean()
    assert before > 0.45 and after < 0.15


def test_paper_fit_runs_per_frame(walker_capture):
    J, t_ns, _, cap, _ = walker_capture
    cfg = FitConfig(method="paper", paper_first_iters=300, paper_iters=60)
    res = fit_capture(cap, t_ns[:4], cfg, progress=False)
    assert res.joints_ned.shape == (4, 17, 3) and res.T_world_cam_refined.shape == (12, 4, 4)
    assert np.all(np.isfinite(res.joints_ned))
    from reconstruction.metrics import pa_mpjpe_mm

    assert pa_mpjpe_mm(res.joints_ned, J[:4], SCORED_JOINTS) < 60.0


def _write_flight(tmp_path, J, t_ns):
    """Three hovering drones looking at the walker, recorded with the real flight recorder (MCAP)."""
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, Header, Keypoints2D, PersonKeypoints, VehicleState

    K = intrinsics_matrix(1200.0, 1200.0, 640.0, 360.0)
    centre = J[:, 11:13].mean((0, 1))
    truth = []
    for i in range(3):
        ang = 2 * np.pi * i / 3
        pos = centre + np.array([7 * np.cos(ang), 7 * np.sin(ang), 0.0])
        pos[2] = -6.0
        d = centre - pos
        yaw = np.arctan2(d[1], d[0])
        pitch = -np.arctan2(-d[2], np.hypot(d[0], d[1]))  # look down at the hips
        Tc = T_world_cam_from_pose(pos, R_world_body_from_euler(0, 0, yaw), pitch, 0.0)
        truth.append(Tc)
        hdr = lambda t, s=f"drone_{i}": Header(schema_version=1, sender_id=s, t_measurement_ns=int(t), t_sent_ns=int(t))  # noqa: E731
        with Recorder.new_sortie(tmp_path, f"drone_{i}") as rec:
            rec.record_message("camera_info", CameraInfo(header=hdr(t_ns[0]), camera_id="cam0", width_px=1280, height_px=720,
                               fx_px=1200.0, fy_px=1200.0, cx_px=640.0, cy_px=360.0, gimbal_pitch_rad=float(pitch)))  # fmt: skip
            for t in np.arange(t_ns[0], t_ns[-1] + 1, 20_000_000):
                w = np.cos(yaw / 2)
                rec.record_message("state", VehicleState(header=hdr(t), position_ned_m=tuple(map(float, pos)), velocity_ned_m_s=(0.0, 0.0, 0.0),
                                   q_world_body=(float(w), 0.0, 0.0, float(np.sin(yaw / 2))), position_cov_m2=(0.01, 0.01, 0.01)))  # fmt: skip
            for f, t in enumerate(t_ns):
                uv, _ = project_points(K, Tc, J[f])
                pk = PersonKeypoints(keypoints_px=tuple(map(float, uv.reshape(-1))), confidence=tuple([0.9] * 17))
                rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(t), camera_id="cam0", frame_index=int(f), detector="sim",
                                   simulated=True, persons=[pk]))  # fmt: skip
    return truth, K


def test_flight_reader_and_reconstruct_cli(tmp_path):
    pytest.importorskip("mcap")
    from reconstruction.multiview.flight import read_flight
    from apps.cli import main

    J, t_ns, *_ = procedural_walker(24)
    truth, K = _write_flight(tmp_path, J, t_ns)
    cap = read_flight(tmp_path)
    assert cap.num_cameras == 3
    for c, Tt in zip(cap.cameras, truth):
        np.testing.assert_allclose(c.T_world_cam[0], Tt, atol=1e-9)
        np.testing.assert_allclose(c.K[0], K)
        np.testing.assert_array_equal(c.t_frame_ns, t_ns)
        uv, _ = project_points(K, Tt, J[3])
        np.testing.assert_allclose(c.keypoints_px[3, 0], uv, atol=1e-6)
    out = tmp_path / "rec"
    assert main(["reconstruct", str(tmp_path), "--method", "multiview", "--mv-out", str(out)]) == 0
    z = np.load(out / "motion.npz")
    assert z["joints_ned"].shape[1:] == (17, 3)
    for ext in ("bvh", "csv", "rrd"):
        assert (out / f"motion.{ext}").stat().st_size > 0
    # the reconstruction sits on the walker (no noise here)
    from reconstruction.synth import interpolate_joints

    gt = interpolate_joints(t_ns, J, z["t_ns"])
    assert w_mpjpe_mm(z["joints_ned"], gt, SCORED_JOINTS) < 40.0


def test_eval_multiview_cli(tmp_path, cmu_dir):
    from apps.cli import main

    out = tmp_path / "ev"
    rc = main(["eval", "multiview", "--motion", str(cmu_dir / "002" / "002_01.bvh"), "--out", str(out), "--frames", "24",
               "--set", "fit.iters=120"])  # fmt: skip
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    for k in ("mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm", "root_err_mm", "per_group_mm", "keypoints_source",
              "position_grade", "per_joint", "camera_pos_err_m_before", "camera_pos_err_m_after",
              "camera_rot_err_deg_before", "camera_rot_err_deg_after", "frames", "fit_seconds"):  # fmt: skip
        assert k in m
    assert m["frames"] == 24 and set(m["per_joint"]) == {"shoulder", "elbow", "wrist", "hip", "knee", "ankle", "head"}
    assert "root_aligned_mpjpe_mm" not in m and set(m["per_group_mm"]) == {"torso", "arms", "legs", "head"}
    assert m["pa_mpjpe_mm"] < 80 and m["camera_pos_err_m_after"] < m["camera_pos_err_m_before"]
    assert (out / "config.toml").is_file() and (out / "reconstruction.bvh").is_file()

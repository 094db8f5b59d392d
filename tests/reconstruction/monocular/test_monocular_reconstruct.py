"""The monocular method (``reconstruction.monocular.reconstruct.run``): one drone's synthetic capture -> world-frame motion written by the shared exporters."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reconstruction.capture import CaptureError
from reconstruction.metrics import pa_mpjpe_mm
from reconstruction.monocular.reconstruct import MonocularRunConfig, run
from reconstruction.synth import SynthConfig, interpolate_joints, synthesize_capture
from skycap.bvh import read_bvh
from skycap.skeleton import mocap_to_coco17


@pytest.mark.shared_data
def test_run_writes_world_motion(cmu_dir, tmp_path):
    m = read_bvh(cmu_dir / "002" / "002_05.bvh").slice(1, 1 + 4 * 120, 1)
    J = mocap_to_coco17(m)
    t_ns = (np.arange(len(J)) * m.frame_time_s * 1e9).astype(np.int64)
    sc = SynthConfig(drones=1, radius_m=4.0, altitude_m=2.0, speed_mps=np.radians(25) * 4.0, camera_rate_hz=24,
                     camera_pos_noise_m=0.0, camera_rot_noise_deg=1.0, swap_rate=0.0)  # fmt: skip
    cap, truth = synthesize_capture(J, t_ns, sc, seed=1)
    out = tmp_path / "rec"
    summary = run(cap, MonocularRunConfig(rrd=False), out_dir=out).summary
    for k in ("bvh", "npz", "csv"):
        assert (out / f"motion.{k}").is_file()
    assert json.loads((out / "summary.json").read_text())["frames"] == cap.cameras[0].num_frames
    assert (out / "config.toml").is_file()
    z = np.load(out / "motion.npz")
    joints = z["joints_ned"]
    gt = interpolate_joints(truth.t_ns, truth.joints_ned, cap.cameras[0].t_frame_ns)
    assert joints.shape == gt.shape
    # shape up to similarity, and the placement in the world: centre within 0.5 m, upright (head above ankles)
    assert pa_mpjpe_mm(joints, gt, joints=range(5, 17)) < 80.0
    assert np.median(np.linalg.norm(joints.mean(1) - gt.mean(1), axis=-1)) < 0.5
    assert np.all(np.median(joints[:, 0, 2] - joints[:, 15:17, 2].mean(-1)) < -1.0)
    assert summary["variant"] == "perspective"


def test_run_rejects_unknown_camera(tmp_path):
    t = np.arange(30) * 33_000_000
    J = np.zeros((30, 17, 3))
    J[:, :, 2] = -np.linspace(0.1, 1.7, 17)
    J[:, :, 1] = np.linspace(-0.2, 0.2, 17)
    cap, _ = synthesize_capture(J, t, SynthConfig(drones=1), seed=0)
    with pytest.raises(CaptureError, match="not in the capture"):
        run(cap, MonocularRunConfig(camera="drone_7"), out_dir=tmp_path / "o")


def _write_orbit_flight(tmp_path, J, t_ns, radius_m=4.0, omega_deg_s=40.0, noise_px=2.0):
    """One drone orbiting the person, recorded with the real flight recorder (MCAP): state, camera_info
    (gimbal pitch aimed at the hips) and noisy simulated keypoints."""
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, Header, Keypoints2D, PersonKeypoints, VehicleState
    from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose, intrinsics_matrix, project_points

    rng = np.random.default_rng(3)
    K = intrinsics_matrix(1200.0, 1200.0, 640.0, 360.0)
    centre = J[:, 11:13].mean(1)  # (T, 3) hips
    hdr = lambda t: Header(schema_version=1, sender_id="drone_0", t_measurement_ns=int(t), t_sent_ns=int(t))  # noqa: E731
    t_s = (t_ns - t_ns[0]) * 1e-9
    ang = np.radians(omega_deg_s) * t_s
    pos = np.stack([centre[:, 0] + radius_m * np.cos(ang), centre[:, 1] + radius_m * np.sin(ang), np.full(len(t_s), -2.5)], 1)
    with Recorder.new_sortie(tmp_path, "drone_0") as rec:
        for f, t in enumerate(t_ns):
            d = centre[f] - pos[f]
            yaw = float(np.arctan2(d[1], d[0]))
            pitch = float(-np.arctan2(-d[2], np.hypot(d[0], d[1])))
            rec.record_message("camera_info", CameraInfo(header=hdr(t), camera_id="cam0", width_px=1280, height_px=720,
                               fx_px=1200.0, fy_px=1200.0, cx_px=640.0, cy_px=360.0, gimbal_pitch_rad=pitch))  # fmt: skip
            rec.record_message("state", VehicleState(header=hdr(t), position_ned_m=tuple(map(float, pos[f])),
                               velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))),
                               position_cov_m2=(0.01, 0.01, 0.01)))  # fmt: skip
            Tc = T_world_cam_from_pose(pos[f], R_world_body_from_euler(0, 0, yaw), pitch, 0.0)
            uv, _ = project_points(K, Tc, J[f])
            uv = uv + rng.normal(0, noise_px, uv.shape)
            pk = PersonKeypoints(keypoints_px=tuple(map(float, uv.reshape(-1))), confidence=tuple([0.9] * 17))
            rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(t), camera_id="cam0", frame_index=int(f), detector="sim",
                               simulated=True, persons=[pk]))  # fmt: skip


def test_reconstruct_cli_on_a_recorded_single_drone_flight(tmp_path):
    pytest.importorskip("mcap")
    from reconstruction.synth import procedural_walker
    from apps.cli import main

    J, t_ns, *_ = procedural_walker(96, fps=24.0)
    _write_orbit_flight(tmp_path, J, t_ns)
    out = tmp_path / "rec"
    assert main(["reconstruct", str(tmp_path), "--method", "monocular", "--mono-out", str(out)]) == 0
    z = np.load(out / "motion.npz")
    for ext in ("bvh", "csv", "rrd"):
        assert (out / f"motion.{ext}").stat().st_size > 0
    gt = interpolate_joints(t_ns, J, z["t_ns"])
    assert z["joints_ned"].shape == gt.shape
    # a 4 s walk is the hard case of the monocular method (depth flips of the legs; see RESULTS.md):
    # this checks the plumbing (frames, cameras, placement), the accuracy is measured on CMU clips
    assert pa_mpjpe_mm(z["joints_ned"], gt, joints=range(5, 17)) < 200.0
    # placed in the world near the walker (metric scale assumed from the dictionary's mean body size)
    assert np.median(np.linalg.norm(z["joints_ned"].mean(1) - gt.mean(1), axis=-1)) < 1.2
    assert np.median(z["joints_ned"][:, 0, 2] - z["joints_ned"][:, 15:17, 2].mean(-1)) < -1.0  # upright
    s = json.loads((out / "summary.json").read_text())
    assert s["method"] == "monocular"
    assert s["sortie"] is None and s["recordings"] == {"drone_0": ["drone_0.s001.mcap"]}


def test_run_directly_reports_progress(tmp_path):
    from reconstruction.monocular.pipeline import ModelFitConfig, MonocularConfig
    from reconstruction.monocular.reconstruct import MonocularRunResult
    from reconstruction.synth import procedural_walker

    J, t_ns, *_ = procedural_walker(48, fps=24.0)
    cap, _ = synthesize_capture(J, t_ns, SynthConfig(drones=1, radius_m=4.0, altitude_m=2.0, camera_rate_hz=24), seed=0)
    # a quick pipeline: the paper's BA only (the plumbing is under test here, not the accuracy)
    pipe = MonocularConfig(ablation_no_articulation=False, ablation_paper_order=False, model=ModelFitConfig(enabled=False))
    calls = []
    res = run(cap, MonocularRunConfig(variant="paper", pipeline=pipe, rrd=False), progress=lambda *a: calls.append(a))
    assert isinstance(res, MonocularRunResult) and res.out_dir is None and res.outputs == {}
    assert calls == [("monocular", 0, 1), ("monocular", 1, 1)]
    assert res.joints_ned.shape == (len(res.t_ns), 17, 3) and res.summary["frames"] == len(res.t_ns)
    assert res.camera == cap.cameras[0].name and "recordings" not in res.summary  # not read from a flight
    calls.clear()
    res = run(cap, MonocularRunConfig(variant="paper", pipeline=pipe, rrd=False), out_dir=tmp_path / "o",
              progress=lambda *a: calls.append(a))
    assert calls[-2:] == [("export", 0, 1), ("export", 1, 1)]
    assert set(res.outputs) == {"bvh", "trc", "npz", "csv"} and all(p.is_file() for p in res.outputs.values())
    assert json.loads((tmp_path / "o" / "summary.json").read_text()) == res.summary

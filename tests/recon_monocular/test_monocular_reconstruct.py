"""``reconstruct_capture``: one drone's synthetic capture -> world-frame motion written by the shared exporters."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reconstruction.capture import CaptureError
from reconstruction.metrics import pa_mpjpe_mm
from reconstruction.monocular.reconstruct import reconstruct_capture
from reconstruction.synth import SynthConfig, interpolate_joints, synthesize_capture
from skycap.bvh import read_bvh
from skycap.skeleton import mocap_to_coco17


@pytest.mark.shared_data
def test_reconstruct_capture_writes_world_motion(cmu_dir, tmp_path):
    m = read_bvh(cmu_dir / "002" / "002_05.bvh").slice(1, 1 + 4 * 120, 1)
    J = mocap_to_coco17(m)
    t_ns = (np.arange(len(J)) * m.frame_time_s * 1e9).astype(np.int64)
    sc = SynthConfig(drones=1, radius_m=4.0, altitude_m=2.0, speed_mps=np.radians(25) * 4.0, camera_rate_hz=24,
                     camera_pos_noise_m=0.0, camera_rot_noise_deg=1.0, swap_rate=0.0)  # fmt: skip
    cap, truth = synthesize_capture(J, t_ns, sc, seed=1)
    out = tmp_path / "rec"
    summary = reconstruct_capture(cap, out, rrd=False)
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
    assert summary["variant"] == "extended"


def test_reconstruct_capture_rejects_unknown_camera(tmp_path):
    t = np.arange(30) * 33_000_000
    J = np.zeros((30, 17, 3))
    J[:, :, 2] = -np.linspace(0.1, 1.7, 17)
    J[:, :, 1] = np.linspace(-0.2, 0.2, 17)
    cap, _ = synthesize_capture(J, t, SynthConfig(drones=1), seed=0)
    with pytest.raises(CaptureError, match="not in the capture"):
        reconstruct_capture(cap, tmp_path / "o", camera="drone_7")

"""Capture contract, synthetic captures, and the shared writers (BVH round trip via bvhio)."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.capture import Capture, CaptureError, CameraCapture
from reconstruction.export import BVH_JOINT_FOR_COCO, export_motion, write_joints_bvh
from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture
from skycap.frames import project_points, yup_to_ned


def _walker(T: int = 40):
    J, t_ns, shape, *_ = procedural_walker(T)
    return J, t_ns, shape


def test_synthetic_capture_projects_truth_and_roundtrips(tmp_path):
    J, t_ns, _ = _walker()
    cfg = SynthConfig(noise_px=0.0, outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0, camera_pos_noise_m=0.3)
    cap, truth = synthesize_capture(J, t_ns, cfg, seed=1)
    assert cap.num_cameras == 3
    c = cap.cameras[1]
    # noiseless keypoints are the projection of the interpolated truth with the TRUE pose
    from reconstruction.synth import interpolate_joints

    X = interpolate_joints(t_ns, J, c.t_frame_ns[5:6])[0]
    uv, _ = project_points(c.K[0], truth.T_world_cam_true_frames[1][5], X)
    np.testing.assert_allclose(c.keypoints_px[5, 0], uv, atol=1e-6)
    # unsynchronised: the cameras' frame times differ
    assert not np.array_equal(cap.cameras[0].t_frame_ns[:5], cap.cameras[1].t_frame_ns[:5])
    # drone pose estimates are off by roughly the configured noise
    err = np.linalg.norm(c.T_world_cam[:, :3, 3] - truth.T_world_cam_true[1][:, :3, 3], axis=-1)
    assert 0.01 < err.mean() < 1.5
    cap2 = Capture.load(cap.save(tmp_path / "cap.npz"))
    np.testing.assert_array_equal(cap2.cameras[2].keypoints_px, cap.cameras[2].keypoints_px)
    assert cap2.cameras[0].detectors == cap.cameras[0].detectors


def test_capture_rejects_bad_shapes():
    with pytest.raises(CaptureError, match="keypoints_px"):
        CameraCapture("a", [0], np.eye(4)[None], 0.1, 1.0, [0], np.eye(3), 640, 480, [0, 1], np.zeros((2, 1, 15, 2)), np.zeros((2, 1, 17)))


def test_bvh_roundtrip_independent_reader(tmp_path):
    bvhio = pytest.importorskip("bvhio")
    J, t_ns, shape = _walker()
    path, err = write_joints_bvh(tmp_path / "m.bvh", J, 1 / 30, shape)  # metres
    assert err < 1e-6
    root = bvhio.readAsHierarchy(str(path))
    joints = {j.Name: j for j, _, _ in root.layout()}
    for f in (0, 17, len(J) - 1):
        root.loadPose(f)
        P = np.array([list(joints[n].PositionWorld) for n in BVH_JOINT_FOR_COCO])
        assert np.abs(yup_to_ned(P) - J[f]).max() < 1e-3


def test_export_motion_writes_all(tmp_path):
    J, t_ns, shape = _walker(10)
    paths = export_motion(tmp_path, J, t_ns, params={"shape": shape}, shape=shape)
    assert set(paths) == {"bvh", "trc", "npz", "csv", "rrd"}
    z = np.load(paths["npz"])
    np.testing.assert_allclose(z["joints_ned"], J)
    csv = np.loadtxt(paths["csv"], delimiter=",", skiprows=1)
    assert csv.shape == (10, 1 + 51)
    np.testing.assert_allclose(csv[:, 1:4], J[:, 0], atol=1e-6)
    assert paths["rrd"].stat().st_size > 1000
